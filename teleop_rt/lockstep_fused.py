"""Two simulated plants run inside a one-process session's tick: the lock-step kernels
(``teleop_rt.lockstep``) and both plants' compiled pieces (``teleop_rt.hal.sim``) in four
compiled calls around the Pinocchio calls (six when loads act at the tools), instead of ten
compiled calls and four backend method calls (the stages' order is ``teleop_rt.tick_stages``'s
lock-step one, the plants' read and write in place of the backends'):

    sense_and_prepare:  both plants' sensors; lockstep_before
    (Python)            RNEA of each controller model, into its data.tau
    finish_and_command: lockstep_after; when safe, both plants' motor torques
    (Python)            ABA of each plant, into its data.ddq
    integrate:          both plants' Euler steps
    (Python)            the tool Jacobian of each plant
    next_ticks:         both plants' loads at the next tick (in task space, with both sites'
                        maps for the next tick after them: ``next_ticks_mapped``, one call
                        fewer per site than the session's own ``map_tool`` calls)

Four compiled calls is the least the Pinocchio calls between them allow. Each is bound once
(``teleop_rt.flat.compiled_for``: the compiled entry point, not the dispatcher, with every
argument fixed but the Jacobians), and the kernels read Pinocchio's results where Pinocchio
leaves them (``data.tau``, ``data.ddq``: views taken once), not the copies its calls return.

It is the same arithmetic in the same order as ``read`` / ``write`` of two ``SimBackend``s, so
a session gives bit-identical results either way. The plants' blocks follow the session's own
(``SESSION_BLOCKS`` on), the TO's from block ``split`` on. The fusion lives here, beside the
lock-step code it calls, not in the HAL: the simulated backend exports its plant kernels and
blocks (``SimBackend.rebind``, ``compiled_common_case``) and knows nothing of the session.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from functools import partial
from typing import Any

import numpy as np
import pinocchio as pin

from teleop_rt.control import ComputedTorque
from teleop_rt.flat import Block, compiled_for, floats_of, ints_of, jit, vec
from teleop_rt.hal.base import Backend
from teleop_rt.hal.sim import SimBackend, command, euler_step, next_tick, sense
from teleop_rt.lockstep import (
    HSI_SITE,
    SESSION_BLOCKS,
    TO_SITE,
    link_at,
    lockstep_after,
    lockstep_before,
)
from teleop_rt.mapping import map_tool
from teleop_rt.site_tick import CT, FB, MAP, WORLD

FB_H, FB_T, WORLD_H, WORLD_T = HSI_SITE + FB, TO_SITE + FB, HSI_SITE + WORLD, TO_SITE + WORLD
CT_H, CT_T = HSI_SITE + CT, TO_SITE + CT
MAP_H, MAP_T = HSI_SITE + MAP, TO_SITE + MAP


class FusedPlants(ABC):
    """Two backends' periods run inside a lock-step session's tick kernels: the same
    arithmetic as both backends' ``read`` and ``write``, in fewer calls. The session packs
    ``blocks`` after its own blocks (``SESSION_BLOCKS``) and calls ``bind``; then per tick
    ``before`` in place of both reads and the lock-step's first kernel, ``after`` (once the
    controller models' RNEA is in ``rnea``) in place of its second (and, without a finding,
    the writes' commands), and ``advance`` for the rest of the writes."""

    blocks: list[Block]

    @abstractmethod
    def bind(
        self, f: np.ndarray, i: np.ndarray, offsets: np.ndarray,
        rnea: tuple[np.ndarray, np.ndarray], port_n: int | None = None,
    ) -> None:  # fmt: skip
        """The packed buffers and the session's offsets (all blocks), once packed; ``rnea``:
        where each controller model's RNEA lands (its Pinocchio ``data.tau``, HSI's and TO's);
        ``port_n``: the channel's size where it is not the joints' (a task-space channel)."""

    @abstractmethod
    def before(self) -> int:
        """Both reads and the lock-step's first half; the finding (0: none)."""

    @abstractmethod
    def after(self) -> int:
        """The lock-step's second half and, without a finding, both motor commands."""

    @abstractmethod
    def advance(self) -> None:
        """The rest of both writes: each plant's period."""

    def take_maps(self, maps: list[tuple[Any, ...]]) -> bool:
        """Both sites' task-space maps (``Site._bound_map``'s calls) run inside ``advance``,
        after the plants' period, where the pair can; False: the session calls them."""
        return False


