"""Packets lost, counted honestly with the codec on (issue 24): a codec's silence is a tick with
no packet that is no loss. Each packet carries its number (how many its sender had sent before
it: ``teleop_rt.com.wire``), and the receiver counts a packet lost only where the number of the
packets it uses jumps (``teleop_rt.com.playout``); the ticks with no packet are counted apart
(``silent_ticks``). Without the codec the per-tick figures stay what they were."""

from __future__ import annotations

import pytest

from teleop_rt import config
from teleop_rt.com.impaired_link import ImpairedLink
from teleop_rt.com.playout import USED_NUMBER, Receiver
from teleop_rt.com.port import HSI, TO, Packet
from teleop_rt.com.wire import IMPLAUSIBLE, OK, WireBuffer, encode_into
from teleop_rt.session import Session
from tests.conftest import CONFIGS

D, TICKS = 20, 3000  # the playout delay, ticks; the run's ticks (3 s at 1 kHz)
SID = 77


def codec_session(k: int | None, playout: str, codec: str = "deadband") -> tuple[Session, list]:
    """The stiff wall at D = 20 ms through the impaired link (seeded, nothing impaired by the
    stage itself), the codec on; with ``k`` each direction drops exactly every k-th packet
    its site sends (the numbers of those dropped, per sending side)."""
    sets = ["duration_s=3", f"channel.delay_ms={D}", f"channel.codec={codec}",
            f"link.playout={playout}", "link.impairment={seed: 3}"]  # fmt: skip
    s = Session(config.load(CONFIGS / "stiff_wall.yaml", sets))
    assert isinstance(s.link, ImpairedLink)
    dropped: list[list[int]] = [[], []]
    if k is not None:
        for side, imp in enumerate(s.link.impairments):
            decide, calls = imp.decide, [0]

            def every_kth(send_tick: int, decide=decide, calls=calls, out=dropped[side]) -> int:
                number = calls[0]  # the link calls it once per packet sent, in order
                calls[0] += 1
                if (number + 1) % k == 0:
                    out.append(number)
                    return 0
                return decide(send_tick)

            imp.decide = every_kth  # type: ignore[method-assign]
    s.summary = s.run()
    return s, dropped


@pytest.mark.parametrize("playout", ["fixed", "newest"])
def test_every_kth_packet_dropped_is_lost_and_the_silences_are_not(playout: str) -> None:
    k = 5
    s, dropped = codec_session(k, playout)
    assert isinstance(s.link, ImpairedLink)
    for side, name, peer in ((HSI, "hsi", "to"), (TO, "to", "hsi")):
        rx = s.summary.link[name]
        codec = s.summary.channel["codec"][peer]
        sent = codec["sent"]
        assert rx["sent"] == sent and sent < 0.3 * TICKS  # the codec was at work
        # the packets dropped before the last one used (those after it are not known yet)
        last = int(s.link.receivers[side].playout.st[USED_NUMBER])
        known = [m for m in dropped[1 - side] if m < last]
        assert len(known) == last // k  # (the numbers k - 1, 2k - 1, ... below it)
        assert rx["lost"] == len(known) > 0, rx
        assert rx["skipped"] == rx["late"] == rx["duplicated"] == 0
        assert rx["received"] == sent - len(dropped[1 - side])
        # the ticks with no packet: every silence of the codec, and each loss
        played = TICKS - D
        assert rx["silent_ticks"] == played - rx["used"] > 0.7 * played
        after = [m for m in range(last + 1, sent) if m not in dropped[1 - side]]
        assert rx["used"] == rx["received"] - len(after)  # (the rest: still in flight)


def test_a_clean_link_with_the_codec_loses_nothing() -> None:
    s, _ = codec_session(None, "newest")
    for name, peer in (("hsi", "to"), ("to", "hsi")):
        rx = s.summary.link[name]
        assert rx["lost"] == rx["skipped"] == 0
        assert rx["received"] == s.summary.channel["codec"][peer]["sent"]
        assert rx["silent_ticks"] == TICKS - D - rx["used"] > 0


def test_without_the_codec_a_lost_packet_is_a_tick_with_none() -> None:
    """The per-tick figures, as they were: no ``silent_ticks``, each lost packet a tick."""
    s, dropped = codec_session(5, "fixed", codec="none")
    for side, name in ((HSI, "hsi"), (TO, "to")):
        rx = s.summary.link[name]
        assert "silent_ticks" not in rx
        assert rx["lost"] == len([m for m in dropped[1 - side] if m < TICKS - D])
        assert rx["used"] + rx["lost"] == TICKS - D


def wire(tick: int, number: int) -> bytes:
    p = Packet(2)
    p.tick = p.seq = tick
    p.valid = 1
    return bytes(encode_into(WireBuffer(2), p, SID, 0, TO, number))


def test_a_forged_number_counts_no_more_than_its_ticks_and_stales_nothing() -> None:
    """A well-formed forged packet (only TLS stops one) between a codec's packets, sent every
    7 ticks and numbered 0, 1, 2, ...: its number can jump at most as far as its tick (beyond:
    ``implausible``), so it makes at most the ticks since the last packet used look lost (what
    the per-tick rule counted), and every genuine packet after it is still used."""
    rx, into = Receiver(2, D, SID, TO, codec=True), Packet(2)
    genuine = list(range(0, 140, 7))
    assert rx.arrive(0, wire(4, 5)) == IMPLAUSIBLE  # a number beyond its tick
    used = []
    for k in range(200):
        if k in genuine:
            assert rx.arrive(k, wire(k, genuine.index(k))) == OK
        if k == 10:
            assert rx.arrive(k, wire(10, 10)) == OK  # forged: as far as a number may jump
        if rx.take(k, into):
            used.append(into.tick)
    assert used == sorted([*genuine, 10])  # no genuine packet stale, none skipped
    stats = rx.stats()
    # the forged one: 10 - 7 - 1 = 2 "lost" (the ticks 8 and 9), never more; the genuine
    # packet after it (number 2) jumps back, and the next ones count nothing
    assert stats["lost"] == 2 and stats["skipped"] == 0
    assert stats["rejected_by_reason"] == {"implausible": 1}
