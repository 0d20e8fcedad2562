"""The communication channel (COM): delay lines and the wave-variable two-port."""

from teleop_rt.com.delay import DelayLine
from teleop_rt.com.wave import WaveChannel

__all__ = ["DelayLine", "WaveChannel"]
