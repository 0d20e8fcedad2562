"""A client of Foxglove's WebSocket protocol for the tests, and decoders of what it receives.

The protocol (github.com/foxglove/ws-protocol, docs/spec.md): subprotocol
``foxglove.websocket.v1`` (the foxglove-sdk also speaks it as ``foxglove.sdk.v1``, the name it
prefers); the server sends JSON ``serverInfo`` and ``advertise`` (channels: id, topic,
encoding, schemaName, schema, schemaEncoding); the client sends ``subscribe`` with
(subscription id, channel id) pairs; the server sends binary messages: opcode 0x01, uint32
subscription id, uint64 log time (ns), then the payload, all little endian.

Payloads are decoded from the schema the server advertised: CDR with mcap_ros2's decoder of
the ros2msg text; protobuf with the small wire-format decoder below, driven by the
FileDescriptorSet the server sends (base64) — no generated code, no protobuf package.
"""

from __future__ import annotations

import base64
import json
import socket
import struct
import time
from dataclasses import dataclass

from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
MESSAGE_DATA = 0x01


@dataclass
class Message:
    topic: str
    log_time: int
    payload: bytes


class FoxgloveClient:
    """A client on ``websockets``' synchronous API (it reads the socket in a thread of its own:
    a client that keeps up)."""

    def __init__(self, port: int, timeout: float = 10.0) -> None:
        from websockets.sync.client import connect

        self.ws = connect(
            f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, max_size=None, open_timeout=timeout
        ).__enter__()  # the connection itself (websockets >= 14 returns it from a context)
        self.server_info: dict = {}
        self.channels: dict[int, dict] = {}
        self.subscriptions: dict[int, int] = {}  # subscription id -> channel id
        self.pending: list[Message] = []

    def close(self) -> None:
        self.ws.close()

    def _handle(self, frame) -> Message | None:
        if isinstance(frame, str):
            op = json.loads(frame)
            if op["op"] == "serverInfo":
                self.server_info = op
            elif op["op"] == "advertise":
                self.channels.update({c["id"]: c for c in op["channels"]})
            elif op["op"] == "unadvertise":
                for cid in op["channelIds"]:
                    self.channels.pop(cid, None)
            return None
        assert frame[0] == MESSAGE_DATA, f"binary opcode {frame[0]:#x}"
        sub, log_time = struct.unpack_from("<IQ", frame, 1)
        topic = self.channels[self.subscriptions[sub]]["topic"]
        return Message(topic, log_time, bytes(frame[13:]))

    def wait_for_topics(self, topics: set[str], timeout: float = 10.0) -> None:
        """Read until every topic of ``topics`` is advertised."""
        deadline = time.monotonic() + timeout
        while not topics <= {c["topic"] for c in self.channels.values()}:
            msg = self._handle(self.ws.recv(timeout=max(0.01, deadline - time.monotonic())))
            if msg is not None:
                self.pending.append(msg)

    def subscribe(self, topics: set[str]) -> None:
        subs = []
        for cid, ch in self.channels.items():
            if ch["topic"] in topics:
                sid = len(self.subscriptions) + 1
                self.subscriptions[sid] = cid
                subs.append({"id": sid, "channelId": cid})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def receive(self, until, timeout: float = 15.0) -> list[Message]:
        """Messages until ``until(messages)`` holds (or the timeout ends: AssertionError)."""
        got, self.pending = self.pending, []
        deadline = time.monotonic() + timeout
        while not until(got):
            left = deadline - time.monotonic()
            assert left > 0, (
                f"timed out with {len(got)} messages on {sorted({m.topic for m in got})}"
            )
            msg = self._handle(self.ws.recv(timeout=left))
            if msg is not None:
                got.append(msg)
        return got

    def decoder(self, topic: str):
        """payload -> decoded message, from the channel's advertised schema."""
        ch = next(c for c in self.channels.values() if c["topic"] == topic)
        return payload_decoder(
            ch["encoding"], ch["schemaName"], ch["schemaEncoding"], schema_bytes(ch)
        )


def schema_bytes(channel: dict) -> bytes:
    """The advertised schema: base64 for a binary (protobuf) one, text otherwise."""
    if channel["schemaEncoding"] == "protobuf":
        return base64.b64decode(channel["schema"])
    return channel["schema"].encode()


def payload_decoder(encoding: str, name: str, schema_encoding: str, schema: bytes):
    if encoding == "cdr":
        return DecoderFactory().decoder_for(
            "cdr", Schema(id=0, name=name, encoding=schema_encoding, data=schema)
        )
    assert encoding == "protobuf" and schema_encoding == "protobuf", (encoding, schema_encoding)
    messages = descriptor_messages(schema)
    return lambda payload: decode_protobuf(messages, "." + name, payload)


