"""Each site's own log, from the outside: ``teleop-rt run --link zenoh`` runs the two sites as
processes over Zenoh on 127.0.0.1 (once for this module: a few seconds of real time), each
writing its log and serving it live; then ``metrics HSI.mcap TO.mcap`` gives exactly the pair
figures the run printed, logs that do not pair are refused in one line, a damaged site log is
one line, a site log replays bit for bit against its partner's logged packets, and both live
views serve what their logs hold. (SIGKILL of one site: tests/test_zenoh_sites.py.)"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import START_LIMIT_S
from foxglove_ws import FoxgloveClient
from log_fixtures import write_synthetic_log
from mcap.reader import make_reader
from mcap.writer import Writer
from test_live import log_messages
from test_zenoh_sites import PAPER, PATIENT, endpoints, free_port

from teleop_rt import config
from teleop_rt.cli import main
from teleop_rt.com.impairment import Impairment, ImpairmentSpec
from teleop_rt.com.port import TO
from teleop_rt.recording.reader import read_log
from teleop_rt.session import Session

pytest.importorskip("zenoh")
pytest.importorskip("websockets")

DELAY = 20
SECONDS = 3
TICKS = SECONDS * 1000
COMMON = {"/port", "/link", "/timing", "/robot_description", "/tf"}
LIVE_TOPICS = {"hsi": COMMON | {"/hsi", "/hand_target"}, "to": COMMON | {"/to", "/environment"}}


class PairRun:
    """What a run left: its combined summary, the logs and, with ``live``, what a client of
    each site's live view received (site -> topic -> messages)."""

    def __init__(self, folder: Path, live: bool = False, seconds: float = SECONDS) -> None:
        self.folder = folder
        self.base = folder / "out.mcap"
        # the fixed rule: a packet is used at s + D or lost, what the fates below and /link's
        # checks state (under newest a stall of the loaded host lets a late packet be used
        # after D: 494 of 4000 in a run under 40 ms stalls; tests/test_late_packets.py)
        cmd = [sys.executable, "-m", "teleop_rt", "run", str(PAPER), "--link", "zenoh",
               "--realtime", "--duration", str(seconds), "--json", "--set",
               f"channel.delay_ms={DELAY}", "--set", "link.playout=fixed", *PATIENT,
               "--log", str(self.base), *endpoints(free_port())]  # fmt: skip
        self.logs = {s: folder / f"out.{s}.mcap" for s in ("hsi", "to")}
        if not live:
            done = subprocess.run(cmd, capture_output=True, text=True, timeout=240)
            assert done.returncode == 0, done.stdout[-3000:]
            self.combined = json.loads(done.stdout)
            return
        cmd += ["--live", "127.0.0.1:0"]
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            line = proc.stderr.readline()
            found = re.search(
                r"live: hsi ws://127\.0\.0\.1:(\d+), to ws://127\.0\.0\.1:(\d+)", line
            )
            assert found, line
            self.ports = {"hsi": int(found.group(1)), "to": int(found.group(2))}
            clients = self._connect()
            try:
                for site, client in clients.items():  # both subscribed before either reads
                    client.wait_for_topics(LIVE_TOPICS[site], timeout=60)
                    client.subscribe(LIVE_TOPICS[site])
                self.advertised = {s: {ch["topic"] for ch in c.channels.values()}
                                   for s, c in clients.items()}  # fmt: skip
                self.seen = {s: self._receive(c, LIVE_TOPICS[s]) for s, c in clients.items()}
                self.decoders = {s: {t: c.decoder(t) for t in LIVE_TOPICS[s]}
                                 for s, c in clients.items()}  # fmt: skip
            finally:
                for client in clients.values():
                    client.close()
            out, err = proc.communicate(timeout=240)
        finally:
            if proc.poll() is None:
                proc.kill()
        assert proc.returncode == 0, out[-3000:]
        self.combined = json.loads(out)

    def _connect(self) -> dict[str, FoxgloveClient]:
        """Both sites' clients, as soon as each server listens (once its process started)."""
        clients: dict[str, FoxgloveClient] = {}
        deadline = time.monotonic() + START_LIMIT_S
        while len(clients) < 2:
            for site in ("hsi", "to"):
                if site not in clients:
                    try:
                        clients[site] = FoxgloveClient(self.ports[site])
                    except OSError:
                        pass
            assert time.monotonic() < deadline, f"live views listening: {sorted(clients)}"
            time.sleep(0.05)
        return clients

    @staticmethod
    def _receive(client: FoxgloveClient, topics: set[str]) -> dict[str, list]:
        """The messages until every topic and three /tf frames came."""
        seen: dict[str, list] = {}

        def enough(messages) -> bool:
            seen.clear()
            for m in messages:
                seen.setdefault(m.topic, []).append(m)
            return set(seen) == topics and len(seen["/tf"]) >= 3

        client.receive(enough, timeout=60)
        return seen


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> PairRun:
    return PairRun(tmp_path_factory.mktemp("pair"))


