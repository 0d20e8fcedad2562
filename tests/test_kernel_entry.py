"""The tick's kernels are called through their compiled entry points, bound once
(``teleop_rt.flat.compiled_for``), not through numba's dispatchers, which work out every
argument's type on every call (issue 27: the tick's cost above the Pinocchio floor); and
what the entry points compute is what the dispatchers compute, bit for bit."""

from __future__ import annotations

from functools import partial

import numba
import numpy as np
import pinocchio as pin

from teleop_rt import config
from teleop_rt.flat import compiled_for
from teleop_rt.lockstep import lockstep_before
from teleop_rt.recording.recorder import Recorder
from teleop_rt.session import Session
from tests.conftest import CONFIGS

PAPER = CONFIGS / "paper_experiment.yaml"


def per_tick_calls(session: Session, recorder: Recorder) -> dict[str, partial]:
    pair = session._pair_plants
    assert pair is not None
    return {
        "lockstep_before": session._before, "lockstep_after": session._after,
        "sense_and_prepare": pair.before, "finish_and_command": pair.after,  # type: ignore[dict-item]
        "integrate": pair._integrate, "next_ticks": pair._next_ticks,  # type: ignore[attr-defined]
        "fill_row": recorder._fill,
    }  # fmt: skip


def test_every_per_tick_kernel_is_bound_to_its_entry_point(tmp_path) -> None:
    session = Session(config.load(PAPER))
    recorder = Recorder(session, tmp_path / "log.mcap")
    try:
        for name, call in per_tick_calls(session, recorder).items():
            assert isinstance(call, partial), name
            assert not isinstance(call.func, numba.core.dispatcher.Dispatcher), name
            assert type(call.func).__name__ == "builtin_function_or_method", name
    finally:
        recorder.close(None)


def test_an_entry_point_computes_what_its_dispatcher_computes() -> None:
    session = Session(config.load(PAPER))
    for _ in range(50):
        session.step()
    f, i, o, n = session._buffers
    at = session._at
    f1, i1, f2, i2 = f.copy(), i.copy(), f.copy(), i.copy()
    code1 = lockstep_before(f1, i1, o, at, n)
    code2 = compiled_for(lockstep_before, f2, i2, o, at, n)(f2, i2, o, at, n)
    assert code1 == code2 == 0
    assert np.array_equal(f1, f2) and np.array_equal(i1, i2)
    assert not np.array_equal(f1, f)  # (the kernel did something)


def test_the_kernels_read_pinocchios_results_where_pinocchio_leaves_them() -> None:
    """RNEA into data.tau, ABA into data.ddq: the arrays the tick's kernels are bound to are
    those (not copies), and Pinocchio writes each call's result there."""
    session = Session(config.load(PAPER))
    pair = session._pair_plants
    assert pair is not None
    rnea = [site.model.data.tau for site in session.sites]
    ddq = [site.backend.plant.data.ddq for site in session.sites]  # type: ignore[attr-defined]
    for call in (session._after, pair.after):
        bound = call.args[-2:]  # type: ignore[attr-defined]
        assert all(np.shares_memory(x, y) for x, y in zip(bound, rnea, strict=True))
    bound = pair._integrate.args[-2:]  # type: ignore[attr-defined]
    assert all(np.shares_memory(x, y) for x, y in zip(bound, ddq, strict=True))
    for _ in range(20):
        session.step()
    for site, tau, a in zip(session.sites, rnea, ddq, strict=True):
        model, data, q, v, a_des = site._pin
        assert np.array_equal(tau, pin.rnea(model, data, q + 0.1, v, a_des))
        plant_model, plant_data, q_p, v_p, tau_p = site.backend._pin  # type: ignore[attr-defined]
        assert np.array_equal(a, pin.aba(plant_model, plant_data, q_p + 0.1, v_p, tau_p))
