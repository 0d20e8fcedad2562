"""The packet on the network: one fixed little-endian layout, encoded without allocation and
decoded defensively.

Layout (n joints; 72 + 56 n bytes, every field 8-byte aligned)::

    offset      type     field
    0           u32      magic b"TRWV"
    4           u8       version (5)
    5           u8       the sender's side: 0 the HSI, 1 the TO
    6           u16      n, the joint count
    8           u64      session id (both sites' handshake agrees on it)
    16          u64      sequence number
    24          i64      the sender's tick
    32          i64      the sender's time, ns, CLOCK_MONOTONIC (``time.monotonic_ns``): the
                         same clock in every process of one host, so a receiver on the same
                         host measures the one-way delay; across hosts only ticks compare
    40          u64      the packet's number: how many packets the sender had sent before it
                         (its copies share it). With the codec a sender is silent most ticks,
                         so only a jump of this number, not of the sequence (the sender's
                         tick), is a packet lost (``teleop_rt.com.playout``)
    48          f64[n]   x, the sender's port input            \\
                f64[n]   wave, the sender's outgoing wave       |
                f64[n]   its wave integral (dt sum of waves)    |
                f64[n]   its port input's integral              |
                f64[n]   its wave energy sent, J (monotone)     |  ``Packet``'s floats,
                f64[n]   E_in per joint, J (monotone)           |  in its order
                f64[n]   E_out per joint, J (monotone)          |
                f64      energy crossed the sender's port, J    /
    56 + 56 n   u64      engaged: 1 the sender's operator map couples, 0 it is decoupled (the
                         HSI's clutch pressed or its operator away: the TO decouples on it)
    64 + 56 n   u32      CRC-32 (zlib's) of every byte before it
    68 + 56 n   u32      zero

The decoder rejects, and counts by reason, a packet of the wrong size, magic or version, a
corrupted one (CRC), one for another joint count or session, one sent by the receiver's own
side (``side``: its own packets reflected back, or a second site of its role), one holding a
non-finite value or a magnitude beyond the bounds it was given (the integrals within the
energy bound's magnitude; the cumulative wave energy, E_in and E_out also >= 0; ``engaged``
0 or 1; the packet's number in [0, tick], as a sender that sends at most one packet a tick
from tick 0 numbers them: ``implausible``), one whose
sequence number or tick is beyond the newest the receiver can play (``ahead``: the playout's
early horizon; a forged jump of the sequence would otherwise make every genuine packet stale),
and one whose sequence number is not newer than the newest one the receiver has used
(``Decoder.used_seq``, which the receiver sets). It never raises on bad bytes and writes
nothing into the packet it was given unless it accepts.

The CRC and these checks catch corruption, reflection and nonsense, not a forger who writes a
well-formed packet: only TLS (``link.zenoh.tls``) authenticates the peer
(docs/network.md).
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass

import numpy as np

from teleop_rt.com.port import Packet
from teleop_rt.flat import compiled_for, int_view, jit

if sys.byteorder != "little":  # the layout is read through native views
    raise ImportError("teleop_rt.com.wire needs a little-endian host")

MAGIC = int.from_bytes(b"TRWV", "little")
# 2: the integrals, wave energy and E_in/E_out per joint; 3: the sender's side; 4: engaged;
# 5: the packet's number (a codec's silence is no loss: only a jump of the number is)
VERSION = 5
NO_LIMIT = (1 << 63) - 1  # ``decode``'s newest tick when the caller bounds nothing
HEADER_WORDS = 6  # magic/version/n, session, seq, tick, time, number
W_ID, W_SESSION, W_SEQ, W_TICK, W_TIME, W_NUMBER = range(HEADER_WORDS)
# the Packet's vectors, then its one scalar; the decoder's checks rely on the cumulative
# energies (wave energy, E_in, E_out) being its last vectors
assert len(Packet.SCALARS) == 1
assert Packet.idx.E_OUT == Packet.idx.N_VECTORS - 1 == Packet.idx.WAVE_ENERGY + 2
ID_MASK = (1 << 40) - 1  # magic and version: the low 40 bits of word 0 (then side, n)

# decode's status codes, each also the index of its counter
(OK, SIZE, MAGIC_VERSION, CHECKSUM, JOINTS, SESSION, SIDE, NON_FINITE, IMPLAUSIBLE, AHEAD,
 STALE) = range(11)  # fmt: skip
REASONS = ("ok", "size", "magic_version", "checksum", "joints", "session", "side", "non_finite",
           "implausible", "ahead", "stale")  # fmt: skip
# the decoder's state (NUMBER: the last accepted packet's number), then its counters
USED_SEQ, SENDER_TIME, SEEN_TICK, NUMBER, COUNTS = range(5)


def wire_size(n: int) -> int:
    """Bytes of a packet of ``n`` joints."""
    Pk = Packet.idx
    return 8 * (HEADER_WORDS + Pk.N_VECTORS * n + 1 + 1 + 1)  # floats, engaged, CRC


def _as_i64(value: int) -> int:
    """A u64 field's value as the int64 with the same bits (what the kernels compare)."""
    if not 0 <= value < 1 << 64:
        raise ValueError(f"{value} is not an unsigned 64-bit number")
    return value - (1 << 64) if value >= 1 << 63 else value


