"""A site log's signals are declared once (teleop_rt.declarations: PORT_LOG, LINK_LOG, issue
25): each names a field of its block of the kind it logs, the log schema, the site log's gather,
a site replay's packets and the channel view are derived from them, so that a declared field
added or renamed reaches all of them with no other edit (tried here by patching the
declaration), and every vector of the packet is logged (what a replay needs to hand the port
the packet the site used)."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from teleop_rt import config
from teleop_rt import declarations as d
from teleop_rt.com.port import Packet, Port
from teleop_rt.com.zenoh_link import Arrival
from teleop_rt.flat import Block, Int, Scalar, Vector
from teleop_rt.recording import schema
from teleop_rt.recording.schema import LogLayout
from teleop_rt.recording.site_log import SiteLogSource
from teleop_rt.recording.site_replay import LoggedLink
from teleop_rt.session import ChannelView
from teleop_rt.site import HsiSite, ToSite

ROOT = Path(__file__).resolve().parents[1]
OWNERS: dict[str, type[Block]] = {"port": Port, "packet": Packet, "arrival": Arrival}


@pytest.fixture(scope="module")
def sites() -> dict[str, HsiSite | ToSite]:
    cfg = config.load(ROOT / "configs" / "paper_experiment.yaml")
    return {"hsi": HsiSite(cfg, "sim", None), "to": ToSite(cfg, "sim", None)}


def _topic(layout: LogLayout, name: str) -> schema.Topic:
    return next(t for t in layout.topics if t.name == name)


def test_each_logged_signal_names_a_field_of_its_block_of_its_kind() -> None:
    for x in (*d.PORT_LOG, *d.LINK_LOG):
        declared = getattr(OWNERS[x.owner], x.source, None)
        kinds = (Vector,) if x.per_joint else (Scalar, Int)
        assert isinstance(declared, kinds), (x.owner, x.source, declared)
        if isinstance(declared, Int):
            assert x.ros_type in ("int64", "uint8"), x
    for site in d.SITES:  # log names are distinct within a topic
        for declared in (d.PORT_LOG, d.LINK_LOG):
            names = [x.log_name(site) for x in declared]
            assert len(set(names)) == len(names)


def test_every_vector_of_the_packet_is_logged() -> None:
    logged = {x.source for x in d.LINK_LOG if x.owner == "packet" and x.per_joint}
    assert logged == set(Packet.VECTORS)


@pytest.mark.parametrize("site", d.SITES)
def test_the_site_topics_are_the_declaration(site: str) -> None:
    n = 3
    for version in (2, 3):
        layout = LogLayout(n, 0, site, version=version)
        for topic, declared in (("/port", d.PORT_LOG), ("/link", d.LINK_LOG)):
            fields = _topic(layout, topic).fields[2:]
            held = [x for x in declared if x.since <= version]
            assert [f.name for f in fields] == [x.log_name(site) for x in held]
            assert [f.source for f in fields] == [(x.owner, x.source) for x in held]
            assert [f.count for f in fields] == [n if x.per_joint else 1 for x in held]
    # the paper's names (Kuschel & Buss eq 8, 9): the HSI's port carries omega_c, tau_c, sends
    # u_l and receives v_l; the TO's omega_t, tau_t, sends v_r, receives u_r; each site's /link
    # documents what its peer's packet carries
    names = [f.name for f in _topic(LogLayout(1, 0, site), "/port").fields[2:6]]
    link = {f.name: f.doc for f in _topic(LogLayout(1, 0, site), "/link").fields}
    if site == "hsi":
        assert names == ["omega_c", "tau_c", "u_l", "v_l"]
        assert "(tau_t)" in link["x"] and "(v_r)" in link["wave"]
    else:
        assert names == ["omega_t", "tau_t", "v_r", "u_r"]
        assert "(omega_c)" in link["x"] and "(u_l)" in link["wave"]


# the site logs' message definitions (all topics) as schema 2 and 3 wrote them: a log written
# today stays byte for byte what those logs hold, and they still read (deriving the topics from
# the declaration changed no byte)
WRITTEN = {("hsi", 2): "aca580a500d996e4", ("hsi", 3): "d856b8e50293fd74",
           ("to", 2): "168b476263cad9c7", ("to", 3): "3722febac2c270bd"}  # fmt: skip


@pytest.mark.parametrize(("site", "version"), sorted(WRITTEN))
def test_the_site_logs_schema_is_the_one_written(site: str, version: int) -> None:
    layout = LogLayout(2, 0, site, version=version)
    text = b"".join(t.type_name.encode() + b"\n" + t.definition for t in layout.topics)
    assert hashlib.sha256(text).hexdigest()[:16] == WRITTEN[site, version]


def test_the_channel_view_takes_the_ports_symbols_from_the_declaration() -> None:
    for site in d.SITES:
        for x in d.PORT_LOG:
            if x.symbols:
                assert ChannelView.SOURCES[x.log_name(site)] == (site, x.source)
    channel = _topic(LogLayout(1, 0), "/channel")
    assert {f.name for f in channel.fields[2:]} <= set(ChannelView.SOURCES)


def _gathered(site: HsiSite | ToSite) -> tuple[LogLayout, np.ndarray, SiteLogSource]:
    source = SiteLogSource(site)
    parts = source.log_parts()
    return parts.layout, parts.gather, source


def _columns(layout: LogLayout, gather: np.ndarray, topic: str, name: str) -> list[int]:
    where = layout.field_columns(topic, name)
    assert where is not None, (topic, name)
    return gather[where.start - 2 : where.stop - 2].tolist()  # (the gather skips tick and t)


def test_a_declared_field_added_reaches_the_schema_the_gather_and_the_replay(
    sites, monkeypatch
) -> None:
    """The mutation: one more packet field declared (Packet.unsent) is logged, gathered from
    the packet the site used and handed back by a replay, with no other edit."""
    added = d.Logged("packet", "unsent", "the packet's unsent", ros_type="uint8",
                     per_joint=False)  # fmt: skip
    monkeypatch.setattr(schema, "LINK_LOG", (*d.LINK_LOG, added))
    site = sites["hsi"]
    layout, gather, source = _gathered(site)
    link = _topic(layout, "/link")
    assert link.fields[-1].name == "unsent" and b"uint8 unsent" in link.definition
    assert _columns(layout, gather, "/link", "unsent") == [source.packed.index_of(site.rx,
                                                                                  "unsent")]
    # a replay of such a log hands the field back
    rows = np.zeros(1, dtype=link.dtype)
    rows["valid"], rows["unsent"], rows["x"] = 1, 1, [[0.25] * layout.n]
    packet = Packet(layout.n)
    LoggedLink(rows, site, None, layout).receive(0, packet)
    assert packet.unsent == 1 and packet.valid == 1
    assert packet.x.tolist() == [0.25] * layout.n


def test_a_declared_symbol_renamed_renames_the_log_field_and_keeps_its_source(
    sites, monkeypatch
) -> None:
    renamed = tuple(
        d.Logged(x.owner, x.source, x.doc, symbols={**x.symbols, "to": "omega_x"})
        if x.source == "flow" else x
        for x in d.PORT_LOG
    )  # fmt: skip
    monkeypatch.setattr(schema, "PORT_LOG", renamed)
    site = sites["to"]
    layout, gather, source = _gathered(site)
    names = [f.name for f in _topic(layout, "/port").fields]
    assert "omega_x" in names and "omega_t" not in names
    first = source.packed.index_of(site.port, "flow")
    assert _columns(layout, gather, "/port", "omega_x") == list(range(first, first + site.n))


@pytest.mark.parametrize("site", d.SITES)
def test_each_site_log_column_is_its_declared_block_field(sites, site: str) -> None:
    s = sites[site]
    layout, gather, source = _gathered(s)
    owners = {"port": s.port, "packet": s.rx, "arrival": source.arrival}
    for topic in ("/port", "/link"):
        for f in _topic(layout, topic).fields[2:]:
            assert f.source is not None
            owner, attr = f.source
            first = source.packed.index_of(owners[owner], attr)
            assert _columns(layout, gather, topic, f.name) == list(range(first, first + f.count))
    for f in _topic(layout, f"/{site}").fields[2:]:  # the robot's: from the blocks it names
        assert f.source is not None, f.name
        owner, attr = f.source
        first = source.packed.index_of(getattr(s, owner), attr)
        assert _columns(layout, gather, f"/{site}", f.name) == list(range(first, first + f.count))
