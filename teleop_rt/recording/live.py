"""The live view: the log writer process serves the session over Foxglove's WebSocket protocol
(the foxglove-sdk's server, ``foxglove.websocket.v1``), the same messages it writes to the log.

Off the tick path by construction: the server lives in the writer process, fed from the rows
the recorder's ring already carries, so the control loop pays nothing for it. It does not hold
the writer either: a message is put on each subscribed client's queue (``BACKLOG`` messages)
and sent by the SDK's own threads; a client that reads too slowly loses the oldest messages
of its queue, never stalls the writer (``tests/test_live.py`` runs a client that never reads).

A client that subscribes to ``/robot_description``, ``/tf`` or ``/environment`` gets what is
otherwise sent once or on change (the URDF, the transforms that never move, the environment)
at once: the writer sends it again.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

from teleop_rt.errors import ConfigError

DEFAULT_HOST, DEFAULT_PORT = "127.0.0.1", 8765
BACKLOG = 1024  # messages queued per client (the SDK's default); the oldest go first
SERVER_NAME = "teleop-rt"
STOP_WAIT_S = 1.0  # how long the writer waits for the server's connections to close


@dataclass(frozen=True)
class LiveAddress:
    host: str
    port: int  # 0: any free port (the one taken is reported)

    def __str__(self) -> str:
        return f"{self.host}:{self.port}"


def parse_address(text: str) -> LiveAddress:
    """``[HOST:]PORT`` (``8765``, ``127.0.0.1:8765``, ``0.0.0.0:9000``; port 0: any free one)."""
    host, sep, port = text.rpartition(":")
    host = host.strip("[]") if sep else DEFAULT_HOST
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ConfigError(f"--live {text}: expected [HOST:]PORT with a port 0..65535")
    if sep and not host:
        raise ConfigError(f"--live {text}: the host before ':' is empty")
    return LiveAddress(host, int(port))


class LiveServer:
    """The WebSocket server on the writer's context; ``resend`` is set when a client
    subscribes to a topic logged only once (the writer logs it again and clears it)."""

    def __init__(self, address: LiveAddress, context, once_topics: set[str]) -> None:
        import foxglove

        self.resend = threading.Event()
        listener = _listener(self.resend, once_topics)
        self.server = foxglove.start_server(
            name=SERVER_NAME,
            host=address.host,
            port=address.port,
            context=context,
            server_listener=listener,
            message_backlog_size=BACKLOG,
        )
        self.address = LiveAddress(address.host, self.server.port)

    def stop(self) -> None:
        """Bounded: the SDK closes each connection gracefully, which a client that does not
        read never completes; the writer's process ends regardless (its threads with it)."""
        closing = threading.Thread(target=self.server.stop, daemon=True)
        closing.start()
        closing.join(STOP_WAIT_S)


def _listener(resend: threading.Event, once_topics: set[str]):
    """A foxglove ``ServerListener`` (imported here: the CLI parses --live without the SDK).

    Subclassed, not duck-typed: the SDK calls every callback the protocol declares (an
    ``on_unsubscribe`` per channel when a client unsubscribes or disconnects, the client
    channel and parameter callbacks, ...), and a missing one is a "Callback failed:
    AttributeError" line on stderr per call; the protocol's defaults do nothing. Called on the
    SDK's threads, so it only sets a flag."""
    from foxglove.websocket import ServerListener

    class Listener(ServerListener):
        def on_subscribe(self, client, channel) -> None:
            if channel.topic in once_topics:
                resend.set()

        def on_unsubscribe(self, client, channel) -> None:
            pass  # what is sent once goes again to whoever subscribes next (on_subscribe)

    return Listener()
