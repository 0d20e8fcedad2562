"""``teleop-rt site hsi|to CONFIG`` (one site, its own process, its own log) and ``teleop-rt run
CONFIG --link zenoh`` (both sites as child processes on this host, one combined summary).

Logs of ``run --link zenoh``: each site writes its own; ``--log out.mcap`` gives ``out.hsi.mcap``
and ``out.to.mcap`` (``site_log_path``), the default ``logs/<name>-<UTC time>.hsi.mcap`` and
``.to.mcap``; both are checked before either site starts, and neither is ever overwritten.
``--live HOST:PORT`` serves the HSI site at PORT and the TO site at PORT + 1 (port 0: two free
ones, chosen here and announced before the sites start)."""

from __future__ import annotations

import ctypes
import ctypes.util
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from teleop_rt.cli_common import incomplete_line, live_arg
from teleop_rt.errors import ConfigError
from teleop_rt.exit_signals import Terminated

# which exit code of the two sites the run gives (cmd_site's codes; docs/usage.md): a
# log that is not whole first, then a safety stop, a bad config, a peer that never answered,
# an error, the signals; 0 only if both sites ended well
EXIT_PRECEDENCE = (4, 3, 2, 5, 1, 129, 143, 130, 0)

CHILD_GRACE_S = 30.0  # after the run's duration: handshake, start-up, staged stop


def cmd_site(args, load_config, live=None) -> int:
    """One site: real time, its own loop, log and summary; exit as a run's (0, 3, 4, 5, 130,
    143: ``site_exit_code``)."""
    from teleop_rt.recording.recorder import create_log_file
    from teleop_rt.recording.site_log import default_pair_base, site_log_path
    from teleop_rt.report import print_site_summary
    from teleop_rt.site_run import run_site

    extra = [f"duration_s={args.duration}"] if args.duration is not None else []
    cfg = load_config(args, extra)
    if cfg.link.kind != "zenoh":
        cfg = cfg.model_copy(update={"link": cfg.link.model_copy(update={"kind": "zenoh"})})
    for line in insecure_warnings(cfg):
        print(f"teleop-rt: warning: {line}", file=sys.stderr)

    def waiting() -> None:  # once the handshake runs (a signal ends it from here on)
        if not args.json:
            print(f"{args.site} site: {cfg.duration_s:g} s at {cfg.rate_hz} Hz over Zenoh, "
                  f"waiting for the {'to' if args.site == 'hsi' else 'hsi'} site (Ctrl-C stops)",
                  file=sys.stderr, flush=True)  # fmt: skip

    record = Path(args.record_ticks) if args.record_ticks else None
    log = None
    if not args.no_log:
        log = (
            Path(args.log_out)
            if args.log_out
            else site_log_path(default_pair_base(cfg.name), args.site)
        )
        create_log_file(log).unlink()  # refused now (exists, no folder) rather than after start
    metadata = {"config": str(args.config),
                "overrides": json.dumps([*args.overrides, *extra])}  # fmt: skip

    def say(line: str) -> None:
        print(f"{args.site} site: {line}", file=sys.stderr, flush=True)

    def say_live(address) -> None:
        print(f"live: ws://{address} (Foxglove: Open connection, Foxglove WebSocket)",
              file=sys.stderr, flush=True)  # fmt: skip

    summary = run_site(cfg, args.site, realtime=True, overrun=args.overrun,
                       max_missed=args.max_missed, record=record, on_peer=say, log=log,
                       live=live, metadata=metadata, on_live=say_live,
                       on_wait=waiting, cpu=args.cpu)  # fmt: skip
    if args.json:
        json.dump(summary.to_dict(), sys.stdout, indent=2)
        print()
    else:
        print_site_summary(summary)
    status = summary.recording
    if status is not None and not status["complete"]:
        print(incomplete_line(summary.log, status), file=sys.stderr)
    if summary.peer_silent:
        print(f"teleop-rt: error: {summary.peer_silent}", file=sys.stderr)
    return site_exit_code(summary)


def site_exit_code(summary) -> int:
    """A run's exit code (``teleop_rt.cli_common.ending_code``: 4, 3, a signal's), and 5 for a run
    that ended otherwise well with a silent peer (``SiteSummary.peer_silent``: the run did not
    really run with it)."""
    from teleop_rt.cli_common import ending_code

    code = ending_code(summary, summary.recording)
    return 5 if code == 0 and summary.peer_silent else code


def site_failure(code: int, err: str) -> str:
    """What a site that gave no summary ended with: its own last line (``teleop-rt: ...``),
    else its exit, a signal by name. Not merely the last line of its stderr: after a SIGKILL
    that is what its helpers print (Python's resource tracker on the log's shared memory)."""
    own = [line for line in err.strip().splitlines() if line.startswith("teleop-rt:")]
    if own:
        return own[-1]
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name} (exit {code})"
        except ValueError:
            pass
    lines = err.strip().splitlines()
    return lines[-1] if lines and code >= 0 else f"exit {code}"