def metrics(capsys, *argv: str) -> tuple[int, str, list[str]]:
    code = main(["metrics", *argv])
    out, err = capsys.readouterr()
    return code, out, err.strip().splitlines()


def fates(run: PairRun, receiver: str, path: Path) -> Path:
    """The packets the peer sent, as ``receiver`` met them, as an impairment trace: used at
    its tick (after a 1 ms flight, played out at tick s + D) or lost."""
    link = read_log(run.logs[receiver]).topics["/link"]
    used = set(link["sender_tick"][link["valid"] == 1].tolist())
    rows = [f"{s},1" if s in used else f"{s},lost" for s in range(TICKS)]
    path.write_text("send_tick,delay_ms\n" + "\n".join(rows) + "\n")
    return path


def test_two_processes_give_the_one_process_figures(run: PairRun, tmp_path) -> None:
    """The same config in one process, its link losing the very packets the two processes'
    link lost (the site logs say which: each direction's fate as an impairment trace), gives
    the pair's T_p and T_tau bit for bit: over the network the sites compute what they compute
    in one process, and the logs hold every packet's fate. (Without the losses the figures
    differ as far as the losses go: a few of 3000 on a quiet machine, ten times more on a
    loaded one; each zero wave shifts the TO for good, as the wave channel carries no
    position: the drift issue 17 deals with.)"""
    pair = run.combined["pair"]
    assert pair["ticks"] == TICKS and run.combined["exit_codes"] == {"hsi": 0, "to": 0}
    for name in ("hsi", "to"):
        link = run.combined["sites"][name]["link"]["from_peer"]
        # the link carried the run (a few lost of 3000 on a quiet host; the catch-up after
        # a loaded host's stalls drops more: 2596 received under 40 ms stalls), not a
        # threshold of the figures, which the losses replayed below give bit for bit
        assert link["received"] > TICKS / 2 and link["rejected"] == 0, link
        assert link["used"] + link["lost"] == TICKS - DELAY  # the first ticks have none due
    sets = [f"channel.delay_ms={DELAY}", f"duration_s={SECONDS}"]
    from_hsi = fates(run, "to", tmp_path / "from_hsi.csv")
    local = Session(config.load(PAPER, [*sets, f"link.impairment.trace={from_hsi}"]))
    spec = ImpairmentSpec(trace=fates(run, "hsi", tmp_path / "from_to.csv"))
    local.link.impairments[TO] = Impairment(spec, local.dt, stream=TO)  # the other direction's
    summary = local.run()
    assert summary.t_p == pair["t_p"] and summary.t_tau == pair["t_tau"]
    lossless = Session(config.load(PAPER, sets)).run()
    assert lossless.t_tau_total / 3 < pair["t_tau_total"] < 3 * lossless.t_tau_total


