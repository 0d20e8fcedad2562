"""The link between two sites, measured against its floors in one run: raw UDP from Python,
bare zenoh-python with the project's settings, the two sites over Zenoh (``teleop-rt run
--link zenoh``) without and with the codec, alternated, and beside them the same config in one
process.

    python tools/bench_link.py [CONFIG] [--seconds 10] [--rounds 2] [--delay-ms 1]
                               [--set KEY=VALUE ...] [--json OUT] [--port P] [--no-codec]
                               [--fast-ticks N]

Every row runs two processes on this host, each pinned to a CPU of its own (the HSI's on the
first allowed CPU, the TO's on the second, as ``run --link zenoh`` does) under the loop's
real-time grant, exchanging a packet of a site's size every tick at 1 kHz; the rows run in
turn, ``--rounds`` times (``udp, zenoh, sites, codec, udp, ...``: the host's load moves all
alike). The floors (``tools/link_floor.py``) do nothing but send and receive. Printed per row
and direction: the one-way delay p50 / p99 (us, CLOCK_MONOTONIC on this host) of the packets
that arrived, the packets lost or late (beyond the playout rule at D = ``--delay-ms``; for a
floor, a delay over a tick), each process's CPU per tick (all its threads), for the sites
their tick compute and the ``put`` on the tick; then the ratios (sites / bare Zenoh, codec /
sites) against the goals of issues 27 and 24. The sites run without logs (their writer is a
process of its own: tools/bench.py times it) and with a peer timeout of ``--peer-timeout-ms``
(a stall of the shared host is then counted as late packets, not a stop); a run that fails
anyway is reported in its row and the others go on. ``--set`` overrides go to the sites'
runs; ``--sparse K`` adds bare Zenoh sending every Kth tick only (about the codec's rate).
Each round also runs the same two sites in fast mode (``fast_ticks``: the same tick and link
code back to back over a ``LoopbackTransport``, no Zenoh) and prints the real-time tick
compute against it (issue 27's goal: within 1.5 x).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from teleop_rt import config  # noqa: E402
from teleop_rt.errors import TeleopError  # noqa: E402
from teleop_rt.session import Session  # noqa: E402

SITES = ("hsi", "to")
START_LEAD_S = 2.0  # a floor's peers start their ticks this long after they were started
# issues 27, 24
GOALS = {"p50": 1.5, "cpu": 1.3, "bad_percent": 0.1, "codec_cpu": -30.0, "compute": 1.5}


def free_port() -> int:
    """A UDP port free on loopback whose successor is free too (a floor's TO takes P + 1)."""
    for _ in range(100):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as a:
            a.bind(("127.0.0.1", 0))
            port = a.getsockname()[1]
            try:
                with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as b:
                    b.bind(("127.0.0.1", port + 1))
                    return port
            except OSError:
                continue
    raise TeleopError("no two consecutive free UDP ports on 127.0.0.1")


def pinned(index: int):  # noqa: ANN201 - a preexec_fn
    cpus = sorted(os.sched_getaffinity(0))
    cpu = {cpus[index % len(cpus)]}
    return lambda: os.sched_setaffinity(0, cpu)


def floor(kind: str, seconds: float, port: int, every: int = 1) -> dict:
    """Both peers of a floor; per receiving site its figures (``tools/link_floor.py``)."""
    start = time.time_ns() + round(START_LEAD_S * 1e9)
    tool = str(ROOT / "tools" / "link_floor.py")
    procs = {
        site: subprocess.Popen(
            [
                sys.executable,
                tool,
                kind,
                site,
                "--port",
                str(port),
                "--start",
                str(start),
                "--seconds",
                str(seconds),
                "--every",
                str(every),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            preexec_fn=pinned(i),
        )  # fmt: skip
        for i, site in enumerate(SITES)
    }
    out = {}
    for site, p in procs.items():
        stdout, stderr = p.communicate(timeout=seconds + 60)
        if p.returncode != 0:
            last = (stderr.strip().splitlines() or [f"exit {p.returncode}"])[-1]
            raise TeleopError(f"the {kind} floor's {site} peer failed: {last}")
        r = json.loads(stdout)
        if r["one_way_us"] is None:
            raise TeleopError(f"the {kind} floor's {site} peer received nothing")
        out[site] = {"p50": r["one_way_us"]["p50"], "p99": r["one_way_us"]["p99"],
                     "bad": r["lost"] + r["late"], "due": r["due"],
                     "cpu_us": r["cpu_us_per_tick"]}  # fmt: skip
    return out


def two_sites(cfg_path: str, seconds: float, delay_ms: int, sets: list[str], port: int) -> dict:
    """``teleop-rt run --link zenoh``; per site what it received and what it spent."""
    at = f"udp/127.0.0.1:{port}"
    cmd = [sys.executable, "-m", "teleop_rt", "run", cfg_path, "--link", "zenoh", "--realtime",
           "--no-log", "--duration", str(seconds), "--json",
           "--set", f"channel.delay_ms={delay_ms}", "--set", f"link.zenoh.hsi.listen=[{at}]",
           "--set", f"link.zenoh.to.connect=[{at}]"]  # fmt: skip
    for o in sets:
        cmd += ["--set", o]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=seconds + 120, cwd=ROOT)
    try:
        both = json.loads(done.stdout)
    except ValueError:
        last = (done.stderr.strip().splitlines() or [f"exit {done.returncode}"])[-1]
        raise TeleopError(f"the two-site run failed: {last}") from None
    out = {}
    for site, other in zip(SITES, SITES[::-1], strict=True):
        s = both["sites"][site]
        if "error" in s or s.get("stopped_early"):
            raise TeleopError(f"the {site} site: {s.get('error') or s['stopped_early']}")
        link, peer = s["link"], s["link"]["from_peer"]
        d, put = link["one_way_delay_us"] or {}, link.get("put_us") or {}
        ticks = max(s["ticks"], 1)
        due = both["sites"][other]["link"]["sent"]  # what the peer sent (with a codec: few)
        out[site] = {"p50": d.get("p50", float("nan")), "p99": d.get("p99", float("nan")),
                     "bad": max(due - peer["received"], 0) + peer["late"], "due": due,
                     "cpu_us": 1e6 * s["cpu_s"] / ticks,
                     "compute_p50": s["timing"]["compute_us"]["p50"],
                     "put_p50": put.get("p50", float("nan")),
                     "put_max": put.get("max", float("nan")),
                     "sent": link["sent"] / ticks}  # fmt: skip
    return out


def fast_ticks(cfg_path: str, delay_ms: int, ticks: int) -> dict:
    """Each site's tick compute p50 (us) in fast mode: the same two sites, the same tick (what
    ``_SiteRun.step`` times: sense, update with the link's encoder and playout, the tick
    record) and the same ``ZenohLink`` code, back to back in one process over a
    ``LoopbackTransport`` (each tick's packet is handed to the peer's receive callback between
    ticks, untimed; no Zenoh ``put``). Runs in a child pinned to the first CPU."""
    cmd = [sys.executable, str(Path(__file__).resolve()), cfg_path, "--delay-ms", str(delay_ms),
           "--fast-probe", str(ticks)]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300, preexec_fn=pinned(0))
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or [f"exit {done.returncode}"])[-1]
        raise TeleopError(f"the fast-mode sites failed: {last}")
    return json.loads(done.stdout)