def check_network(cfg) -> None:
    """ConfigError if ``cfg`` cannot run its two sites over Zenoh (a delay under one tick, a
    TLS certificate that does not name its site's role: ``ZenohLink.check``), for ``check`` and
    ``run --link zenoh`` before any site starts, as each site refuses it after its warm-up."""
    from teleop_rt.com.zenoh_link import ZenohLink

    for site in ("hsi", "to"):
        ZenohLink.check(cfg, site)


def insecure_warnings(cfg) -> list[str]:
    """A warning for a link that reaches beyond loopback without TLS, allowed only by
    ``link.zenoh.allow_insecure`` (config.ZenohSpec refuses it otherwise)."""
    from teleop_rt.config import insecure_endpoints

    zenoh = cfg.link.zenoh
    exposed = insecure_endpoints(zenoh)
    if not exposed or not zenoh.allow_insecure:
        return []
    return [f"link.zenoh.allow_insecure: {', '.join(exposed)} without TLS: anyone who reaches "
            "it can drive the robots"]  # fmt: skip


def run_two_sites(args, cfg) -> int:
    """Both sites as child processes of this one (``teleop-rt site``), waited for; the pair's
    T_p and T_tau from their tick records; one combined summary."""
    from teleop_rt.report import print_pair_summary
    from teleop_rt.site_run import pair_transparency

    if not args.realtime:
        raise ConfigError("--link zenoh runs two processes in real time: add --realtime")
    if args.can_log is not None:
        raise ConfigError("--can-log records the buses of one process: not with --link zenoh")
    check_network(cfg)
    for line in insecure_warnings(cfg):
        print(f"teleop-rt: warning: {line}", file=sys.stderr)
    logs = _site_logs(args, cfg)
    lives = _live_addresses(args)
    if lives:
        print("live: " + ", ".join(f"{s} ws://{a}" for s, a in lives.items())
              + " (Foxglove: Open connection, Foxglove WebSocket)", file=sys.stderr,
              flush=True)  # fmt: skip
    cpus = sorted(os.sched_getaffinity(0))
    with tempfile.TemporaryDirectory(prefix="teleop-rt-sites-") as tmp:
        children: dict[str, subprocess.Popen] = {}
        stop: int | None = None  # a signal that came while the children were being started
        try:
            for index, site in enumerate(("hsi", "to")):
                # a CPU each where there are two (the real-time grant pins a loop to the last
                # CPU it may use: two spinning SCHED_FIFO loops on one CPU would take turns)
                cpu = {cpus[index % len(cpus)]} if len(cpus) > 1 else None
                children[site] = _start_site(_site_command(args, site, tmp, logs, lives), cpu)
        except Terminated as sig:
            stop = sig.signum
        except KeyboardInterrupt:
            stop = signal.SIGINT
        outs = _wait(children, cfg.duration_s + cfg.link.handshake_timeout_s + CHILD_GRACE_S,
                     stop)  # fmt: skip
        summaries, codes = {}, {}
        for site, (code, out, err) in outs.items():
            codes[site] = code
            try:
                summaries[site] = json.loads(out)
            except ValueError:
                summaries[site] = {"site": site, "error": site_failure(code, err)}
        files = [Path(tmp) / f"{s}.npz" for s in ("hsi", "to")]
        pair = None
        if all(f.exists() for f in files):
            t_p, t_tau, ticks = pair_transparency(files[0], files[1], cfg.dt)
            pair = {"ticks": ticks, "t_p": t_p, "t_tau": t_tau,
                    "t_p_total": sum(t_p), "t_tau_total": sum(t_tau)}  # fmt: skip
    combined = {"name": cfg.name, "link": "zenoh", "pair": pair, "sites": summaries,
                "exit_codes": codes,
                "logs": {s: str(p) for s, p in logs.items()} if logs else None}  # fmt: skip
    if args.json:
        json.dump(combined, sys.stdout, indent=2)
        print()
    else:
        print_pair_summary(combined)
    for s in summaries.values():  # each site's own lines (its stderr is not passed through)
        status = s.get("recording")
        if status is not None and not status["complete"]:
            print(incomplete_line(s["log"], status), file=sys.stderr)
        if s.get("peer_silent"):
            print(f"teleop-rt: error: {s['site']} site: {s['peer_silent']}", file=sys.stderr)
    if stop is not None and len(children) < 2:
        return 128 + stop  # stopped before both sites were started
    return worst_exit(codes.values())


def worst_exit(codes) -> int:
    """The exit code of two sites' run: the one a script must see first (``EXIT_PRECEDENCE``);
    a code not listed there (a child killed: negative) ranks after them, as 1."""
    ranked = [c if c in EXIT_PRECEDENCE else 1 for c in codes]
    return min(ranked, key=EXIT_PRECEDENCE.index, default=0)


