"""Two sites' ``ZenohLink`` over a ``LoopbackTransport`` in one process: the link's own code
(encoder, receive path, playout, drift follower) without Zenoh, as tools/bench_link.py's
fast-mode figure runs it. At D = 1 tick, each tick's packet handed over between ticks, every
site uses the peer's packet of the tick before at every tick after the first: nothing lost."""

from __future__ import annotations

from pathlib import Path

from teleop_rt import config
from teleop_rt.com.wire import wire_size
from teleop_rt.com.zenoh_link import LoopbackTransport, ZenohLink
from teleop_rt.site import HsiSite, ToSite

PAPER = Path(__file__).resolve().parents[1] / "configs" / "paper_experiment.yaml"
TICKS = 300


def test_a_loopback_pair_plays_every_packet_one_tick_later() -> None:
    cfg = config.load(PAPER, ["channel.delay_ms=1", "duration_s=0.3"])
    sites = [HsiSite(cfg, None), ToSite(cfg, None)]
    links = []
    for site in sites:
        link = ZenohLink(cfg, site.side, site.n, lambda site=site: site.tick,
                         LoopbackTransport(wire_size(site.n)))  # fmt: skip
        link.connect(7)
        link.start()
        links.append(link)
    a, b = (link.transport for link in links)
    for _ in range(TICKS):
        for site, link in zip(sites, links, strict=True):
            site.sense(link)
            site.update(link)
        a.deliver(b)
        b.deliver(a)
    for link in links:
        stats = link.stats()
        peer = stats["from_peer"]
        assert stats["sent"] == TICKS
        assert (peer["received"], peer["used"], peer["lost"]) == (TICKS, TICKS - 1, 0)
        assert peer["delay_ticks"]["max"] == 1
        assert stats["one_way_delay_us"] is not None  # every fresh arrival's delay noted
        assert link.receiver.delay_count == TICKS
    for site in sites:  # the last tick used the peer's packet of the tick before
        assert (site.rx.valid, site.rx.tick) == (1, TICKS - 2)
