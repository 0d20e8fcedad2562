"""Shared fixtures: paths and small helpers for measuring responses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
SCARA_URDF = ROOT / "robots" / "urdf" / "scara_2dof.urdf"


@pytest.fixture
def configs_dir() -> Path:
    return CONFIGS


@pytest.fixture(autouse=True)
def _logs_in_tmp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Runs that log by default write to the test's own folder, never into the checkout."""
    import teleop_rt.recording.recorder as recorder

    monkeypatch.setattr(recorder, "DEFAULT_LOG_DIR", tmp_path / "logs")


def lock_in(signal: np.ndarray, omega: float, dt: float) -> complex:
    """Complex amplitude of the omega component of a sampled signal (whole periods assumed)."""
    t = np.arange(len(signal)) * dt
    return 2.0 / len(signal) * complex(np.sum(signal * np.exp(-1j * omega * t)))
