"""A live clutch in the logs (issue 26, schema 3): the received ``engaged`` of each packet in a
site's /link, each mapped site's coupling gain r, coupled state and the live inputs its map read
per tick, and the map's constants once in the metadata; so that a site's replay of a TO that
followed a live clutch, and of the HSI that pressed it, and a session's replay of one, are bit
for bit.

The clutch is pressed as the terminal's keys press it (``mapping.keys``: ``teleop_rt.keys``
toggles the HSI's ``Feedback.inputs``), here from the test between ticks of the two sites
stepped alone over an in-process link, each recording its own site log."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from teleop_rt import config
from teleop_rt.com.link import InProcessLink
from teleop_rt.com.port import Packet
from teleop_rt.hal.signals import INPUT_CLUTCH, INPUT_PRESENT
from teleop_rt.keys import AT_START
from teleop_rt.recording import site_replay
from teleop_rt.recording.reader import read_log
from teleop_rt.recording.recorder import Recorder
from teleop_rt.recording.replay import build_replay
from teleop_rt.recording.schema import LogLayout
from teleop_rt.recording.site_log import site_recorder
from teleop_rt.recording.site_replay import replay_site
from teleop_rt.session import Session
from tests.conftest import CONFIGS

DELAY_TICKS = 20
SETTINGS = ["duration_s=3", f"channel.delay_ms={DELAY_TICKS}", "mapping.keys=true"]
PRESSED = range(1200, 1800)  # the clutch held from tick 1200 to 1799 (the hand in the foam)
AWAY = range(2300, 2400)  # and the operator away for 0.1 s


def inputs_at(tick: int) -> int:
    """The HSI's inputs at ``tick``, as the keys' reader would have set them."""
    bits = AT_START | (INPUT_CLUTCH if tick in PRESSED else 0)
    return bits & ~INPUT_PRESENT if tick in AWAY else bits


class NotedLink(InProcessLink):
    """The in-process link, noting for the TO's log what the Zenoh link notes (``Arrival``)."""

    def __init__(self, n: int, delay_ticks: int, arrivals: dict) -> None:
        super().__init__(n, delay_ticks)
        self.arrivals = arrivals

    def receive(self, side: int, into: Packet) -> None:
        super().receive(side, into)
        a = self.arrivals[side]
        if into.valid:
            a.sender_tick, a.arrival_tick, a.valid = float(into.tick), float(into.tick), 1.0
        else:
            a.none()
        a.one_way_delay_us = math.nan


def two_site_logs(folder: Path, *overrides: str) -> dict[str, Path]:
    """Both sites of the foam config, stepped alone over a 20-tick link, each with its site
    log; the clutch and the presence pressed as ``inputs_at`` says."""
    cfg = config.load(CONFIGS / "foam.yaml", [*SETTINGS, *overrides])
    session = Session(cfg, fuse=False)
    paths = {s.name: folder / f"live.{s.name}.mcap" for s in session.sites}
    recorders = {s.name: site_recorder(s, paths[s.name], wait_for_room=True)
                 for s in session.sites}  # fmt: skip
    arrivals = {site.side: recorders[site.name].session.arrival for site in session.sites}
    link = NotedLink(session.n, cfg.delay_ticks, arrivals)
    hsi, to = session.hsi, session.to
    for k in range(cfg.n_ticks):
        hsi.feedback.inputs = inputs_at(k)
        hsi.sense(link)
        to.sense(link)
        hsi.update(link)
        to.update(link)
        for r in recorders.values():
            r.record(0, 0, False)
    for r in recorders.values():
        r.close({"ticks": cfg.n_ticks, "safety_stop": False})
    return paths


@pytest.fixture(scope="module")
def logs(tmp_path_factory) -> dict[str, Path]:
    return two_site_logs(tmp_path_factory.mktemp("live_clutch"))


def test_the_site_logs_hold_the_live_clutch(logs) -> None:
    """The TO's /link holds each packet's engaged (0 from the HSI's first decoupled tick on,
    D ticks late), both robots' gain, coupled state and inputs, and the metadata the map."""
    hsi, to = read_log(logs["hsi"]), read_log(logs["to"])
    assert to.layout == LogLayout(2, 1, "to", 2, 2, True)
    engaged = to.topics["/link"]["engaged"]
    hsi_gain, to_gain = hsi.topics["/hsi"]["gain"], to.topics["/to"]["gain"]
    hsi_off, to_off = np.flatnonzero(hsi_gain == 0), np.flatnonzero(to_gain == 0)
    assert hsi_off[0] == PRESSED[0] and len(hsi_off) == len(PRESSED) + len(AWAY)
    valid = to.topics["/link"]["valid"] == 1  # (the first D ticks: no packet, zeros)
    assert valid[DELAY_TICKS:].all() and not valid[:DELAY_TICKS].any()
    off = np.flatnonzero(valid & (engaged == 0))
    assert off[0] == PRESSED[0] + DELAY_TICKS  # the packet's state, D ticks late
    assert len(off) == len(PRESSED) + len(AWAY)
    assert to_off[0] == PRESSED[0] + DELAY_TICKS + 1  # read by the TO's next tick
    assert np.array_equal(hsi.topics["/hsi"]["coupled"] == 0, hsi_gain == 0)
    assert np.array_equal(to.topics["/to"]["coupled"] == 0, to_gain == 0)
    assert hsi.topics["/hsi"]["inputs"][PRESSED[0]] == INPUT_CLUTCH | INPUT_PRESENT
    assert hsi.topics["/hsi"]["inputs"][AWAY[0]] == 0 and (to.topics["/to"]["inputs"] == 0).all()
    assert 0 < to_gain[to_off[-1] + 1] < 1  # the ramp back, logged
    meta = json.loads(to.meta["mapping"])
    assert meta["follows_packets"] == 1 and meta["motion_scale"] == 1.0
    assert meta["rotation"] == np.eye(3).tolist()
    assert json.loads(hsi.meta["mapping"])["live_inputs"] == INPUT_CLUTCH | INPUT_PRESENT


