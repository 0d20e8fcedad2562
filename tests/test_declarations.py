"""The shared names, codes and limits are declared once (teleop_rt/declarations.py): every
config name has a kernel code and the other way round, and the config reads its declarations
without loading an implementation (issue 25)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import get_args

from teleop_rt import declarations as d

ROOT = Path(__file__).resolve().parents[1]


def test_every_channel_name_has_one_code_of_its_own() -> None:
    for names, codes in ((d.ChannelMode, d.MODES), (d.Reconstruction, d.RECONSTRUCTIONS)):
        assert sorted(codes) == sorted(get_args(names))
        assert sorted(codes.values()) == list(range(len(codes)))  # distinct, dense
    assert d.DEFAULT_RECONSTRUCTION in d.RECONSTRUCTIONS
    assert d.OVERRUN_DEFAULT in d.OVERRUN_POLICIES


def test_the_config_loads_no_implementation() -> None:
    # config.py reads the channel's and the impairment's declarations, not com/ or hal/can/
    # implementations (which load numpy and numba): checked in a fresh interpreter
    probe = (
        "import sys, teleop_rt.config\n"
        "loaded = [m for m in sys.modules if m.split('.')[0] in ('numpy', 'numba')]\n"
        "print(sorted(m for m in sys.modules if m.startswith('teleop_rt')), loaded)\n"
        "raise SystemExit(1 if loaded else 0)\n"
    )
    done = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True,
                          text=True)  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr


def test_the_channel_defaults_are_the_declared_ones() -> None:
    import inspect

    from teleop_rt.com.port import Port
    from teleop_rt.config import ChannelSpec

    assert ChannelSpec().mode == d.DEFAULT_MODE in d.MODES
    assert ChannelSpec().wave_reconstruction == d.DEFAULT_RECONSTRUCTION
    defaults = inspect.signature(Port.__init__).parameters
    assert defaults["mode"].default == d.MODES[d.DEFAULT_MODE]
    assert defaults["reconstruction"].default == d.RECONSTRUCTIONS[d.DEFAULT_RECONSTRUCTION]


def test_both_writer_processes_share_one_control_block() -> None:
    # the MCAP log's writer and the CAN log's read the same declared words
    from teleop_rt.hal.can.canlog import CONTROL
    from teleop_rt.recording.writer import CONTROL_BYTES

    words = (d.PUBLISHED, d.CLOSED, d.CONSUMED, d.HEARTBEAT, d.STATUS, d.ERRNO, d.START_NS)
    assert sorted(words) == list(range(len(words))) and len(words) <= d.CONTROL_WORDS
    assert CONTROL.size == CONTROL_BYTES == 8 * d.CONTROL_WORDS