def fuse_plants(hsi: Backend, to: Backend) -> FusedPlants | None:
    """The HSI's and the TO's backends run inside the session's tick, where they can: two
    simulated plants of one joint count, both in their common case (``SimBackend``'s
    ``compiled_common_case``); None keeps the plain ``read`` / ``write`` path."""
    if not (isinstance(hsi, SimBackend) and isinstance(to, SimBackend) and hsi.n == to.n):
        return None
    if not (hsi.compiled_common_case and to.compiled_common_case):
        return None
    return FusedSimPair(hsi, to)


@jit
def sense_and_prepare(
    f: np.ndarray, i: np.ndarray, o: np.ndarray, at: np.ndarray, n: int, split: int, nj: int
) -> int:
    """Both plants' ideal sensors into the sites' feedback and world blocks, then the
    lock-step's first half; its finding. ``n``: the port's size; ``nj``: the plants' joints
    (n but in task space)."""
    plant_h, plant_t = o[2 * SESSION_BLOCKS : 2 * split], o[2 * split :]
    sense(f, i, plant_h, nj, floats_of(f, o, FB_H), ints_of(i, o, FB_H), floats_of(f, o, WORLD_H))
    sense(f, i, plant_t, nj, floats_of(f, o, FB_T), ints_of(i, o, FB_T), floats_of(f, o, WORLD_T))
    return lockstep_before(f, i, o, at, n)


@jit
def finish_and_command(
    f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int, split: int, nj: int,
    rnea_h: np.ndarray, rnea_t: np.ndarray,
) -> int:  # fmt: skip
    """The lock-step's second half; the safety finding (0: none), and only without one both
    plants take their checked motor torques."""
    code = lockstep_after(f, i, o, n, rnea_h, rnea_t)
    if code:
        return code
    tau = ComputedTorque.idx.TAU
    command(f, o[2 * SESSION_BLOCKS : 2 * split], nj, vec(floats_of(f, o, CT_H), tau, nj))
    command(f, o[2 * split :], nj, vec(floats_of(f, o, CT_T), tau, nj))
    return 0


@jit
def integrate(
    f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int, split: int, a_h: np.ndarray,
    a_t: np.ndarray,
) -> None:  # fmt: skip
    """Both plants' Euler steps with their ABA accelerations."""
    euler_step(f, i, o[2 * SESSION_BLOCKS : 2 * split], n, a_h)
    euler_step(f, i, o[2 * split :], n, a_t)


@jit
def next_ticks(
    f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int, split: int,
    x_h: np.ndarray, x_t: np.ndarray, jac_h: np.ndarray, jac_t: np.ndarray,
) -> None:  # fmt: skip
    """Both plants' time and loads at the next tick, their tools at x with Jacobians jac (the
    tick's one argument not bound once: Pinocchio's Jacobian call returns a new array)."""
    next_tick(f, i, o[2 * SESSION_BLOCKS : 2 * split], n, jac_h, x_h)
    next_tick(f, i, o[2 * split :], n, jac_t, x_t)


@jit
def next_ticks_mapped(
    f: np.ndarray, i: np.ndarray, o: np.ndarray, n: int, split: int,
    x_h: np.ndarray, x_t: np.ndarray, tool_h: np.ndarray, rot_h: np.ndarray,
    tool_t: np.ndarray, rot_t: np.ndarray, jac_h: np.ndarray, jac_t: np.ndarray,
    map_h: np.ndarray, map_t: np.ndarray,
) -> None:  # fmt: skip
    """``next_ticks``, then both sites' task-space maps for the next tick (``map_tool``, in
    the order the session calls them: the HSI's, the TO's) with their Jacobians ``map_h``,
    ``map_t`` and their controller models' tools (place, rotation): one compiled call in
    place of three."""
    next_tick(f, i, o[2 * SESSION_BLOCKS : 2 * split], n, jac_h, x_h)
    next_tick(f, i, o[2 * split :], n, jac_t, x_t)
    map_tool(floats_of(f, o, MAP_H), ints_of(i, o, MAP_H), tool_h, rot_h, map_h)
    map_tool(floats_of(f, o, MAP_T), ints_of(i, o, MAP_T), tool_t, rot_t, map_t)


