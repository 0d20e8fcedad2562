"""Names, codes, defaults and limits that the config, the command line and the implementations
share, each declared once here. The module imports nothing of the package (nor numpy), so that
the config and the command line read them without loading an implementation."""

from __future__ import annotations

from typing import Literal, get_args

# --- the channel (teleop_rt.com.port) ---------------------------------------------------------
ChannelMode = Literal["wave", "tdpa", "direct"]  # the config's names (channel.mode)
DIRECT, WAVE, TDPA = 0, 1, 2  # the kernels' codes
MODES: dict[ChannelMode, int] = {"direct": DIRECT, "wave": WAVE, "tdpa": TDPA}

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