def fast_probe(cfg_path: str, delay_ms: int, ticks: int) -> dict:
    """``fast_ticks``'s child: per site the p50 and p99 of its tick compute, us, over the ticks
    after the first tenth."""
    import numpy as np

    from teleop_rt.com.wire import wire_size
    from teleop_rt.com.zenoh_link import LoopbackTransport, ZenohLink
    from teleop_rt.site import HsiSite, ToSite
    from teleop_rt.site_run import TickRecord

    cfg = config.load(cfg_path, [f"channel.delay_ms={delay_ms}"])
    sites = [HsiSite(cfg, None), ToSite(cfg, None)]
    links, records = [], []
    for site in sites:
        site.warm_up()
        link = ZenohLink(cfg, site.side, site.n, lambda site=site: site.tick,
                         LoopbackTransport(wire_size(site.n)))  # fmt: skip
        link.connect(1)
        link.start()
        links.append(link)
        records.append(TickRecord(ticks, site.n))
    a, b = (link.transport for link in links)
    compute = np.zeros((2, ticks), dtype=np.int64)
    perf = time.perf_counter_ns
    for k in range(ticks):
        for j, (site, link, record) in enumerate(zip(sites, links, records, strict=True)):
            t0 = perf()
            site.sense(link)
            site.update(link)
            record.add(site)
            compute[j, k] = perf() - t0
        a.deliver(b)  # type: ignore[attr-defined]
        b.deliver(a)  # type: ignore[attr-defined]
    used = [link.receiver.playout.counters()["used"] for link in links]  # type: ignore[union-attr]
    if min(used) < ticks // 2:
        raise TeleopError(f"the fast-mode sites used only {min(used)} of {ticks} packets")
    c = compute[:, ticks // 10 :] / 1e3
    return {site: {"p50": float(np.percentile(c[j], 50)), "p99": float(np.percentile(c[j], 99))}
            for j, site in enumerate(SITES)}  # fmt: skip


def one_process(cfg_path: str, seconds: float, delay_ms: int) -> float:
    """CPU per tick of the same config as one session (both sites, in-process link), us."""
    cfg = config.load(cfg_path, [f"channel.delay_ms={delay_ms}", f"duration_s={seconds}"])
    session = Session(cfg)
    cpu0 = time.process_time()
    summary = session.run(realtime=True)
    return 1e6 * (time.process_time() - cpu0) / max(summary.ticks, 1)


def median(runs: list[dict], site: str, key: str) -> float:
    return statistics.median(r[site][key] for r in runs)


def main() -> int:
    p = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    p.add_argument("config", nargs="?", default=str(ROOT / "configs" / "paper_experiment.yaml"),
                   help="session config (default: configs/paper_experiment.yaml)")  # fmt: skip
    p.add_argument("--seconds", type=float, default=10.0, help="each run, s (default 10)")
    p.add_argument("--rounds", type=int, default=2, help="alternated rounds (default 2)")
    p.add_argument("--delay-ms", type=int, default=1, help="the sites' channel delay, the "
                   "playout delay (default 1: one tick)")  # fmt: skip
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                   help="a config override for the sites' runs (repeatable)")  # fmt: skip
    p.add_argument("--json", type=Path, help="also write every run's figures as JSON")
    p.add_argument("--port", type=int, help="the first UDP port (default: free ones)")
    p.add_argument("--peer-timeout-ms", type=float, default=1000.0,
                   help="the sites' link.peer_timeout_ms (default 1000: this shared VM stalls a "
                   "process by 50-200 ms now and then; a stall is counted late here, not a "
                   "stop)")  # fmt: skip
    p.add_argument("--no-codec", action="store_true", help="leave out the codec's row")
    p.add_argument("--sparse", type=int, default=0, metavar="K",
                   help="also bare Zenoh on every Kth tick (a codec's rate)")  # fmt: skip
    p.add_argument("--fast-ticks", type=int, default=5000, metavar="N",
                   help="the sites' ticks in fast mode per round (default 5000)")  # fmt: skip
    p.add_argument("--fast-probe", type=int, default=0, help=argparse.SUPPRESS)  # (the child)
    args = p.parse_args()
    if args.fast_probe:  # fast_ticks's child: one JSON line
        print(json.dumps(fast_probe(args.config, args.delay_ms, args.fast_probe)))
        return 0
    if (not 0 < args.seconds <= 3600 or args.delay_ms < 1 or not 1 <= args.rounds <= 20
            or args.sparse < 0 or args.fast_ticks < 100):  # fmt: skip
        print("bench_link: error: --seconds in (0, 3600], --delay-ms >= 1, --rounds in [1, 20], "
              "--sparse >= 0, --fast-ticks >= 100", file=sys.stderr)  # fmt: skip
        return 2
    rows = ["udp", "zenoh", *(["sparse"] if args.sparse else []), "sites", "fast",
            *([] if args.no_codec else ["codec"])]  # fmt: skip
    runs: dict[str, list[dict]] = {row: [] for row in rows}
    failed: dict[str, list[str]] = {row: [] for row in rows}
    for r in range(args.rounds):
        for j, row in enumerate(rows):
            port = args.port + 2 * (r * len(rows) + j) if args.port else free_port()
            print(f"round {r + 1}/{args.rounds}: {row}, {args.seconds:g} s ...", file=sys.stderr)
            try:
                if row in ("udp", "zenoh"):
                    runs[row].append(floor(row, args.seconds, port))
                elif row == "sparse":
                    runs[row].append(floor("zenoh", args.seconds, port, args.sparse))
                elif row == "fast":
                    runs[row].append(fast_ticks(args.config, args.delay_ms, args.fast_ticks))
                else:
                    codec = ["channel.codec=deadband"] if row == "codec" else []
                    sets = [f"link.peer_timeout_ms={args.peer_timeout_ms:g}", *args.sets, *codec]
                    runs[row].append(two_sites(args.config, args.seconds, args.delay_ms, sets,
                                               port))  # fmt: skip
            except (TeleopError, subprocess.TimeoutExpired) as err:
                failed[row].append(str(err))
                print(f"  {row} failed: {err}", file=sys.stderr)
    try:
        local = one_process(args.config, args.seconds, args.delay_ms)
    except TeleopError as err:
        print(f"bench_link: error: {err}", file=sys.stderr)
        return 3
    report(args, runs, failed, local)
    if args.json:
        args.json.write_text(json.dumps({"runs": runs, "failed": failed,
                                         "one_process_cpu_us": local}, indent=1))  # fmt: skip
    return 0 if not any(failed.values()) else 3