class FusedSimPair(FusedPlants):
    """The HSI's and the TO's simulated plants, stepped inside the session's kernels."""

    def __init__(self, plant_h: SimBackend, plant_t: SimBackend) -> None:
        self.plants = (plant_h, plant_t)
        self.blocks = [*plant_h.blocks, *plant_t.blocks]
        self.n = plant_h.n  # the plants' joints

    def bind(
        self, f: np.ndarray, i: np.ndarray, offsets: np.ndarray,
        rnea: tuple[np.ndarray, np.ndarray], port_n: int | None = None,
    ) -> None:  # fmt: skip
        plant_h, plant_t = self.plants
        first = SESSION_BLOCKS
        self.split = split = first + len(plant_h.blocks)
        end = split + len(plant_t.blocks)
        assert offsets.size == 2 * end, "the plants' blocks must close the session's buffers"
        plant_h.rebind(f, i, offsets[2 * first : 2 * split])
        plant_t.rebind(f, i, offsets[2 * split : 2 * end])
        n, at = self.n, link_at(offsets)
        m = self.n if port_n is None else port_n  # the port's size (in task space: 2)
        rnea_h, rnea_t = rnea
        a_h, a_t = plant_h.plant.data.ddq, plant_t.plant.data.ddq  # (where ABA leaves a)
        x_h, x_t = plant_h._x, plant_t._x
        # load (or, on a fresh install, compile) the four kernels now, on scratch copies
        sf, si, jac = f.copy(), i.copy(), np.zeros((6, n))
        sense_and_prepare(sf, si, offsets, at, m, split, n)
        finish_and_command(sf, si, offsets, m, split, n, rnea_h, rnea_t)
        integrate(sf, si, offsets, n, split, a_h, a_t)
        next_ticks(sf, si, offsets, n, split, x_h, x_t, jac, jac)
        # the per-tick calls bound once, every argument but the Jacobians fixed (a partial of
        # a compiled entry point costs next to nothing beyond the call itself)
        args: tuple[Any, ...] = (f, i, offsets, at, m, split, n)
        self.before = partial(compiled_for(sense_and_prepare, *args), *args)  # type: ignore[method-assign]
        args = (f, i, offsets, m, split, n, rnea_h, rnea_t)
        self.after = partial(compiled_for(finish_and_command, *args), *args)  # type: ignore[method-assign]
        args = (f, i, offsets, n, split, a_h, a_t)
        self._integrate = partial(compiled_for(integrate, *args), *args)
        args = (f, i, offsets, n, split, x_h, x_t)
        self._next_ticks = partial(compiled_for(next_ticks, *args, jac, jac), *args)
        self._aba = (plant_h._pin, plant_t._pin)
        self._jac = (plant_h.jacobian_call, plant_t.jacobian_call)
        self._bound = (f, i, offsets, n, split, x_h, x_t)
        self._maps: tuple[Any, ...] | None = None

    def take_maps(self, maps: list[tuple[Any, ...]]) -> bool:
        if len(maps) != 2:  # (a task-space channel maps at both sites)
            return False
        (jacobian_h, args_h, mapped_h), (jacobian_t, args_t, mapped_t) = maps
        tools = (*mapped_h.args[2:], *mapped_t.args[2:])  # (x, rotation of each site)
        jac = np.zeros((6, self.n))  # (the four Jacobians' type: Pinocchio's (6, n), C order)
        args = (*self._bound, *tools)
        sf, si = self._bound[0].copy(), self._bound[1].copy()
        next_ticks_mapped(sf, si, *args[2:], jac, jac, jac, jac)  # (loaded now, on copies)
        kernel = compiled_for(next_ticks_mapped, *args, jac, jac, jac, jac)
        self._next_ticks_mapped = partial(kernel, *args)
        self._maps = ((jacobian_h, args_h), (jacobian_t, args_t))
        return True

    def before(self) -> int:  # (replaced by a partial at bind)
        raise RuntimeError("bind first")

    def after(self) -> int:  # (replaced at bind)
        raise RuntimeError("bind first")

    def advance(self) -> None:
        (pin_h, pin_t), ((jac_h, tool_h), (jac_t, tool_t)) = self._aba, self._jac
        aba = pin.aba
        aba(*pin_h)  # (into each plant's data.ddq, which integrate reads)
        aba(*pin_t)
        self._integrate()
        maps = self._maps
        if maps is None:
            self._next_ticks(jac_h(*tool_h), jac_t(*tool_t))
            return
        (map_h, args_h), (map_t, args_t) = maps
        self._next_ticks_mapped(jac_h(*tool_h), jac_t(*tool_t), map_h(*args_h), map_t(*args_t))
