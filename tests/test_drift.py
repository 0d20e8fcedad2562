"""Following a peer whose clock drifts (teleop_rt.com.drift), in fast mode: the sender ticks
on a clock 100 ppm fast or slow against the receiver's, its packets cross a jittery network,
and the receiver's playout, driven by the drift follower, keeps the floor of the arrivals'
lateness and the channel's delay within a tick of where they started, each retarget costing
one packet (a zero packet or a skipped one), none used twice. No real waiting: the clocks are
simulated."""

from __future__ import annotations

import math

import numpy as np
import pytest

from teleop_rt.com.drift import WINDOW, DriftFollower
from teleop_rt.com.playout import Playout
from teleop_rt.com.port import Packet

N, D = 2, 5
TICKS = 100_000  # 100 s at 1 kHz: 10 ticks of slide at 100 ppm


def run(ppm: float, max_ppm: float = 200.0, seed: int = 1) -> dict:
    """The receiver's ticks 0..TICKS against a sender whose clock runs ``ppm`` fast (> 0).

    Time in the receiver's ticks: its tick k spans [k, k + 1) and takes its packet at
    k + 0.5; the sender's tick s starts at s / (1 + ppm 1e-6), sends 0.1 tick later, and the
    network adds 0.2 tick plus an exponential jitter of mean 0.3 (at most 3: within D)."""
    rng = np.random.default_rng(seed)
    rate = 1.0 + ppm * 1e-6
    sends = TICKS + 200
    arrival = np.arange(sends) / rate + 0.1 + 0.2 + np.minimum(rng.exponential(0.3, sends), 3.0)
    order = np.argsort(arrival, kind="stable")  # the network may reorder
    playout = Playout(N, D, policy="fixed")  # the rule whose floor the follower keeps
    follower = DriftFollower(playout, max_ppm=max_ppm)
    packet, into = Packet(N), Packet(N)
    lateness, used, delays = [], [], []
    a = 0
    for k in range(TICKS):
        while arrival[order[a]] < k + 0.5:  # what arrived before this tick's take
            s = int(order[a])
            packet.tick = packet.seq = s
            packet.valid = 1
            lateness.append(arrival[s] - s - playout.offset_ticks)
            playout.arrive(k, packet)
            follower.arrival(float(arrival[s]), s)
            a += 1
        if playout.take(k, into):
            s = int(into.tick)
            used.append(s)
            delays.append(k + 0.5 - (s / rate + 0.1))  # played minus sent, receiver ticks
    x = np.array(lateness)
    windows = x[: x.size // WINDOW * WINDOW].reshape(-1, WINDOW).min(axis=1)
    return {"floor_moved": windows - windows[0], "used": np.array(used),
            "delay": np.array(delays), "counters": playout.counters(),
            "drift": follower.stats()}  # fmt: skip


@pytest.mark.parametrize("ppm", [100.0, -100.0], ids=["sender-fast", "sender-slow"])
def test_the_playout_follows_a_drifting_clock_within_a_tick(ppm: float) -> None:
    out = run(ppm)
    slide = abs(ppm) * 1e-6 * TICKS  # ticks the clocks slid over the run: 10
    drift, c = out["drift"], out["counters"]
    # lateness: every window's floor within a tick of the first window's
    assert np.abs(out["floor_moved"]).max() < 1.0, np.abs(out["floor_moved"]).max()
    # the channel's delay (played minus sent) stays within a tick of D's (D + 0.4 here)
    assert np.abs(out["delay"] - out["delay"][0]).max() < 1.0 + 1e-9
    # no packet used twice, none used out of order
    assert np.all(np.diff(out["used"]) > 0)
    # one retarget per tick of slide, in the direction of the slide, each costing one packet
    assert math.floor(slide) - 1 <= drift["retargets"] <= math.ceil(slide)
    if ppm > 0:  # the sender's ticks come faster: jump over one now and then
        assert drift["forward"] == drift["retargets"] and c["skipped"] == drift["retargets"]
        assert c["repeated"] == 0 and drift["offset_ticks"] == -drift["retargets"]
    else:  # they come slower: a zero packet now and then, never the last one again
        assert drift["back"] == drift["retargets"] and c["repeated"] == drift["retargets"]
        assert c["skipped"] == 0 and drift["offset_ticks"] == drift["retargets"]
    assert c["late"] == 0 and c["lost"] == 0 and c["early"] == 0


def test_without_following_the_floor_slides_by_the_drift() -> None:
    """The same run with retargets off (max_ppm 0): the floor slides by about the 10 ticks
    and, with the receiver behind the sender's clock, every packet ends up late."""
    out = run(-100.0, max_ppm=0.0)
    assert out["floor_moved"][-1] > 8.5
    assert out["counters"]["late"] > 0.4 * TICKS
    assert out["drift"]["retargets"] == 0


def test_jitter_alone_never_retargets() -> None:
    """Equal clocks: however the jitter falls, the floor does not move by 3/4 tick."""
    out = run(0.0)
    assert out["drift"]["retargets"] == 0
    assert np.abs(out["floor_moved"]).max() < 0.1


def test_a_step_of_the_networks_delay_is_followed_slowly_not_at_once() -> None:
    """A lasting step down of 5 ticks looks like drift; the follower moves by at most one
    tick per 1e6 / max_ppm ticks (5000 at 200 ppm), never in a jump, until it has followed."""
    playout = Playout(N, D, policy="fixed")  # the rule whose floor the follower keeps
    follower = DriftFollower(playout, max_ppm=200.0)
    offsets = []
    for s in range(40_000):
        step = 5.0 if s >= 10_000 else 0.0  # the delay drops by 5 ticks at tick 10 000
        follower.arrival(s + 6.3 - step, s)
        if s % 1000 == 999:
            offsets.append(playout.offset_ticks)
    # the first window wholly after the step asks at once; then one per 5000 ticks
    assert offsets[10:] == [-1] * 5 + [-2] * 5 + [-3] * 5 + [-4] * 5 + [-5] * 10
    assert (follower.forward, follower.back) == (5, 0)
