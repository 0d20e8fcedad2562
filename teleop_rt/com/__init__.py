"""The communication channel (COM): the wave-variable two-port and a direct delayed channel."""

from teleop_rt.com.direct import DirectChannel
from teleop_rt.com.wave import WaveChannel

__all__ = ["DirectChannel", "WaveChannel"]
