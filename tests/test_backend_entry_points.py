"""Third-party backends are found by name through the ``teleop_rt.backends`` entry-point group
(as python-can finds its interfaces): a package that declares one needs no change here."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from teleop_rt import config
from teleop_rt.errors import ConfigError
from teleop_rt.hal.registry import _REGISTRY, BACKENDS, available_backends
from teleop_rt.session import Session
from tests.conftest import CONFIGS

ROOT = Path(__file__).resolve().parents[1]

PLUGIN = """
from teleop_rt.hal import sim

def make(cfg, side, model, operator=None):
    backend = sim.make_sim(cfg, side, model, operator)
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


def test_the_interface_and_the_registry_import_no_backend() -> None:
    # the built-in backends are "module:factory" names, imported when one is created: listing
    # them, the interface and the signal blocks load neither the simulation nor the CAN stack
    probe = (
        "import sys\n"
        "import teleop_rt.hal.base, teleop_rt.hal.signals\n"
        "from teleop_rt.hal.registry import available_backends\n"
        "assert {'sim', 'can'} <= set(available_backends())\n"
        "backends = ('teleop_rt.hal.sim', 'teleop_rt.hal.can.backend')\n"
        "loaded = [m for m in backends if m in sys.modules]\n"
        "raise SystemExit(f'loaded: {loaded}' if loaded else 0)\n"
    )
    done = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr


def test_a_built_in_backend_that_does_not_load_is_one_clear_error(monkeypatch) -> None:
    monkeypatch.setitem(BACKENDS, "sim_elsewhere", "teleop_rt.hal.nowhere:make")
    with pytest.raises(ConfigError, match=r"'sim_elsewhere' is declared by 'teleop_rt.hal.nowhere"):
        Session(config.load(CONFIGS / "free_space.yaml", ["backend=sim_elsewhere"]))