class SlowClient:
    """A raw client that subscribes and then never reads: its socket's small receive buffer
    fills and stays full, as with a client on a slow link."""

    def __init__(self, port: int, rcvbuf: int = 4096) -> None:
        self.sock = socket.socket()
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.settimeout(10.0)
        self.sock.connect(("127.0.0.1", port))
        key = base64.b64encode(b"teleop-rt-tests!").decode()
        self.sock.sendall(
            (
                f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
                f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                f"Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: {SUBPROTOCOLS[0]}\r\n\r\n"
            ).encode()
        )
        self.buf = b""
        while b"\r\n\r\n" not in self.buf:
            self.buf += self.sock.recv(1)  # byte by byte: nothing past the headers is taken
        assert self.buf.startswith(b"HTTP/1.1 101"), self.buf
        self.buf = b""
        self.channels: dict[int, dict] = {}

    def _frame(self) -> tuple[int, bytes]:
        def take(n: int) -> bytes:
            while len(self.buf) < n:
                more = self.sock.recv(65536)
                if not more:
                    raise ConnectionError("the server closed the connection")
                self.buf += more
            out, self.buf = self.buf[:n], self.buf[n:]
            return out

        b0, b1 = take(2)
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack(">H", take(2))[0]
        elif n == 127:
            n = struct.unpack(">Q", take(8))[0]
        return b0 & 0x0F, take(n)

    def subscribe_all(self, topics: set[str]) -> None:
        while not topics <= {c["topic"] for c in self.channels.values()}:
            opcode, data = self._frame()
            if opcode == 1:
                op = json.loads(data)
                if op["op"] == "advertise":
                    self.channels.update({c["id"]: c for c in op["channels"]})
        subs = [{"id": i + 1, "channelId": cid} for i, cid in enumerate(self.channels)]
        self._send_text(json.dumps({"op": "subscribe", "subscriptions": subs}).encode())

    def _send_text(self, data: bytes) -> None:
        mask = b"\x01\x02\x03\x04"
        head = bytes([0x81])
        n = len(data)
        if n < 126:
            head += bytes([0x80 | n])
        elif n < 65536:
            head += bytes([0x80 | 126]) + struct.pack(">H", n)
        else:
            head += bytes([0x80 | 127]) + struct.pack(">Q", n)
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))

    def drain(self, topic: str, quiet_s: float = 2.0) -> list[bytes]:
        """Read everything left (after the session): the payloads of ``topic`` that reached
        us, in order."""
        ids = {i + 1: c["topic"] for i, c in enumerate(self.channels.values())}
        out = []
        self.sock.settimeout(quiet_s)
        try:
            while True:
                opcode, data = self._frame()
                if opcode == 2 and data[0] == MESSAGE_DATA:
                    if ids.get(struct.unpack_from("<I", data, 1)[0]) == topic:
                        out.append(data[13:])
                elif opcode == 8:  # close
                    break
        except (TimeoutError, ConnectionError, ValueError):
            pass
        return out

    def close(self) -> None:
        self.sock.close()


# --- protobuf, from the wire format and descriptor.proto's field numbers -------------------------
def _fields(buf: bytes):
    """(field number, wire type, value) of a protobuf message."""
    at = 0
    while at < len(buf):
        key, at = _varint(buf, at)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, at = _varint(buf, at)
        elif wire == 1:
            value, at = buf[at : at + 8], at + 8
        elif wire == 2:
            n, at = _varint(buf, at)
            value, at = buf[at : at + n], at + n
        elif wire == 5:
            value, at = buf[at : at + 4], at + 4
        else:
            raise ValueError(f"wire type {wire}")
        yield number, wire, value


def _varint(buf: bytes, at: int) -> tuple[int, int]:
    out = shift = 0
    while True:
        b = buf[at]
        at += 1
        out |= (b & 0x7F) << shift
        shift += 7
        if not b & 0x80:
            return out, at


def descriptor_messages(file_descriptor_set: bytes) -> dict[str, dict[int, tuple]]:
    """Full message name ('.foxglove.Vector3') -> field number -> (name, type, type name,
    repeated), from a FileDescriptorSet (file = 1; package = 2, message_type = 4; a message's
    name = 1, field = 2, nested_type = 3; a field's name = 1, number = 3, label = 4, type = 5,
    type_name = 6)."""
    out: dict[str, dict[int, tuple]] = {}

    def message(body: bytes, scope: str) -> None:
        name, fields, nested = "", {}, []
        for number, _, value in _fields(body):
            if number == 1:
                name = value.decode()
            elif number == 2:
                f = {n: v for n, _, v in _fields(value)}
                fields[f[3]] = (f[1].decode(), f[5], f.get(6, b"").decode(), f.get(4) == 3)
            elif number == 3:
                nested.append(value)
        full = f"{scope}.{name}"
        out[full] = fields
        for body in nested:
            message(body, full)

    for number, _, file in _fields(file_descriptor_set):
        if number != 1:
            continue
        parts = list(_fields(file))
        package = next((v.decode() for n, _, v in parts if n == 2), "")
        for n, _, body in parts:
            if n == 4:
                message(body, f".{package}" if package else "")
    return out


_SCALAR = {1: "<d", 2: "<f", 6: "<Q", 7: "<I", 15: "<i", 16: "<q"}  # fixed-width types


def decode_protobuf(messages: dict, name: str, payload: bytes) -> dict:
    """A message as a dict (repeated fields as lists; unset fields absent)."""
    spec = messages[name]
    out: dict = {}
    for number, wire, value in _fields(payload):
        if number not in spec:
            continue
        fname, ftype, tname, repeated = spec[number]
        if ftype == 11:
            values = [decode_protobuf(messages, tname, value)]
        elif ftype == 9:
            values = [value.decode()]
        elif ftype == 12:
            values = [bytes(value)]
        elif wire == 2:  # packed repeated scalars
            if ftype in _SCALAR:
                size = struct.calcsize(_SCALAR[ftype])
                values = [
                    struct.unpack(_SCALAR[ftype], value[i : i + size])[0]
                    for i in range(0, len(value), size)
                ]
            else:
                values, at = [], 0
                while at < len(value):
                    v, at = _varint(value, at)
                    values.append(v)
        elif ftype in _SCALAR:
            values = [struct.unpack(_SCALAR[ftype], value)[0]]
        else:
            values = [bool(value) if ftype == 8 else value]
        if repeated:
            out.setdefault(fname, []).extend(values)
        else:
            out[fname] = values[-1]
    return out
