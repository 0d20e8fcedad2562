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


def lock_in(signal: np.ndarray, omega: float, dt: float) -> complex:
    """Complex amplitude of the omega component of a sampled signal (whole periods assumed)."""
    t = np.arange(len(signal)) * dt
    return 2.0 / len(signal) * complex(np.sum(signal * np.exp(-1j * omega * t)))