def _crc_table() -> np.ndarray:
    table = np.zeros(256, dtype=np.int64)
    for b in range(256):
        c = b
        for _ in range(8):
            c = (c >> 1) ^ 0xEDB88320 if c & 1 else c >> 1
        table[b] = c
    return table


CRC_TABLE = _crc_table()


@jit
def crc32(u8: np.ndarray, length: int) -> int:
    """zlib's CRC-32 of the first ``length`` bytes."""
    c = 0xFFFFFFFF
    for k in range(length):
        c = CRC_TABLE[(c ^ u8[k]) & 0xFF] ^ (c >> 8)
    return c ^ 0xFFFFFFFF


class WireBuffer:
    """One packet's bytes, preallocated as 8-byte words (the kernels view them as floats and
    bytes); ``data`` is what goes on the network (a memoryview of exactly one packet).
    ``sends``: the buffer is encoded into (``encode_into``); a decoder's (False) only holds
    what arrived, and binds no encoder."""

    def __init__(self, n: int, sends: bool = True) -> None:
        self.n, self.size = n, wire_size(n)
        self.words = np.zeros(self.size // 8, dtype=np.int64)
        self.data = int_view(self.words.view(np.uint8))
        self._encode = _receive_only
        if sends:
            # ``encode_into``'s compiled entry point (no dispatcher typing three arrays a
            # packet), bound here, before any tick: a process that only decodes would
            # otherwise load (or compile) the encoder for nothing (0.2-0.8 s here, by load)
            probe = Packet(n)
            self._encode = compiled_for(_encode, self.words, n, probe.f, probe.i, 0, 0, 0, 0)


def _receive_only(*args: object) -> None:
    raise ValueError("encode_into: this wire buffer is a decoder's (WireBuffer(n, sends=False))")


def encode_into(
    buffer: WireBuffer,
    packet: Packet,
    session_id: int,
    time_ns: int,
    side: int,
    number: int | None = None,
) -> memoryview:
    """``packet`` (its tick and seq as they are) of the site on ``side`` (0 HSI, 1 TO) into
    ``buffer``; returns ``buffer.data``. ``number``: how many packets the sender sent before
    this one (None: the packet's tick, what a sender that sends every tick from tick 0 has
    sent). No allocation (session_id and time_ns below 2**63 pass as they are)."""
    n = buffer.n
    if packet.n != n:
        raise ValueError(f"a {packet.n}-joint packet into a {n}-joint wire buffer")
    if session_id >= 1 << 63:
        session_id = _as_i64(session_id)
    if number is None:
        number = packet.tick
    elif number >= 1 << 63:  # (a test's forged one: the kernel's int64 with the same bits)
        number = _as_i64(number)
    buffer._encode(buffer.words, n, packet.f, packet.i, session_id, time_ns, side, number)
    return buffer.data


@jit
def _encode(
    words: np.ndarray, n: int, pf: np.ndarray, pi: np.ndarray, session: int, time_ns: int,
    side: int, number: int,
) -> None:  # fmt: skip
    Pk = Packet.idx
    floats = words.view(np.float64)  # (fewer array arguments: each costs ~80 ns a call)
    words[W_ID] = MAGIC | (VERSION << 32) | ((side & 0xFF) << 40) | (n << 48)
    words[W_SESSION] = session
    words[W_SEQ] = pi[Pk.SEQ]
    words[W_TICK] = pi[Pk.TICK]
    words[W_TIME] = time_ns
    words[W_NUMBER] = number
    for k in range(Pk.N_VECTORS * n + 1):
        floats[HEADER_WORDS + k] = pf[k]
    last = words.size - 1
    words[last - 1] = pi[Pk.ENGAGED]
    words[last] = crc32(words.view(np.uint8), 8 * last)


@dataclass(frozen=True)
class WireBounds:
    """The largest magnitudes a receiver accepts (a scalar for every joint, or one per joint):
    ``x`` the peer's port input (omega_c in rad/s from the HSI, tau_t in N m from the TO),
    ``wave`` its wave, ``energy`` any of the energies, J (and the integrals)."""

    x: float | list[float] = 1e6
    wave: float | list[float] = 1e6
    energy: float = 1e12

    def array(self, n: int) -> np.ndarray:
        """[x_max (n), wave_max (n), energy_max]."""
        out = np.empty(2 * n + 1)
        for k, (name, value) in enumerate((("x", self.x), ("wave", self.wave))):
            v = np.broadcast_to(np.asarray(value, dtype=np.float64), (n,))
            if not (np.isfinite(v) & (v > 0)).all():
                raise ValueError(f"wire bound {name} must be finite and > 0 for every joint")
            out[k * n : (k + 1) * n] = v
        if not (math.isfinite(self.energy) and self.energy > 0):
            raise ValueError("wire bound energy must be finite and > 0")
        out[2 * n] = self.energy
        return out


class Decoder:
    """The receiving side's defensive decoder for one peer (the site on side ``sender``):
    bounds, counters by reason (indexed by the status codes), the newest used sequence
    number, and the last accepted packet's
    sender time (``sender_time_ns``). ``seen_tick`` is the sender tick of the last
    packet whose header was intact and ours (accepted or stale): what the playout needs to
    count a stale packet as late."""

    def __init__(self, n: int, sender: int, bounds: WireBounds | None = None) -> None:
        if sender not in (0, 1):
            raise ValueError(f"a packet's sender is side 0 (HSI) or 1 (TO), not {sender}")
        self.n, self.size, self.sender = n, wire_size(n), sender
        self.bounds = (bounds or WireBounds()).array(n)
        self._rx = WireBuffer(n, sends=False)  # (what arrived: never encoded into)
        self._rx_data = self._rx.data
        # used_seq, sender_time_ns, seen_tick, then the counters by reason
        self.state = np.zeros(COUNTS + len(REASONS), dtype=np.int64)
        self.state[USED_SEQ] = -1
        self.counts = self.state[COUNTS:]

    @property
    def used_seq(self) -> int:
        """The newest sequence number the receiver has used (-1: none): anything not newer is
        stale."""
        return int(self.state[USED_SEQ])

    @used_seq.setter
    def used_seq(self, seq: int) -> None:
        self.state[USED_SEQ] = seq

    @property
    def sender_time_ns(self) -> int:
        return int(self.state[SENDER_TIME])

    @property
    def seen_tick(self) -> int:
        return int(self.state[SEEN_TICK])

    @property
    def rejected(self) -> int:
        """Packets rejected for any reason."""
        return int(self.counts[1:].sum())

    def counts_by_reason(self) -> dict[str, int]:
        return {name: int(c) for name, c in zip(REASONS, self.counts, strict=True)}

    def load(self, data: bytes | bytearray | memoryview) -> bool:
        """The size rule, the one check made in Python: ``data`` copied into the buffer the
        compiled checks read (``_decode``, ``playout._receive``) if it is one packet's size,
        else counted ``SIZE`` and False (so the kernels never see a wrong size)."""
        if len(data) != self.size:
            self.counts[SIZE] += 1
            return False
        self._rx_data[:] = data
        return True

    def decode(
        self, data: bytes | bytearray | memoryview, expect_session: int, into: Packet,
        newest: int = NO_LIMIT,
    ) -> int:  # fmt: skip
        """``data`` checked and, if accepted, into ``into`` (valid = 1); returns the status
        (``OK`` or the reason it was dropped). ``newest``: the highest sequence number and
        sender tick the receiver can play now (beyond: ``AHEAD``)."""
        if into.n != self.n:
            raise ValueError(f"a {self.n}-joint decoder into a {into.n}-joint packet")
        if not self.load(data):
            return SIZE
        if expect_session >= 1 << 63:
            expect_session = _as_i64(expect_session)
        return _decode(self._rx.words, self.n, expect_session, self.sender, newest, self.bounds,
                       self.state, into.f, into.i)  # fmt: skip


@jit
def _decode(
    words: np.ndarray, n: int, session: int, sender: int, newest: int, bounds: np.ndarray,
    state: np.ndarray, pf: np.ndarray, pi: np.ndarray,
) -> int:  # fmt: skip
    Pk = Packet.idx
    floats = words.view(np.float64)
    status = _check(words, floats, n, session, sender, newest, bounds, state)
    state[COUNTS + status] += 1
    if status == OK:
        for k in range(Pk.N_VECTORS * n + 1):
            pf[k] = floats[HEADER_WORDS + k]
        pi[Pk.TICK] = words[W_TICK]
        pi[Pk.SEQ] = words[W_SEQ]
        pi[Pk.VALID] = 1
        pi[Pk.UNSENT] = 0  # (it arrived: it was sent)
        pi[Pk.ENGAGED] = words[words.size - 2]
        state[SENDER_TIME] = words[W_TIME]
        state[NUMBER] = words[W_NUMBER]
    return status


@jit
def _check(
    words: np.ndarray, floats: np.ndarray, n: int, session: int, sender: int, newest: int,
    bounds: np.ndarray, state: np.ndarray,
) -> int:  # fmt: skip
    Pk = Packet.idx
    w = words[W_ID]
    if (w & ID_MASK) != (MAGIC | (VERSION << 32)):
        return MAGIC_VERSION
    last = words.size - 1
    if words[last] != crc32(words.view(np.uint8), 8 * last):
        return CHECKSUM
    if ((w >> 48) & 0xFFFF) != n:
        return JOINTS
    if words[W_SESSION] != session:
        return SESSION
    if ((w >> 40) & 0xFF) != sender:  # our own packets reflected back, or a second of our role
        return SIDE
    if words[W_SEQ] < 0:  # beyond 2**63: no sender counts that far
        return IMPLAUSIBLE
    # at most one packet a tick from tick 0: a number beyond the tick is forged (and the tick
    # is bounded by ``ahead`` below, so the number is too)
    if words[W_NUMBER] < 0 or words[W_NUMBER] > words[W_TICK]:
        return IMPLAUSIBLE
    m = Pk.N_VECTORS * n
    for k in range(m + 1):
        if not math.isfinite(floats[HEADER_WORDS + k]):
            return NON_FINITE
    for k in range(2 * n):  # x and wave against their bounds
        if abs(floats[HEADER_WORDS + k]) > bounds[k]:
            return IMPLAUSIBLE
    e_max = bounds[2 * n]
    for k in range(n):  # the integrals, and the energy crossed (they may be negative)
        if abs(floats[HEADER_WORDS + Pk.WAVE_SUM * n + k]) > e_max:
            return IMPLAUSIBLE
        if abs(floats[HEADER_WORDS + Pk.X_SUM * n + k]) > e_max:
            return IMPLAUSIBLE
    if abs(floats[HEADER_WORDS + m]) > e_max:
        return IMPLAUSIBLE
    if words[last - 1] != 0 and words[last - 1] != 1:  # engaged: a flag, nothing else
        return IMPLAUSIBLE
    for k in range(Pk.WAVE_ENERGY * n, m):  # cumulative energies: monotone from zero
        e = floats[HEADER_WORDS + k]
        if e < 0.0 or e > e_max:
            return IMPLAUSIBLE
    if words[W_SEQ] > newest or words[W_TICK] > newest:  # beyond what can play yet: a jump
        return AHEAD
    state[SEEN_TICK] = words[W_TICK]  # intact and ours: the playout may count it late
    if words[W_SEQ] <= state[USED_SEQ]:
        return STALE
    return OK
