"""Names, codes, defaults and limits that the config, the command line and the implementations
share, each declared once here. The module imports nothing of the package (nor numpy), so that
the config and the command line read them without loading an implementation."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, get_args

# --- the channel (teleop_rt.com.port) ---------------------------------------------------------
ChannelMode = Literal["wave", "tdpa", "direct"]  # the config's names (channel.mode)
DIRECT, WAVE, TDPA = 0, 1, 2  # the kernels' codes
MODES: dict[ChannelMode, int] = {"direct": DIRECT, "wave": WAVE, "tdpa": TDPA}
DEFAULT_MODE: ChannelMode = "wave"  # the paper's wave variables (channel.mode's default)

# what a wave channel puts in place of a packet that did not arrive (channel.wave_reconstruction;
# the methods in teleop_rt.com.port's docstring)
Reconstruction = Literal["reflected", "bounded", "corrected", "zero", "hold", "integral"]
ZERO, HOLD, INTEGRAL, BOUNDED, CORRECTED, REFLECTED = 0, 1, 2, 3, 4, 5  # the kernels' codes
RECONSTRUCTIONS: dict[Reconstruction, int] = {
    "zero": ZERO, "hold": HOLD, "integral": INTEGRAL, "bounded": BOUNDED, "corrected": CORRECTED,
    "reflected": REFLECTED,
}  # fmt: skip
# the default: the wall is still felt under burst loss (docs/transparency_under_loss.md)
DEFAULT_RECONSTRUCTION: Reconstruction = "reflected"
# the wave reconstructions the deadband codec keeps passive (teleop_rt.com.codec), its default
# first: reflected (a held wave beyond the peer's declaration paid by the energy it reflects:
# the stiff wall at D = 1 ms within 5 %, docs/codec.md); bounded (the honest bound alone)
CODEC_RECONSTRUCTIONS: tuple[Reconstruction, ...] = ("reflected", "bounded")
CODEC_RECONSTRUCTION: Reconstruction = CODEC_RECONSTRUCTIONS[0]
# ``corrected`` and ``reflected`` pay the wave integral's debt back with this time constant, s
# (channel.wave_drift_time_s): shorter, less position lost (T_p); longer, less of the pay-back
# felt (T_tau: after a delay step down it replays the samples the playout skipped;
# docs/transparency_under_loss.md)
WAVE_DRIFT_TIME_S = 0.25
# the part of that debt that a change of the delay brought under the ``newest`` playout (packets
# skipped with no silence, or silent ticks with none missed) may be paid back with a time
# constant of its own, s (channel.wave_skip_time_s; None, the default: one debt): 2 s meets the
# foam sawtooth row but costs T_p and drift under jitter (docs/transparency_under_loss.md, "s37")
WAVE_SKIP_TIME_S: float | None = None
# the wave impedance scheduled by the delay (channel.wave_impedance_schedule, off by default;
# teleop_rt.com.port.schedule_b): b = b_0 D / age of the packet used, between this share of b_0
# and b_0, moving by at most WAVE_B_RATE b_0 per second (docs/transparency_under_loss.md, "s38")
WAVE_B_FLOOR, WAVE_B_RATE = 0.125, 0.5
# ... and the TO's position correction of the drift it causes stays on this long, s, after b
# is back at b_0
WAVE_B_HOLD_S = 1.0

# --- the deadband codec (teleop_rt.com.codec; channel.deadband) --------------------------------
# the ticks between two packets a codec sends (min_interval_ticks, max_interval_ticks) and the
# energy deadband's pace (exchange_min_ticks) lie in this range: 1, a packet may go every tick;
# a codec silent longer than 10 s at 1 kHz is a lost peer
MIN_CODEC_INTERVAL, MAX_CODEC_INTERVAL = 1, 10_000
# the codec's options, off by default: the velocity-adaptive Weber fraction's gain, s/rad;
# TDPA's energy deadband step, J, its Weber fraction and its pace, ticks (1: sends at once)
VELOCITY_GAIN_S_PER_RAD = 0.0
EXCHANGE_J = 0.0
EXCHANGE_WEBER = 0.0
EXCHANGE_MIN_TICKS = MIN_CODEC_INTERVAL


def deadband_problem(
    weber: float, floor: float, min_ticks: int, max_ticks: int, velocity_gain: float,
    exchange_j: float, exchange_weber: float, exchange_min_ticks: int,
) -> str | None:  # fmt: skip
    """The first rule the deadband codec's parameters break, as one line in the config's names
    (channel.deadband), or None: the config's check and ``codec.configure`` (which tests and
    tools call without a config) both ask this."""
    if not (0.0 < weber < 1.0 and floor >= 0.0 and velocity_gain >= 0.0):
        return "the deadband needs 0 < weber < 1, floor >= 0, velocity_gain_s_per_rad >= 0"
    ticks = (("min_interval_ticks", min_ticks), ("max_interval_ticks", max_ticks),
             ("exchange_min_ticks", exchange_min_ticks))  # fmt: skip
    for name, value in ticks:
        if not MIN_CODEC_INTERVAL <= value <= MAX_CODEC_INTERVAL:
            return f"{name} = {value} is not in {MIN_CODEC_INTERVAL} .. {MAX_CODEC_INTERVAL}"
    if min_ticks > max_ticks:
        return f"min_interval_ticks = {min_ticks} is above max_interval_ticks = {max_ticks}"
    if not (exchange_j >= 0.0 and exchange_weber >= 0.0):
        return "exchange_j and exchange_weber are >= 0"
    if exchange_weber > 0 and not exchange_j > 0:
        return "exchange_weber grows the energy step exchange_j: set exchange_j > 0"
    if exchange_min_ticks > EXCHANGE_MIN_TICKS and not exchange_j > 0:
        return "exchange_min_ticks paces the energy step exchange_j: set exchange_j > 0"
    if exchange_min_ticks > max_ticks:
        return (f"exchange_min_ticks = {exchange_min_ticks} is above max_interval_ticks = "
                f"{max_ticks}")  # fmt: skip
    return None


# what the channel couples (channel.space; teleop_rt.mapping): joint j to joint j, or the tools
# in task space, each robot through its own Jacobian: the plane (x, y), 3-D position (x, y, z),
# or the pose (position and orientation: the twist and wrench, world axes at the tool)
Space = Literal["joint", "plane", "position", "pose"]
TASK_DIMS: dict[str, int] = {"plane": 2, "position": 3, "pose": 6}  # the port's vector length

# which packet a site uses at its tick k (link.playout; teleop_rt.com.playout): newest, the
# newest one sent by k - D not yet used (a late packet is used once due instead of dropped: it
# meets what fixed misses under outages and delay swings, docs/transparency_under_loss.md);
# fixed, only the one sent at k - D (jitter within D becomes the constant delay D)
Playout = Literal["newest", "fixed"]
PLAYOUT_DEFAULT: Playout = "newest"

MAX_DELAY_MS = 10_000.0  # 10 s one way: beyond any teleoperation link, and bounded memory


def require_delay_ticks(delay_ticks: int) -> int:
    """``delay_ticks`` if it is a delay (>= 0 whole ticks), else ValueError."""
    if delay_ticks < 0:
        raise ValueError("delay_ticks must be >= 0")
    return delay_ticks


# --- the real-time loop (teleop_rt.loop.TickClock) --------------------------------------------
Overrun = Literal["catch_up", "skip", "stop"]  # what a late tick does
OVERRUN_POLICIES: tuple[str, ...] = get_args(Overrun)
OVERRUN_DEFAULT: Overrun = "catch_up"


# --- the logged signals (teleop_rt.recording.schema; the gathers of teleop_rt.recording) -------
SITES = ("hsi", "to")


@dataclass(frozen=True)
class Logged:
    """One block field a log holds, declared once: where it comes from (``owner``, a block of
    the site: "port", "packet" (the peer's packet used), "arrival"; its field ``source``),
    its name in the log (the paper's symbol per site where it has one, else ``name`` or the
    field's own), its ROS type, whether it is a vector of the channel's size, its doc (the
    message definition's comment; ``{carried}``: the paper's symbol of what the peer's packet
    carries in it, ``carries``: the sender's port field per sender site) and the first schema
    that has it. The schema, the site log's gather and a site replay's packets read this."""

    owner: str
    source: str
    doc: str
    name: str = ""
    symbols: dict[str, str] = field(default_factory=dict)  # site -> the paper's symbol
    ros_type: str = "float64"
    per_joint: bool = True
    carries: dict[str, str] = field(default_factory=dict)  # sender site -> its port field
    since: int = 1

    def log_name(self, site: str) -> str:
        return self.symbols.get(site) or self.name or self.source

    def log_doc(self, site: str) -> str:
        if not self.carries:
            return self.doc
        sender = SITES[1 - SITES.index(site)]
        return self.doc.format(carried=port_symbol(sender, self.carries[sender]))


# a site's port (``/port``), in row order: its variables under the paper's names (eq 8, 9)
PORT_LOG: tuple[Logged, ...] = (
    Logged("port", "flow", "port flow, rad/s", symbols={"hsi": "omega_c", "to": "omega_t"}),
    Logged("port", "effort", "port effort, N m", symbols={"hsi": "tau_c", "to": "tau_t"}),
    Logged("port", "wave_out", "the wave this port sends (eq 9)",
           symbols={"hsi": "u_l", "to": "v_r"}),
    Logged("port", "wave_in", "the wave received, after the optional filter",
           symbols={"hsi": "v_l", "to": "u_r"}),
    Logged("port", "power", "into the channel at this port, W and J"),
    Logged("port", "energy", "into the channel at this port, W and J"),
    Logged("port", "total_energy", "J, all joints", per_joint=False),
    Logged("port", "balance", "J received minus emitted (< 0: active)", per_joint=False),
    Logged("port", "limited", "J removed by the protection", name="removed"),
)  # fmt: skip
_EXTRA = "the packet's (teleop_rt.com.port.Packet)"  # the vectors a replay hands back as they are
# a site's link (``/link``), in row order: the peer's packet the site used at the tick and when
# it came; all that a replay needs to hand the port the same packet (site_replay.LoggedLink)
LINK_LOG: tuple[Logged, ...] = (
    Logged("arrival", "sender_tick", "the peer's tick of the packet used; -1: none",
           ros_type="int64", per_joint=False),
    Logged("arrival", "arrival_tick", "this site's tick it arrived at; -1: none",
           ros_type="int64", per_joint=False),
    Logged("arrival", "one_way_delay_us", "sent to arrived, one host only", per_joint=False),
    Logged("packet", "x", "the packet's port input ({carried})",
           carries={"hsi": "flow", "to": "effort"}),
    Logged("packet", "wave", "the packet's wave ({carried}), before filtering",
           carries={"hsi": "wave_out", "to": "wave_out"}),
    Logged("packet", "wave_sum", _EXTRA),
    Logged("packet", "x_sum", _EXTRA),
    Logged("packet", "wave_energy", _EXTRA),
    Logged("packet", "e_in", _EXTRA),
    Logged("packet", "e_out", _EXTRA),
    Logged("packet", "energy", "energy through the peer's port, J", name="peer_energy",
           per_joint=False),
    Logged("arrival", "valid", "1: the peer's packet due was there; 0: zeros", ros_type="uint8",
           per_joint=False),
    Logged("packet", "engaged", "the packet's engaged: the HSI's coupling", ros_type="uint8",
           since=3, per_joint=False),
)  # fmt: skip


def port_symbol(site: str, source: str) -> str:
    """The log name of a site's port field ``source`` (``PORT_LOG``): its paper symbol."""
    return next(x.log_name(site) for x in PORT_LOG if x.source == source)


# --- a writer process's shared memory (teleop_rt.recording.writer, teleop_rt.hal.can.canlog) --
# int64 control words first, then the ring of rows (log rows, CAN frames) that the producing
# process publishes and the writer process consumes: the index of each word
PUBLISHED, CLOSED, CONSUMED, HEARTBEAT, STATUS, ERRNO, START_NS = range(7)
CONTROL_WORDS = 8  # (64 bytes: the rows after them stay aligned)
WRITE_FAILED = 1  # ctrl[STATUS] after a write error, whose errno is ctrl[ERRNO]
