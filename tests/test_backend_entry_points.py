"""Third-party backends are found by name through the ``teleop_rt.backends`` entry-point group
(as python-can finds its interfaces): a package that declares one needs no change here."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from teleop_rt import config
from teleop_rt.errors import ConfigError
from teleop_rt.hal.base import _REGISTRY, available_backends
from teleop_rt.session import Session
from tests.conftest import CONFIGS

PLUGIN = """
from teleop_rt.hal import sim

def make(cfg, side, model, operator=None):
    backend = sim._make_sim(cfg, side, model, operator)
    backend.made_by_plugin = True
    return backend

def broken(cfg, side, model, operator=None):
    raise AssertionError("never called")
"""


@pytest.fixture
def plugin_package(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """An installed distribution (a .dist-info on sys.path) declaring two backends."""
    (tmp_path / "acme_backend.py").write_text(PLUGIN)
    info = tmp_path / "acme_backend-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: acme-backend\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(
        "[teleop_rt.backends]\nacme = acme_backend:make\nacme_missing = acme_nowhere:make\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    yield tmp_path
    for name in ("acme", "acme_missing"):
        _REGISTRY.pop(name, None)
    sys.modules.pop("acme_backend", None)


def test_a_backend_declared_by_an_entry_point_is_found_by_name(plugin_package) -> None:
    assert "acme" in available_backends()
    session = Session(config.load(CONFIGS / "free_space.yaml", ["to.backend=acme"]))
    assert getattr(session.to.backend, "made_by_plugin", False)
    assert not getattr(session.hsi.backend, "made_by_plugin", False)


def test_a_broken_entry_point_is_one_clear_error(plugin_package) -> None:
    with pytest.raises(ConfigError, match=r"'acme_missing' is declared by 'acme_nowhere:make'"):
        Session(config.load(CONFIGS / "free_space.yaml", ["backend=acme_missing"]))