def _site_command(args, site: str, tmp: str, logs, lives) -> list[str]:
    cmd = [sys.executable, "-m", "teleop_rt", "site", site, str(args.config), "--json",
           "--record-ticks", str(Path(tmp) / f"{site}.npz")]  # fmt: skip
    for o in args.overrides:
        cmd += ["--set", o]
    for side, name in args.backend:
        if side in ("", site):
            cmd += ["--backend", name]
    if args.duration is not None:
        cmd += ["--duration", str(args.duration)]
    cmd += ["--log", str(logs[site])] if logs else ["--no-log"]
    if lives:
        cmd += ["--live", str(lives[site])]
    if args.max_missed is not None:
        cmd += ["--max-missed", str(args.max_missed)]
    return [*cmd, "--overrun", args.overrun]


def _start_site(cmd: list[str], cpu: set[int] | None) -> subprocess.Popen:
    """A site process in a session of its own (a terminal's Ctrl-C reaches this process only,
    which passes it on once: ``_wait``) that stops as on SIGTERM when this process dies, even
    by SIGKILL: the kernel's parent-death signal (Linux). Started from the main thread: the
    signal follows the death of the thread that forked, not of the process."""
    parent = os.getpid()

    def in_child() -> None:  # after fork, before exec: no Python objects of the parent's
        if cpu:
            os.sched_setaffinity(0, cpu)
        if _LIBC is not None:
            _LIBC.prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)  # kept across exec
        if os.getppid() != parent:  # the parent died before prctl: it would never fire
            os.kill(os.getpid(), signal.SIGTERM)

    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True, preexec_fn=in_child)  # fmt: skip


def _libc() -> ctypes.CDLL | None:
    if not sys.platform.startswith("linux"):
        return None  # pragma: no cover - elsewhere only the signals this process sees pass on
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    except OSError:  # pragma: no cover
        return None


PR_SET_PDEATHSIG = 1  # <sys/prctl.h>
_LIBC = _libc()  # loaded before any fork: the child only calls it


def _site_logs(args, cfg) -> dict[str, Path] | None:
    """Each site's log path (None: --no-log); refused now if either exists."""
    from teleop_rt.recording.recorder import LogPathError
    from teleop_rt.recording.site_log import default_pair_base, site_log_path

    if args.no_log:
        return None
    base = Path(args.log_out) if args.log_out else default_pair_base(cfg.name)
    logs = {site: site_log_path(base, site) for site in ("hsi", "to")}
    for path in logs.values():
        if path.exists():
            raise LogPathError(f"--log {base}: {path} exists; choose another path")
    return logs


def _live_addresses(args) -> dict:
    """--live HOST:PORT: the HSI site at PORT, the TO at PORT + 1; port 0: two free ones."""
    from teleop_rt.recording.live import LiveAddress

    live = live_arg(args)
    if live is None:
        return {}
    if live.port == 0:
        ports = _free_ports(live.host, 2)
    elif live.port < 65535:
        ports = [live.port, live.port + 1]
    else:
        raise ConfigError(f"--live {live}: the TO site takes PORT + 1; choose a lower port")
    pairs = zip(("hsi", "to"), ports, strict=True)
    return {site: LiveAddress(live.host, port) for site, port in pairs}


def _free_ports(host: str, count: int) -> list[int]:
    import socket

    socks = []
    try:
        for _ in range(count):
            s = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET)
            socks.append(s)
            try:
                s.bind((host, 0))
            except OSError as err:
                raise ConfigError(f"--live {host}:0: cannot bind there ({err.strerror})") from None
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


def _wait(children: dict, timeout_s: float, stop: int | None = None) -> dict:
    """Wait for every child. A terminating signal here (SIGINT, SIGTERM, SIGHUP; ``stop``: one
    that came while they were being started) is passed on to each, once: each stops at a tick
    boundary, brings its robot to rest, finishes its log and exits 128 + the signal; later
    ones are ignored (``exit_on_signals``). Past the timeout, SIGTERM, then SIGKILL."""
    deadline = time.monotonic() + timeout_s
    passed_on = False
    killing = False
    while any(p.poll() is None for p in children.values()):
        if stop is not None and not passed_on:
            passed_on = True
            for p in children.values():
                _signal(p, stop)
        try:
            time.sleep(0.05)
        except Terminated as sig:
            stop = stop or sig.signum
        except KeyboardInterrupt:
            stop = stop or signal.SIGINT
        if time.monotonic() > deadline:
            if killing:
                for p in children.values():
                    _signal(p, signal.SIGKILL)
                break
            for p in children.values():
                _signal(p, signal.SIGTERM)
            deadline = time.monotonic() + 5.0
            killing = True
    return {site: (p.wait(), *p.communicate()) for site, p in children.items()}


def _signal(p: subprocess.Popen, signum: int) -> None:
    if p.poll() is None:
        try:
            os.kill(p.pid, signum)
        except ProcessLookupError:
            pass