def test_the_two_site_logs_give_the_live_pair_figures(run: PairRun, capsys) -> None:
    """Bit for bit, whichever order the logs come in: the logs hold the q and tau each site's
    tick record held, and tick k of one is paired with tick k of the other."""
    pair = run.combined["pair"]
    assert run.combined["logs"] == {s: str(p) for s, p in run.logs.items()}
    for order in ((run.logs["hsi"], run.logs["to"]), (run.logs["to"], run.logs["hsi"])):
        code, out, err = metrics(capsys, *map(str, order), "--json")
        assert code == 0 and err == []
        figures = json.loads(out)
        for key in ("ticks", "t_p", "t_tau", "t_p_total", "t_tau_total"):
            assert figures[key] == pair[key], key
    code, out, _ = metrics(capsys, str(run.logs["hsi"]), str(run.logs["to"]))
    assert f"T_p total                    {pair['t_p_total']:.6g}" in out
    assert f"T_tau total                  {pair['t_tau_total']:.6g}" in out
    # what pairs them: one session, one start instant, the two sides
    logs = {s: read_log(p) for s, p in run.logs.items()}
    assert {d.site for d in logs.values()} == {"hsi", "to"}
    assert logs["hsi"].meta["session_id"] == logs["to"].meta["session_id"]
    assert logs["hsi"].start_ns == logs["to"].start_ns > 0
    for site, data in logs.items():
        assert not data.truncated and data.ticks == TICKS
        assert data.summary["recording"]["complete"] and data.summary["site"] == site


def test_each_tick_records_the_packet_it_used(run: PairRun) -> None:
    """/link: at tick k the peer's packet of tick k - D (the fixed rule), arrived by then,
    with its one-way delay; as many as the site's summary used; its
    contents are what the peer logged at its port that tick."""
    logs = {s: read_log(p) for s, p in run.logs.items()}
    for site, peer in (("hsi", "to"), ("to", "hsi")):
        link = logs[site].topics["/link"]
        used = link[link["valid"] == 1]
        summary = logs[site].summary["link"]["from_peer"]
        assert len(used) == summary["used"] > TICKS / 2  # (2203 under 40 ms stalls)
        assert (used["sender_tick"] == used["tick"] - DELAY).all()
        assert (used["arrival_tick"] - used["sender_tick"] <= DELAY).all()  # in time
        assert (used["one_way_delay_us"] > 0).all()
        none = link[link["valid"] == 0]
        assert (none["sender_tick"] == -1).all() and (none["x"] == 0).all()
        sent = logs[peer].topics["/port"][used["sender_tick"].astype(int)]
        x, wave = {"hsi": ("tau_t", "v_r"), "to": ("omega_c", "u_l")}[site]
        assert (used["x"] == sent[x]).all() and (used["wave"] == sent[wave]).all()


def rewrite(src: Path, dst: Path, **meta: str) -> None:
    """A copy of a log with some ``teleop_rt`` metadata changed (mcap's own writer)."""
    with open(src, "rb") as f, open(dst, "wb") as g:
        reader = make_reader(f)
        summary = reader.get_summary()
        w = Writer(g)
        w.start(profile="ros2", library="tests")
        ids = {}
        for sid, s in summary.schemas.items():
            ids[sid] = w.register_schema(s.name, s.encoding, s.data)
        chans = {c.id: w.register_channel(c.topic, c.message_encoding, ids[c.schema_id])
                 for c in summary.channels.values()}  # fmt: skip
        for record in reader.iter_metadata():
            data = dict(record.metadata)
            if record.name == "teleop_rt":
                data.update(meta)
            w.add_metadata(record.name, data)
        for a in reader.iter_attachments():
            w.add_attachment(a.create_time, a.log_time, a.name, a.media_type, a.data)
        for _, channel, m in reader.iter_messages():
            w.add_message(chans[channel.id], m.log_time, m.data, m.publish_time)
        w.finish()


