"""The log format: one fixed-layout row of float64 per tick, split into four MCAP topics.

Encoding: ROS 2 message definitions (``ros2msg``) with CDR payloads (``cdr``). Foxglove decodes
them without plugins, and because every field has a fixed size the payloads of a whole batch of
ticks are one numpy view: the writer encodes thousands of messages with a single ``astype``
instead of one encoder call per message, and the reader decodes a topic the same way.

Topics (n joints, E environment elements; all SI units, joint space). A session whose
robots have their own joint counts (a heterogeneous pair, coupled in the plane) logs each robot
with its own (``joints_hsi``, ``joints_to``) and the channel with its size n (the task's
dimension); one whose sites map their ports (``mapped``: a task-space channel, motion or force
scaling, a clutch) also logs per robot what T_p and T_tau compare (``q_mapped``, ``tau_mapped``,
of size n; ``teleop_rt.mapping``), so that its metrics are the live ones, and each site's
coupling per tick (``MAPPED_STATE``: the gain r, coupled or not, the live inputs read), so that
a live clutch is in the log and replays:

* ``/hsi``       teleop_rt/msg/HsiTick: the HSI robot and the operator
* ``/to``        teleop_rt/msg/ToTick: the TO robot and the environment
* ``/channel``   teleop_rt/msg/ChannelTick: the channel's port variables, waves, energy, and
  each port's balance and the energy its protection removed (``teleop_rt.com.port``)
* ``/timing``    teleop_rt/msg/TimingTick: compute time and deadline lateness of the tick

A site's own log (``teleop-rt site``, ``LogLayout(site="hsi" | "to")``) holds its robot's topic
(``/hsi`` or ``/to``, as above), ``/port`` (teleop_rt/msg/HsiPortTick or ToPortTick: its port's
variables, waves, power and energy under the paper's names, its balance and the energy its
protection removed), ``/link``
(teleop_rt/msg/LinkTick: the peer's packet used at the tick, or none, with the HSI's coupling
state it carried, ``engaged``) and ``/timing``.

A message's log time is wall-clock: UTC at the session start plus the tick's time, in ns since
the epoch (``start_time_ns + k * period_ns``); the field ``t`` is the tick's time from the start.

Besides the messages a log holds (so that it describes itself):
* metadata ``teleop_rt`` at the start: software_version (with the git commit when run from a
  checkout), schema_version, joints (the channel's size), env_elements, rate_hz, period_ns,
  delay_ticks, name, backend, operator ("damper", "hand" or "none"), start_time_ns and
  start_time_utc (ISO 8601), and from the command line config (its path) and overrides (a JSON
  list of the --set values), for a replay replay_of (the replayed log); a mapped session's
  also joints_hsi, joints_to and mapped ("1"), which logs of one joint count without a map
  leave out, and mapping (JSON: the map's constants, and how its sites took the operator's
  live inputs: ``teleop_rt.recording.recorder.mapping_metadata``);
* attachments ``config.yaml`` (the resolved session config) and ``urdf/hsi.urdf``,
  ``urdf/to.urdf`` when the robots came from URDF files;
* in a site's log also log_kind ("site"), site ("hsi" or "to"), session_id (hex, from the
  handshake), config_hash (of what both sites share) and the start time is the instant both
  sites agreed to start at: tick k of either site's log is the same instant;
* metadata ``teleop_rt.summary`` at the end: the live summary as JSON under the key ``json``.
  A log without it was cut short.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from teleop_rt.declarations import LINK_LOG, PORT_LOG, Logged, port_symbol

CDR_HEADER = b"\x00\x01\x00\x00"  # CDR, little endian, no options
# 2: /channel has the ports' balances and the energy the protection removed; 3: a mapped
# layout's robots have MAPPED_STATE, a site's /link the packet's engaged (older logs read as
# they were written: LogLayout.version)
SCHEMA_VERSION = 3


@dataclass(frozen=True)
class Field:
    name: str
    ros_type: str  # "uint64", "int64", "float64", "uint8"
    length: int | None  # None for a scalar, else the size of a fixed array
    doc: str = ""
    # (owner, field) of the block field it logs, where it is declared so (``Logged``)
    source: tuple[str, str] | None = field(default=None, compare=False)

    @property
    def count(self) -> int:
        """Row columns taken by this field."""
        return 1 if self.length is None else self.length

    @property
    def definition(self) -> str:
        size = "" if self.length is None else f"[{self.length}]"
        line = f"{self.ros_type}{size} {self.name}"
        return f"{line}  # {self.doc}" if self.doc else line


_NUMPY = {"uint64": "<u8", "int64": "<i8", "float64": "<f8", "uint8": "u1"}


@dataclass(frozen=True)
class Topic:
    """One topic: its message type and fields, in row order."""

    name: str
    type_name: str
    fields: tuple[Field, ...]

    @property
    def width(self) -> int:
        """Number of float64 columns this topic takes in a row (the tick and time included)."""
        return sum(f.count for f in self.fields)

    @property
    def definition(self) -> bytes:
        return "\n".join(f.definition for f in self.fields).encode() + b"\n"

    @property
    def dtype(self) -> np.dtype:
        """Numpy dtype of one CDR payload (after the 4-byte encapsulation header).

        All 8-byte fields come first, so CDR's natural alignment adds no padding."""
        return np.dtype(
            [
                (f.name, _NUMPY[f.ros_type], () if f.length is None else (f.length,))
                for f in self.fields
            ]
        )