def report(args: argparse.Namespace, runs: dict, failed: dict, local: float) -> None:
    names = {"udp": "raw UDP (Python)", "zenoh": "bare zenoh-python", "sites": "two sites",
             "codec": "two sites, codec", "sparse": f"bare Zenoh, 1/{args.sparse}",
             "fast": "sites, fast mode"}  # fmt: skip
    print(f"\n{Path(args.config).name}, 1 kHz, {args.rounds} alternated rounds of "
          f"{args.seconds:g} s, sites at D = {args.delay_ms} ms (medians over rounds; "
          "per direction: to the HSI / to the TO)")  # fmt: skip
    print(f"  {'':18s} {'one-way p50 (us)':>17s} {'p99 (us)':>15s} {'lost or late':>16s} "
          f"{'CPU/tick (us)':>15s} {'tick compute':>13s} {'put p50/max':>12s}")  # fmt: skip
    for row, rs in runs.items():
        if not rs:
            print(f"  {names[row]:18s} failed: {'; '.join(failed[row])}")
            continue
        if row == "fast":  # the tick alone: no link, no CPU of a run
            comp = " / ".join(f"{median(rs, s, 'p50'):.1f}" for s in SITES)
            print(f"  {names[row]:18s} {'':>17s} {'':>15s} {'':>16s} {'':>15s} {comp:>13s}")
            continue
        p50 = " / ".join(f"{median(rs, s, 'p50'):.0f}" for s in SITES)
        p99 = " / ".join(f"{median(rs, s, 'p99'):.0f}" for s in SITES)
        bad = sum(r[s]["bad"] for r in rs for s in SITES)
        due = sum(r[s]["due"] for r in rs for s in SITES)
        cpu = " / ".join(f"{median(rs, s, 'cpu_us'):.0f}" for s in SITES)
        line = (f"  {names[row]:18s} {p50:>17s} {p99:>15s} "
                f"{f'{bad} ({100 * bad / max(due, 1):.2f} %)':>16s} {cpu:>15s}")  # fmt: skip
        if row in ("sites", "codec"):
            comp = " / ".join(f"{median(rs, s, 'compute_p50'):.0f}" for s in SITES)
            worst = max(r[s]["put_max"] for r in rs for s in SITES)
            put = f"{median(rs, 'hsi', 'put_p50'):.0f}/{worst:.0f}"
            line += f" {comp:>13s} {put:>12s}"
            if row == "codec":
                line += f"  (sent {100 * median(rs, 'hsi', 'sent'):.1f} % of ticks)"
        if failed[row]:
            line += f"  [{len(failed[row])} failed: {failed[row][0]}]"
        print(line)
    print(f"  one process (both sites, in-process link): CPU {local:.0f} us per tick")
    zen, sites, codec = runs["zenoh"], runs["sites"], runs.get("codec", [])
    met = {True: "met", False: "MISSED"}
    if zen and sites:
        r_p50 = max(median(sites, s, "p50") / median(zen, s, "p50") for s in SITES)
        r_cpu = max(median(sites, s, "cpu_us") / median(zen, s, "cpu_us") for s in SITES)
        bad = max(100 * r[s]["bad"] / max(r[s]["due"], 1) for r in sites for s in SITES)
        print(f"  sites / bare Zenoh: one-way p50 x{r_p50:.2f} (goal <= {GOALS['p50']}: "
              f"{met[r_p50 <= GOALS['p50']]}), CPU per site x{r_cpu:.2f} (goal <= "
              f"{GOALS['cpu']}: {met[r_cpu <= GOALS['cpu']]}); lost or late, worst run and "
              f"direction {bad:.3f} % (goal <= {GOALS['bad_percent']} %: "
              f"{met[bad <= GOALS['bad_percent']]})")  # fmt: skip
    fast = runs.get("fast", [])
    if sites and fast:
        r_c = max(median(sites, s, "compute_p50") / median(fast, s, "p50") for s in SITES)
        r_n = max((median(sites, s, "compute_p50") - median(sites, s, "put_p50"))
                  / median(fast, s, "p50") for s in SITES)  # fmt: skip
        print(f"  sites' tick compute, real time / fast mode (the same tick and link code; fast "
              f"mode has no Zenoh put): x{r_c:.2f} (goal <= {GOALS['compute']}: "
              f"{met[r_c <= GOALS['compute']]}); without the put's p50 x{r_n:.2f}")  # fmt: skip
    if sites and codec:
        d = max(median(codec, s, "p50") / median(sites, s, "p50") for s in SITES)
        c = max(100 * (median(codec, s, "cpu_us") / median(sites, s, "cpu_us") - 1) for s in SITES)
        print(f"  codec / without: one-way p50 of the packets sent x{d:.2f} (goal: no worse), "
              f"CPU per site {c:+.0f} % (goal <= {GOALS['codec_cpu']:.0f} %: "
              f"{met[c <= GOALS['codec_cpu']]})")  # fmt: skip


if __name__ == "__main__":
    sys.exit(main())
