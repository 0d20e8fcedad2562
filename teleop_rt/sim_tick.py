"""A session's tick on two simulated plants, fused: the controller's halves (``teleop_rt.tick``)
and both plants' compiled pieces (``teleop_rt.hal.sim``) in four compiled calls around the
Pinocchio calls (six when loads act at the tools), instead of ten compiled calls and four
backend method calls.

    sense_and_prepare:  both plants' sensors; before_models
    (Python)            RNEA of each controller model
    finish_and_command: after_models; when safe, both plants' motor torques
    (Python)            ABA of each plant
    integrate:          both plants' Euler steps
    (Python)            the tool Jacobian of each plant
    next_ticks:         both plants' loads at the next tick

It is the same arithmetic in the same order as ``Backend.read`` / ``write`` of two
``SimBackend``s, so a session gives bit-identical results either way. It runs when both plants
are in their common case (``SimBackend.compiled_common_case``); the plants' blocks follow the
session's own in its packed buffers (``PLANT_H`` on), the TO's from block ``split`` on.
"""

from __future__ import annotations

import numpy as np

from teleop_rt.control import TAU
from teleop_rt.flat import floats_of, ints_of, jit, vec
from teleop_rt.hal.sim import command, euler_step, next_tick, sense
from teleop_rt.tick import (
    BLOCK_ORDER,
    CT_H,
    CT_T,
    FB_H,
    FB_T,
    WORLD_H,
    WORLD_T,
    after_models,
    before_models,
)

PLANT_H = len(BLOCK_ORDER)  # the HSI plant's first block in the session's packed buffers


@jit
def sense_and_prepare(f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int, split: int) -> None:
    """Both plants' ideal sensors into the session's feedback and world blocks, then the
    controller's half before the models."""
    plant_h, plant_t = o[2 * PLANT_H : 2 * split], o[2 * split :]
    sense(f, i, plant_h, n, floats_of(f, o, FB_H), ints_of(i, o, FB_H), floats_of(f, o, WORLD_H))
    sense(f, i, plant_t, n, floats_of(f, o, FB_T), ints_of(i, o, FB_T), floats_of(f, o, WORLD_T))
    before_models(f, i, o, n)


@jit
def finish_and_command(
    f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int, split: int,
    rnea_h: np.ndarray, rnea_t: np.ndarray,
) -> int:  # fmt: skip
    """The controller's half after the models; the safety finding (0: none), and only without
    one both plants take their checked motor torques."""
    code = after_models(f, i, o, n, rnea_h, rnea_t)
    if code:
        return code
    command(f, o[2 * PLANT_H : 2 * split], n, vec(floats_of(f, o, CT_H), TAU, n))
    command(f, o[2 * split :], n, vec(floats_of(f, o, CT_T), TAU, n))
    return 0


@jit
def integrate(
    f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int, split: int, a_h: np.ndarray,
    a_t: np.ndarray,
) -> None:  # fmt: skip
    """Both plants' Euler steps with their ABA accelerations."""
    euler_step(f, i, o[2 * PLANT_H : 2 * split], n, a_h)
    euler_step(f, i, o[2 * split :], n, a_t)


@jit
def next_ticks(
    f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int, split: int,
    jac_h: np.ndarray, x_h: np.ndarray, jac_t: np.ndarray, x_t: np.ndarray,
) -> None:  # fmt: skip
    """Both plants' time and loads at the next tick, their tools at x with Jacobians jac."""
    next_tick(f, i, o[2 * PLANT_H : 2 * split], n, jac_h, x_h)
    next_tick(f, i, o[2 * split :], n, jac_t, x_t)


def warm_up_simulated_tick(f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int, split: int) -> None:
    """Load (or, on a fresh install, compile) the four kernels now, not at the first deadline:
    run them once on the given scratch copies of a session's buffers."""
    zeros, jac, x = np.zeros(n), np.zeros((6, n)), np.zeros(3)
    sense_and_prepare(f, i, o, n, split)
    finish_and_command(f, i, o, n, split, zeros, zeros)
    integrate(f, i, o, n, split, zeros, zeros)
    next_ticks(f, i, o, n, split, jac, x, jac, x)