def _common() -> list[Field]:
    return [Field("tick", "uint64", None, "tick number k"), Field("t", "float64", None, "k dt, s")]


def _joint(names: list[str], n: int, doc: str) -> list[Field]:
    return [Field(name, "float64", n, doc) for name in names]


# what T_p and T_tau (eq 18) compare at a mapped site, of the channel's size
MAPPED_FIELDS = (
    ("q_mapped", "position T_p compares: the mapped, indexed q, or the tool's x, y (rad, m)"),
    ("tau_mapped", "what T_tau compares: tau_h or beta tau_e, or the tool's force (N m, N)"),
)

# a mapped site's coupling per tick (schema 3): what a replay needs to reproduce a live
# clutch, and what says when the sites were coupled (name, type, doc)
MAPPED_STATE = (
    ("gain", "float64", "r, the coupling gain: 1 coupled, 0 decoupled, ramping between"),
    ("coupled", "uint8", "1: the clutch released and the operator present (at the TO: as the "
     "HSI's packets say, when it follows them)"),
    ("inputs", "uint8", "the live inputs this tick's map read: 1 clutch pressed, 2 present"),
)

# a robot's per-joint fields: (name, doc, (the site's block, its field))
ROBOT_FIELDS = (
    ("q", "joint angles, rad", ("feedback", "q")),
    ("v", "joint velocities, rad/s", ("feedback", "v")),
    ("tau_ext", "measured torque the outside applies to the robot, N m", ("feedback", "tau_ext")),
    ("tau_cmd", "commanded motor torque, N m", ("computed_torque", "tau")),
    ("a_ref", "reference acceleration times the virtual mass (controller output), N m",
     ("controller", "out")),
)



def _logged(declared: tuple[Logged, ...], site: str, n: int, version: int) -> list[Field]:
    """The fields of a site's declared signals (``teleop_rt.declarations.Logged``) a log of
    schema ``version`` holds."""
    return [
        Field(x.log_name(site), x.ros_type, n if x.per_joint else None, x.log_doc(site),
              (x.owner, x.source))
        for x in declared if x.since <= version
    ]  # fmt: skip


def _symbols(*fields: tuple[str, str]) -> list[str]:
    """The paper's symbols of (site, port field) pairs (the /channel topic's names)."""
    return [port_symbol(site, source) for site, source in fields]