def test_logs_that_do_not_pair_are_refused_in_one_line(run: PairRun, tmp_path, capsys) -> None:
    hsi, to = str(run.logs["hsi"]), str(run.logs["to"])
    session = write_synthetic_log(tmp_path / "session.mcap", 50).path
    other = tmp_path / "other.to.mcap"
    rewrite(run.logs["to"], other, session_id="123abc")
    moved = tmp_path / "moved.to.mcap"
    rewrite(run.logs["to"], moved, start_time_ns="1")
    cases = [
        ((hsi, hsi), "are both the hsi site's log"),
        ((hsi, str(session)), "is a session's log (both robots)"),
        ((str(session), to), "is a session's log (both robots)"),
        ((hsi, str(other)), "are logs of different sessions"),
        ((hsi, str(moved)), "start_time_ns"),
        ((hsi, to, to), "not 3"),
    ]
    for argv, said in cases:
        code, out, err = metrics(capsys, *argv)
        assert code == 2 and out == "", argv
        assert len(err) == 1 and err[0].startswith("teleop-rt: error:") and said in err[0], err
    # one site log alone has no pair figures: one line, naming what to give
    code, _, err = metrics(capsys, hsi)
    assert code == 2 and len(err) == 1 and "metrics HSI.mcap TO.mcap" in err[0], err


