"""The in-process link with a network in between: with no impairment (or jitter that stays
within the playout delay) the sites compute exactly what they compute over an InProcessLink;
with impairments a run is bit-reproducible from the seed, and the link's figures add up."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from teleop_rt import config
from teleop_rt.com.impaired_link import ImpairedLink
from teleop_rt.com.impairment import ImpairmentSpec
from teleop_rt.com.link import InProcessLink, Link
from teleop_rt.com.port import HSI, TO, Packet
from teleop_rt.session import Session
from tests.conftest import CONFIGS
from tests.test_no_allocation import net_blocks


def sites_alone(cfg: config.SessionConfig) -> Session:
    """A session's two sites on buffers of their own, to be stepped through a Python link."""
    session = Session(cfg, fuse=False)
    for site in session.sites:
        site.bind(type(session.packed)(site.blocks))
    return session


def step(session: Session, link: Link) -> None:
    hsi, to = session.hsi, session.to
    hsi.sense(link)
    to.sense(link)
    hsi.update(link)
    to.update(link)


def paper(duration_s: float, delay_ms: float) -> config.SessionConfig:
    return config.load(
        CONFIGS / "paper_experiment.yaml",
        [f"duration_s={duration_s}", f"channel.delay_ms={delay_ms}"],
    )


@pytest.mark.parametrize(
    "delay_ms, impairment",
    [
        (20, None),
        (1, None),
        (20, ImpairmentSpec(seed=3, delay_ms=20)),  # arrives exactly at its playout tick
        (
            20,
            ImpairmentSpec(
                seed=3,
                delay_ms=10,
                jitter_ms=5,
                distribution="uniform",
                correlation_percent=50,
                reorder_percent=10,
            ),
        ),  # fmt: skip
    ],
    ids=["20ms", "1ms", "network-delay-equals-playout", "jitter-within-playout"],
)
def test_within_the_playout_delay_the_sites_compute_what_an_in_process_link_gives(
    delay_ms, impairment
) -> None:
    cfg = paper(2, delay_ms)
    plain, impaired = sites_alone(cfg), sites_alone(cfg)
    link_a = InProcessLink(plain.n, cfg.delay_ticks)
    link_b = ImpairedLink(impaired.n, cfg.delay_ticks, cfg.dt, impairment)
    for k in range(cfg.n_ticks):
        step(plain, link_a)
        step(impaired, link_b)
        for a, b in ((plain.hsi, impaired.hsi), (plain.to, impaired.to)):
            assert np.array_equal(a.rx.f, b.rx.f) and np.array_equal(a.rx.i, b.rx.i), k
            assert np.array_equal(a.tau_cmd, b.tau_cmd), k
            assert np.array_equal(a.port.f, b.port.f), k
            assert np.array_equal(a.feedback.q, b.feedback.q), k
    assert np.abs(impaired.to.port.flow).max() > 0.01
    for side in (HSI, TO):
        stats = link_b.stats(side)
        assert stats["used"] == cfg.n_ticks - cfg.delay_ticks and stats["lost"] == 0


ROUGH = ImpairmentSpec(
    delay_ms=15, jitter_ms=4, distribution="pareto", correlation_percent=30,
    gilbert_elliott={"p_percent": 1, "r_percent": 30}, duplicate_percent=2, reorder_percent=3,
)  # fmt: skip


def run_digest(cfg: config.SessionConfig, impairment: ImpairmentSpec) -> tuple[str, dict]:
    """A hash of both sites' torques, ports and joint angles at every tick, and the stats."""
    session = sites_alone(cfg)
    link = ImpairedLink(session.n, cfg.delay_ticks, cfg.dt, impairment)
    digest = hashlib.sha256()
    for _ in range(cfg.n_ticks):
        step(session, link)
        for site in session.sites:
            for x in (site.tau_cmd, site.port.f, site.feedback.q, site.rx.i):
                digest.update(x.tobytes())
    return digest.hexdigest(), {side: link.stats(side) for side in (HSI, TO)}


def test_the_same_seed_gives_a_bit_identical_session() -> None:
    cfg = paper(3, 20)
    a = run_digest(cfg, ROUGH.model_copy(update={"seed": 7}))
    b = run_digest(cfg, ROUGH.model_copy(update={"seed": 7}))
    c = run_digest(cfg, ROUGH.model_copy(update={"seed": 8}))
    assert a == b
    assert a[0] != c[0]
    stats = a[1][TO]
    # the impairment acted: late and lost packets, duplicates, reordering, all counted
    for name in ("lost", "late", "duplicated", "reordered"):
        assert stats[name] > 0, name
    assert stats["network"]["lost"] > 0 and stats["network"]["duplicated"] > 0


def test_lost_packets_are_the_networks_losses_when_nothing_is_late() -> None:
    """Constant delay within D and independent loss: each packet the network lost is one
    playout tick with a zero packet; the rest are used, none late."""
    d, ticks = 10, 5000
    link = ImpairedLink(1, d, 0.001, ImpairmentSpec(seed=4, delay_ms=6, loss_percent=5))
    dropped = []
    packets = [Packet(1), Packet(1)]
    into = Packet(1)
    for k in range(ticks):
        for side in (HSI, TO):
            packets[side].tick = packets[side].seq = k
            packets[side].valid = 1
            link.send(side, packets[side])
        for side in (HSI, TO):
            link.receive(side, into)
            before = link.impairments[side].lost
            link.end_tick(side)
            if side == HSI and link.impairments[side].lost > before:
                dropped.append(k)
    stats = link.stats(TO)
    played = [s for s in dropped if s < ticks - d]  # the last D ticks' packets never played
    assert stats["lost"] == len(played) > 0
    assert stats["used"] == ticks - d - len(played)
    assert stats["late"] == stats["duplicated"] == stats["early"] == 0
    assert stats["sent"] == ticks and stats["delay_ticks"]["max"] == 6


def test_a_network_slower_than_the_playout_delay_is_all_late() -> None:
    """Under the fixed rule: a packet after its playout tick is dropped."""
    d, ticks = 5, 200
    link = ImpairedLink(1, d, 0.001, ImpairmentSpec(delay_ms=8), playout="fixed")
    packet, into = Packet(1), Packet(1)
    for k in range(ticks):
        packet.tick = packet.seq = k
        for side in (HSI, TO):
            link.send(side, packet)
            link.receive(side, into)
            assert into.valid == 0
            link.end_tick(side)
    stats = link.stats(HSI)
    assert (
        stats["used"] == 0 and stats["late"] == stats["received"] == ticks - 8
    )  # arrived by the last tick
    assert stats["lost"] == ticks - d


def test_the_link_allocates_nothing_it_keeps_per_tick() -> None:
    link = ImpairedLink(2, 20, 0.001, ROUGH)
    packets, into = [Packet(2), Packet(2)], Packet(2)
    k = [0]

    def tick() -> None:
        for side in (HSI, TO):
            packets[side].tick = packets[side].seq = k[0]
            link.send(side, packets[side])
        for side in (HSI, TO):
            link.receive(side, into)
            link.end_tick(side)
        k[0] += 1

    for _ in range(1000):
        tick()
    assert net_blocks(tick, 10_000) < 100


def test_the_link_needs_a_playout_delay() -> None:
    with pytest.raises(ValueError, match="at least one tick"):
        ImpairedLink(2, 0, 0.001)