@dataclass(frozen=True)
class LogLayout:
    """Row layout and topics of a session with n joints and E environment elements, or of one
    site's log (``site``: "hsi" or "to"; "" for a session's). ``n_hsi``, ``n_to``: the robots'
    joints when they are not n (0: n); ``mapped``: the robots' topics hold ``MAPPED_FIELDS``
    (and from schema 3 ``MAPPED_STATE``); ``version``: the schema of the log."""

    n: int
    n_env: int
    site: str = ""
    n_hsi: int = 0
    n_to: int = 0
    mapped: bool = False
    version: int = SCHEMA_VERSION  # the fields a log of an older schema holds

    @property
    def joints_hsi(self) -> int:
        return self.n_hsi or self.n

    @property
    def joints_to(self) -> int:
        return self.n_to or self.n

    @property
    def plain(self) -> bool:
        """One joint count and no mapped fields: the layout of the metadata's joints alone."""
        return self.joints_hsi == self.joints_to == self.n and not self.mapped

    @property
    def topics(self) -> tuple[Topic, ...]:
        """The topics in row order; /timing last (the recorder fills it, not the gather)."""
        n, e = self.n, self.n_env
        hsi = Topic(
            "/hsi",
            "teleop_rt/msg/HsiTick",
            (
                *_common(),
                *self._robot(self.joints_hsi),
                Field("operator_reference_m", "float64", 3, "hand reference, world frame",
                      ("world", "reference")),
                Field("operator_reference_velocity_m_s", "float64", 3, "",
                      ("world", "reference_velocity")),
                Field("operator_force_n", "float64", 3, "operator force on the HSI tool",
                      ("world", "force")),
            ),
        )
        contact = [Field("in_contact", "uint8", e, "per environment element",
                         ("world", "contacts"))] if e else []  # fmt: skip
        to = Topic(
            "/to",
            "teleop_rt/msg/ToTick",
            (
                *_common(),
                *self._robot(self.joints_to),
                Field("environment_force_n", "float64", 3, "environment force on the TO tool",
                      ("world", "force")),
                *contact,
            ),
        )
        channel = Topic(
            "/channel",
            "teleop_rt/msg/ChannelTick",
            (
                *_common(),
                *_joint(_symbols(("hsi", "flow"), ("hsi", "effort"), ("to", "flow"),
                                 ("to", "effort")), n, "port variables (eq 8)"),
                *_joint(_symbols(("hsi", "wave_out"), ("hsi", "wave_in"), ("to", "wave_in"),
                                 ("to", "wave_out")), n, "waves (eq 9), as used this tick"),
                *_joint(["power", "energy"], n, "W and J per joint (eq 7, 8)"),
                Field("total_energy", "float64", None, "J, all joints"),
                Field("balance_hsi", "float64", None, "J received minus emitted at the HSI port"),
                Field("balance_to", "float64", None, "J, the same at the TO port (< 0: active)"),
                *_joint(["removed_hsi", "removed_to"], n, "J removed by the protection"),
            ),
        )
        timing = Topic(
            "/timing",
            "teleop_rt/msg/TimingTick",
            (
                *_common(),
                Field("compute_ns", "int64", None, "tick compute time"),
                Field("lateness_ns", "int64", None, "wake-up after the deadline"),
                Field("missed", "uint8", None, "1 if the tick ended after the next deadline"),
            ),
        )
        if not self.site:
            return (hsi, to, channel, timing)
        return ({"hsi": hsi, "to": to}[self.site], *self._site_topics(), timing)

    def _robot(self, joints: int) -> list[Field]:
        """A robot's fields: per joint, then (a mapped layout) of the channel's size."""
        robot = [Field(name, "float64", joints, doc, source) for name, doc, source in ROBOT_FIELDS]
        mapped = [Field(name, "float64", self.n, doc) for name, doc in MAPPED_FIELDS]
        state = [Field(name, kind, None, doc, ("mapping", name))
                 for name, kind, doc in MAPPED_STATE]  # fmt: skip
        state = state if self.version >= 3 else []
        return robot + (mapped + state if self.mapped else [])

    def _site_topics(self) -> tuple[Topic, Topic]:
        n, side, version = self.n, self.site, self.version
        port = Topic(
            "/port",
            f"teleop_rt/msg/{side.capitalize()}PortTick",
            (*_common(), *_logged(PORT_LOG, side, n, version)),
        )
        link = Topic(
            "/link", "teleop_rt/msg/LinkTick", (*_common(), *_logged(LINK_LOG, side, n, version))
        )
        return port, link

    @property
    def row_width(self) -> int:
        """float64 columns per tick: the tick and time once, then every topic's own fields."""
        return 2 + sum(t.width - 2 for t in self.topics)

    @property
    def ring_width(self) -> int:
        """float64 columns per tick in the recorder's ring: a log row, then per environment
        element its surface's shift along -normal (a pushed mass), which only the 3D scene
        shows (``teleop_rt.recording.scene``)."""
        return self.row_width + self.n_env

    def field_columns(self, topic: str, name: str) -> slice | None:
        """Row columns of one field of a topic (None if the topic has no such field)."""
        where = self.columns().get(topic)
        if where is None:
            return None
        start = where.start
        for f in next(t for t in self.topics if t.name == topic).fields[2:]:
            if f.name == name:
                return slice(start, start + f.count)
            start += f.count
        return None

    def columns(self) -> dict[str, slice]:
        """Row slice of every topic's own fields (after the shared tick and time)."""
        out, start = {}, 2
        for topic in self.topics:
            width = topic.width - 2
            out[topic.name] = slice(start, start + width)
            start += width
        return out

    def encode(self, rows: np.ndarray, topic: Topic, cols: slice) -> np.ndarray:
        """CDR payloads (without the header) of many ticks for one topic, one row each."""
        out = np.empty(len(rows), dtype=topic.dtype)
        out["tick"] = rows[:, 0]
        out["t"] = rows[:, 1]
        block = rows[:, cols]
        col = 0
        for f in topic.fields[2:]:
            values = block[:, col : col + f.count]
            out[f.name] = values[:, 0] if f.length is None else values
            col += f.count
        return out
