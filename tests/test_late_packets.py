"""Late packets used once they are due (issue 23): the ``newest`` playout rule against the
fixed one, on the ports alone and over two site processes.

The fixed rule plays the packet sent at k - D and drops one that comes later (after an outage
of 685 ticks at 30.7 ms against D = 10 ms: 685 ticks with no fresh sample). The ``newest`` rule
uses, at tick k, the newest packet that has arrived and was sent by k - D, if it is newer than
the last one used: a late packet once it arrives, never earlier than D, never twice. Checked
here: the ring hands out exactly that for any arrivals (against a plain model of the rule);
the ports fed by the real playout, late packets included, stay passive (each port's balance
and the two-port's own energy >= -1e-9 J), and the mutations that credit a late packet's
energy twice or use its wave without the energy rule are caught; two site processes over
Zenoh with late packets used log what their ports used, so that ``replay`` of each site's log
reproduces it bit for bit.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from teleop_rt.com.playout import Playout
from teleop_rt.com.port import HSI, TO, Packet, port_input, port_step
from teleop_rt.recording.reader import read_log
from tests.test_passive_channels import PASSIVE_J, Harness
from tests.test_playout import N, sent, taken
from tests.test_zenoh_sites import PAPER, PATIENT, endpoints, free_port


def newest_due(arrived: dict[int, int], k: int, d: int, last: int | None) -> int | None:
    """The rule in plain Python: the newest sender tick s <= k - D that has arrived by k
    (``arrived``: s -> its arrival tick) and is newer than ``last``."""
    due = [s for s, a in arrived.items() if a <= k and s <= k - d and (last is None or s > last)]
    return max(due, default=None)


@settings(max_examples=150, deadline=None)
@given(d=st.integers(1, 6), data=st.data())
def test_newest_uses_a_late_packet_once_it_arrives_and_never_before_d(d, data) -> None:
    """Random one-way delays, some far beyond D (as an outage), some packets lost: at every
    tick the ring hands out the newest due packet not older than the last one used."""
    ticks = 80
    lag = data.draw(st.lists(st.one_of(st.none(), st.integers(0, d + 30)), min_size=ticks,
                             max_size=ticks))  # fmt: skip
    arrived = {s: s + x for s, x in enumerate(lag) if x is not None}
    by_tick: dict[int, list[int]] = {}
    for s, a in arrived.items():
        by_tick.setdefault(a, []).append(s)
    playout, last, used = Playout(N, d, policy="newest"), None, 0
    for k in range(ticks + d + 40):
        for s in data.draw(st.permutations(by_tick.get(k, []))):
            playout.arrive(k, sent(s))
        want = newest_due(arrived, k, d, last)
        assert taken(playout, k) == want, k
        if want is not None:
            last, used = want, used + 1
    assert playout.counters()["used"] == used


# the budget sums the peer's terms in another order than the peer (catch-ups add differences
# of its running sums): rounding, far below the passivity tolerance
CREDIT_ROUNDING_J = 1e-12


class PlayedOut(Harness):
    """The harness's two ports, each direction through a real ``Playout`` of delay D: the
    network delays each packet by its lag (None: lost), the playout decides what is used."""

    def __init__(self, how: str, mode: str, policy: str, d: int, filter_hz: float | None,
                 n: int = 1) -> None:  # fmt: skip
        super().__init__(mode, how, n, filter_hz)
        self.mode, self.how = mode, how
        self.playouts = [Playout(n, d, policy=policy) for _ in (HSI, TO)]
        self.flight: list[dict[int, list[Packet]]] = [{}, {}]  # per receiver: arrival -> packets

    def run(self, inputs, lags) -> float:
        """Tick by tick: inputs (x_h, x_t) and each direction's lag per sender tick (to the
        TO, to the HSI); the lowest balance or two-port energy seen."""
        low = 0.0
        for k in range(len(inputs[0])):
            for side in (HSI, TO):
                port, tx = self.ports[side], self.tx[side]
                port_input(port.f, port.i, self.n, np.full(self.n, inputs[side][k]), tx.f)
                tx.tick = tx.seq = k
                tx.valid = 1
            for side in (HSI, TO):
                rx, playout = self.rx[side], self.playouts[side]
                for p in self.flight[side].pop(k, []):
                    playout.arrive(k, p)
                playout.take(k, rx)
                port_step(self.ports[side].f, self.ports[side].i, self.n, rx.f, rx.i,
                          self.tx[side].f)  # fmt: skip
            for side in (HSI, TO):
                lag = lags[side][k]
                if lag is not None:
                    copy = Packet(self.n)
                    copy.f[:], copy.i[:] = self.tx[side].f, self.tx[side].i
                    self.flight[1 - side].setdefault(k + lag, []).append(copy)
            low = min(low, self.lowest(), self.credit_room())
        return low

    def credit_room(self) -> float:
        """The least, over both ports and joints, of what the peer has declared (its wave
        energy sent, less under ``reflected`` what it used beyond its budget; TDPA: its E_in)
        minus this port's budget from it, J: the passivity proof's G_i <= D_j. Negative: a
        port credited energy the peer never declared (a late packet's counted twice)."""
        low = np.inf
        for side in (HSI, TO):
            port, peer = self.ports[side], self.ports[1 - side]
            if self.mode == "tdpa":
                gap = peer.e_in - port.peer_e_in
            elif self.how == "reflected":
                gap = peer.declared - port.got_energy
            else:
                gap = peer.wave_energy - port.got_energy
            low = min(low, float(gap.min()) + CREDIT_ROUNDING_J)
        return low


def outage_lags(ticks: int, d: int, period: int, late: int, extra: int) -> list[int]:
    """Each period: ``late`` packets ``extra`` ticks beyond D, then on time at D."""
    return [d + extra if k % period < late else 0 for k in range(ticks)]


def network(ticks: int, d: int):
    """Lags per tick and direction: runs of a constant lag (0 .. D + 40: on time, or late as
    an outage), losses; and each port's input, in runs, in [-5, 5]."""
    lag = st.lists(st.tuples(st.integers(1, 40), st.one_of(st.none(), st.integers(0, d + 40))),
                   min_size=1, max_size=12)  # fmt: skip
    signal = st.lists(st.tuples(st.integers(1, 60), st.floats(-5, 5, allow_nan=False)),
                      min_size=1, max_size=12)  # fmt: skip

    def expand(runs):
        out = [v for length, v in runs for _ in range(length)]
        return (out * (ticks // len(out) + 1))[:ticks]

    return st.tuples(lag.map(expand), lag.map(expand), signal.map(expand), signal.map(expand))


CHANNELS = [("bounded", "wave"), ("corrected", "wave"), ("reflected", "wave"),
            ("bounded", "tdpa")]  # fmt: skip


@settings(max_examples=120, deadline=None)
@given(schedule=network(240, 5), channel=st.sampled_from(CHANNELS),
       policy=st.sampled_from(["newest", "fixed"]),
       filter_hz=st.sampled_from([None, 30.0]))  # fmt: skip
def test_ports_fed_late_packets_by_the_playout_stay_passive(schedule, channel, policy,
                                                            filter_hz) -> None:  # fmt: skip
    to_to, to_hsi, x_h, x_t = schedule
    harness = PlayedOut(*channel, policy, 5, filter_hz)
    assert harness.run((x_h, x_t), (to_to, to_hsi)) >= PASSIVE_J


def outage_run(how: str, mode: str, policy: str, push: float, ticks: int = 4000) -> float:
    """The HSI swept at 1 rad/s peak (2 s period) against a TO pressed by ``push`` N m,
    D = 10 ticks, 30 Hz filter; every 1685 ticks the first 685 packets each way are 21 ticks
    late (the study's outages). The lowest balance or two-port energy seen."""
    d, t = 10, np.arange(ticks) * 1e-3
    lags = outage_lags(ticks, d, 1685, 685, 21)
    harness = PlayedOut(how, mode, policy, d, 30.0)
    return harness.run((np.cos(np.pi * t), np.full(ticks, push)), (lags, lags))


@pytest.mark.parametrize("channel", CHANNELS)
@pytest.mark.parametrize("push", [0.0, 2.0])
def test_through_the_studys_outages_late_packets_keep_the_ports_passive(channel, push) -> None:
    """Into each outage the delay jumps from D to D + 21 (21 ticks with nothing due), out of
    it back to D (21 packets passed over at once): each port and the two-port stay >= -1e-9 J
    with late packets used, in free space and pressed."""
    assert outage_run(*channel, "newest", push) >= PASSIVE_J


# --- two site processes over Zenoh: what each port used is in its log, replayed bit for bit


def late_trace(path: Path, d_ms: int) -> Path:
    """Every 500 ticks, 150 packets 45 ms on the way (later than D = 20 ms), the rest 5 ms."""
    rows = [f"{s},{45.0 if s % 500 < 150 else 5.0}" for s in range(500)]
    assert 45.0 > d_ms
    path.write_text("send_tick,delay_ms\n" + "\n".join(rows) + "\n")
    return path


@pytest.fixture(scope="module")
def late_pair(tmp_path_factory) -> dict:
    pytest.importorskip("zenoh")
    folder = tmp_path_factory.mktemp("late_pair")
    trace = late_trace(folder / "late.csv", 20)
    base = folder / "late.mcap"
    sets = ["channel.delay_ms=20", PATIENT[1], "link.playout=newest",
            "channel.wave_reconstruction=reflected",
            f"link.impairment={{seed: 3, trace: {trace}}}"]  # fmt: skip
    cmd = [sys.executable, "-m", "teleop_rt", "run", str(PAPER), "--link", "zenoh",
           "--realtime", "--duration", "3", "--json", "--log", str(base),
           *(x for s in sets for x in ("--set", s)), *endpoints(free_port())]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=240, cwd=folder)
    assert done.returncode == 0, done.stderr[-3000:]
    return {"folder": folder, "logs": {s: folder / f"late.{s}.mcap" for s in ("hsi", "to")},
            "summary": json.loads(done.stdout)}  # fmt: skip


@pytest.mark.parametrize("site", ["to", "hsi"])
def test_a_site_log_with_late_packets_used_replays_bit_for_bit(late_pair, site) -> None:
    """The log's /link holds each packet the port used (its sender tick: its sequence number)
    with its arrival; late ones among them (arrived more than D after they were sent, used
    then: never before D); the replay against those packets reproduces every signal."""
    data = read_log(late_pair["logs"][site])
    link = data.topics["/link"]
    used = link[link["valid"] == 1]
    late = used[used["arrival_tick"] - used["sender_tick"] > 20]
    assert len(late) > 100, len(late)  # the trace's late packets, used
    assert (used["tick"] - used["sender_tick"] >= 20).all()  # never before D
    assert (np.diff(used["sender_tick"]) > 0).all()  # never one twice, never an older one
    replay = late_pair["folder"] / f"replay.{site}.mcap"
    out = subprocess.run([sys.executable, "-m", "teleop_rt", "replay",
                          str(late_pair["logs"][site]), "--json", "--log", str(replay)],
                         capture_output=True, text=True, timeout=240)  # fmt: skip
    assert out.returncode == 0, out.stderr[-2000:]
    result = json.loads(out.stdout)
    assert result["identical"] and result["max_abs_q_difference_rad"] == 0.0
    again = read_log(replay)
    for topic in (f"/{site}", "/port", "/link"):
        for name in data.topics[topic].dtype.names:
            np.testing.assert_array_equal(data.topics[topic][name], again.topics[topic][name])