@pytest.mark.parametrize("overrides", [[], ["mapping.keys=false"]], ids=["keys", "metadata"])
@pytest.mark.parametrize("site", ["to", "hsi"])
def test_a_site_replay_of_a_live_clutch_is_bit_for_bit(logs, site, overrides) -> None:
    """Each site replayed against its partner's logged packets reproduces its log: the TO from
    the packets' engaged, the HSI from its logged inputs. Also with a config that does not
    say where the inputs came from (``mapping.keys=false``: as a CAN drive's 0x60FD, which the
    replay's simulated backend does not have): the log's ``mapping`` metadata says."""
    done = replay_site(read_log(logs[site]), overrides, None, False, str(logs[site]))
    assert done.figures["identical"] is True, done.figures
    assert done.figures["original"] == done.figures["replay"]


def test_without_the_logged_engaged_the_tos_replay_differs(logs, monkeypatch) -> None:
    """The mutation: a replay that hands the TO packets that say "coupled" throughout (as
    before schema 3) no longer reproduces the TO that followed the clutch."""
    receive = site_replay.LoggedLink.receive

    def coupled(self, side: int, into: Packet) -> None:
        receive(self, side, into)
        into.engaged = 1

    monkeypatch.setattr(site_replay.LoggedLink, "receive", coupled)
    data = read_log(logs["to"])
    done = replay_site(data, [], None, False, str(logs["to"]))
    assert done.figures["identical"] is False


def test_without_the_logged_inputs_the_hsis_replay_differs(logs, monkeypatch) -> None:
    monkeypatch.setattr(site_replay, "logged_inputs", lambda data: None)
    done = replay_site(read_log(logs["hsi"]), [], None, False, str(logs["hsi"]))
    assert done.figures["identical"] is False


def test_a_session_replay_of_a_live_clutch_is_bit_for_bit(tmp_path) -> None:
    """A one-process session with the keys' clutch, logged and replayed: every field equal
    (the TO follows the HSI's packets in the session too)."""
    cfg = config.load(CONFIGS / "foam.yaml", SETTINGS)
    session = Session(cfg)
    session.hsi.feedback.inputs = inputs_at(0)

    def press(s: Session) -> None:  # (for the next tick, as the keys' thread would)
        s.hsi.feedback.inputs = inputs_at(s.tick)

    session.run(observer=press, recorder=Recorder(session, tmp_path / "live.mcap"))
    data = read_log(tmp_path / "live.mcap")
    assert (data.topics["/to"]["gain"] == 0).sum() == len(PRESSED) + len(AWAY)
    again, ticks = build_replay(data, [])
    again.run(ticks=ticks, recorder=Recorder(again, tmp_path / "again.mcap"))
    replayed = read_log(tmp_path / "again.mcap")
    for topic in data.layout.topics[:3]:
        for field in topic.fields:
            a, b = data.topics[topic.name][field.name], replayed.topics[topic.name][field.name]
            assert np.array_equal(a, b), f"{topic.name}.{field.name} differs"


def test_an_older_schemas_logs_read_as_written(tmp_path, monkeypatch) -> None:
    """A schema-2 log of a mapped session (q_mapped, tau_mapped; no MAPPED_STATE), written as
    that schema wrote it, reads back with its own fields, its metrics equal the live ones, and
    it replays bit for bit (no inputs logged: none fed)."""
    from teleop_rt.recording import recorder as rec
    from teleop_rt.recording.metrics import log_metrics

    layout_of = rec.session_layout
    monkeypatch.setattr(rec, "SCHEMA_VERSION", 2)
    monkeypatch.setattr(rec, "session_layout",
                        lambda s: dataclasses.replace(layout_of(s), version=2))  # fmt: skip
    cfg = config.load(CONFIGS / "foam.yaml", ["duration_s=0.5", "mapping.motion_scale=0.5"])
    session = Session(cfg)
    summary = session.run(recorder=Recorder(session, tmp_path / "v2.mcap"))
    monkeypatch.undo()
    data = read_log(tmp_path / "v2.mcap")
    assert data.meta["schema_version"] == "2" and data.layout.version == 2
    assert data.layout.mapped and "gain" not in data.topics["/hsi"].dtype.names
    assert "q_mapped" in data.topics["/to"].dtype.names
    m = log_metrics(data)
    assert m["t_p"] == summary.t_p and m["t_tau"] == summary.t_tau
    again, ticks = build_replay(data, [])
    again.run(ticks=ticks, recorder=Recorder(again, tmp_path / "again.mcap"))
    replayed = read_log(tmp_path / "again.mcap")
    assert replayed.layout.version == 3
    for topic in data.layout.topics[:3]:
        for field in topic.fields:
            a, b = data.topics[topic.name][field.name], replayed.topics[topic.name][field.name]
            assert np.array_equal(a, b), f"{topic.name}.{field.name} differs"
    # a schema-2 site log's /link has no engaged: its packets replay as "coupled"
    site = LogLayout(2, 1, "to", 2, 2, True, version=2)
    assert "engaged" not in {f.name for t in site.topics for f in t.fields}