def test_a_damaged_site_log_is_one_line(run: PairRun, tmp_path, capsys) -> None:
    """Cut before its metadata: nothing to read (exit 2); cut half-way: the figures of the
    ticks it still holds, and one warning line (as for a session's log)."""
    head = tmp_path / "head.hsi.mcap"
    head.write_bytes(run.logs["hsi"].read_bytes()[:300])
    code, out, err = metrics(capsys, str(head), str(run.logs["to"]))
    assert code == 2 and out == "" and len(err) == 1 and str(head) in err[0], err
    half = tmp_path / "half.to.mcap"
    data = run.logs["to"].read_bytes()
    half.write_bytes(data[: len(data) // 2])
    code, out, err = metrics(capsys, str(run.logs["hsi"]), str(half), "--json")
    assert code == 0 and len(err) == 1 and "half.to.mcap" in err[0], err
    assert 0 < json.loads(out)["ticks"] < TICKS


def test_a_site_log_replays_bit_for_bit_against_its_partners_packets(
    run: PairRun, tmp_path
) -> None:
    """No overrides: every logged signal of the site again (exit 0); a change of the site's own
    gain changes it; a change of what both sites share is refused in one line."""
    replay = tmp_path / "replay.to.mcap"
    base = [sys.executable, "-m", "teleop_rt", "replay", str(run.logs["to"]), "--json"]
    out = subprocess.run([*base, "--log", str(replay)], capture_output=True, text=True,
                         timeout=240)  # fmt: skip
    assert out.returncode == 0, out.stderr[-2000:]
    result = json.loads(out.stdout)
    assert result["identical"] and result["max_abs_q_difference_rad"] == 0.0
    assert result["original"] == result["replay"]
    original, again = read_log(run.logs["to"]), read_log(replay)
    for topic in ("/to", "/port", "/link"):
        for name in original.topics[topic].dtype.names:
            np.testing.assert_array_equal(original.topics[topic][name], again.topics[topic][name])
    assert again.meta["replay_of"] == str(run.logs["to"])
    changed = subprocess.run([*base, "--no-log", "--set", "to.controller.kp=50"],
                             capture_output=True, text=True, timeout=240)  # fmt: skip
    assert changed.returncode == 0, changed.stderr[-2000:]
    result = json.loads(changed.stdout)
    assert not result["identical"] and result["max_abs_q_difference_rad"] > 0
    refused = subprocess.run([*base, "--no-log", "--set", "channel.delay_ms=40"],
                             capture_output=True, text=True, timeout=240)  # fmt: skip
    lines = refused.stderr.strip().splitlines()
    assert refused.returncode == 2 and len(lines) == 1 and "delay_ticks" in lines[0], lines


def test_each_site_is_served_live_as_its_log_holds(tmp_path) -> None:
    """``run --link zenoh --live 127.0.0.1:0``: two servers (the HSI at the first port, the TO
    at the second), each with its site's topics only, its robot alone in the URDF, and the
    messages its log holds at the same log times. (A run of its own: two live views and their
    clients load this 2-core machine enough to lose packets, which the figures' test above
    must not meet.)"""
    run = PairRun(tmp_path, live=True, seconds=2)
    assert run.combined["exit_codes"] == {"hsi": 0, "to": 0}
    for site in ("hsi", "to"):
        assert run.advertised[site] == LIVE_TOPICS[site]
        seen, decode = run.seen[site], run.decoders[site]
        urdf = decode["/robot_description"](seen["/robot_description"][0].payload).data
        assert f"{site}/shoulder" in urdf and ("to/" if site == "hsi" else "hsi/") not in urdf
        for topic in LIVE_TOPICS[site]:
            stored = log_messages(run.logs[site], topic)
            for m in seen[topic][-3:]:
                assert m.payload in stored[m.log_time], (site, topic)


def test_run_link_zenoh_refuses_a_log_pair_that_exists(tmp_path) -> None:
    """Both site logs are checked before either site starts: one line, exit 2, nothing run."""
    (tmp_path / "x.to.mcap").write_bytes(b"")
    cmd = [
        sys.executable,
        "-m",
        "teleop_rt",
        "run",
        str(PAPER),
        "--link",
        "zenoh",
        "--realtime",
        "--set",
        "channel.delay_ms=20",
        "--log",
        str(tmp_path / "x.mcap"),
    ]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "x.to.mcap exists" in lines[0], lines
    assert not (tmp_path / "x.hsi.mcap").exists()


def test_plot_draws_the_two_site_logs_as_one_session(run: PairRun, tmp_path, capsys,
                                                     monkeypatch) -> None:  # fmt: skip
    """``plot HSI.mcap TO.mcap`` (either order) pairs the logs by tick as ``metrics`` does:
    each angle and torque axis holds the HSI's and the TO's own logged values, the channel
    energy is the two ports' sum; a site log alone, or with a session's, is one line, exit 2."""
    from test_log_plot import _captured_figures

    figures = _captured_figures(monkeypatch)
    logs = {s: read_log(p) for s, p in run.logs.items()}
    for k, order in enumerate(((run.logs["hsi"], run.logs["to"]),
                               (run.logs["to"], run.logs["hsi"]))):  # fmt: skip
        out = tmp_path / f"pair{k}.png"
        assert main(["plot", *map(str, order), "-o", str(out)]) == 0
        assert out.stat().st_size > 20_000 and f"wrote {out}" in capsys.readouterr().out
    for fig in figures:
        h, t = logs["hsi"].topics["/hsi"], logs["to"].topics["/to"]
        for j in range(logs["hsi"].layout.n):
            to_q, hsi_q = fig.axes[2 * j].get_lines()
            np.testing.assert_array_equal(hsi_q.get_ydata(), h["q"][:, j])
            np.testing.assert_array_equal(to_q.get_ydata(), t["q"][:, j])
            tau_e, tau_h = fig.axes[2 * j + 1].get_lines()
            np.testing.assert_array_equal(tau_h.get_ydata(), h["tau_ext"][:, j])
            np.testing.assert_array_equal(tau_e.get_ydata(), -t["tau_ext"][:, j])
        (energy,) = [a for a in fig.axes if a.get_ylabel() == "channel energy (J)"][0].get_lines()
        ports = (logs["hsi"].topics["/port"]["total_energy"]
                 + logs["to"].topics["/port"]["total_energy"])  # fmt: skip
        np.testing.assert_array_equal(energy.get_ydata(), ports)
        assert "two site logs paired by tick" in fig.get_suptitle()
        assert any(a.get_title().startswith("tool paths") for a in fig.axes)
    session = write_synthetic_log(tmp_path / "session.mcap", 50).path
    for argv, words in (
        ([str(run.logs["hsi"])], "is the hsi site's log, one robot: plot it with its partner's"),
        ([str(run.logs["hsi"]), str(session)], "plot takes it alone"),
        ([str(run.logs["hsi"])] * 3, "plot takes one log or the two logs"),
    ):
        assert main(["plot", *argv, "-o", str(tmp_path / "no.png")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], err
    assert not (tmp_path / "no.png").exists()
