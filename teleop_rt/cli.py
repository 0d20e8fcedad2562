"""Command line: ``teleop-rt run | check | info | metrics | replay | plot | bode``.

Anything that is the user's input's fault ends as one line on stderr and a non-zero exit code
(2 for a bad config or argument), never a traceback. ``run`` and ``replay`` exit with 0 (a
complete run and log), 3 (a safety stop, ``--overrun stop``, ``--max-missed``), 4 (the log is
incomplete: its writer stalled, died or could not write), 130 / 143 (ended by SIGINT / SIGTERM).
Output files (plots, JSON) are checked before any work and never overwritten without ``--force``
(``teleop_rt.output``); logs are never overwritten at all.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from teleop_rt.cli_common import EXIT_INTERRUPTED, ending_code, incomplete_line, live_arg
from teleop_rt.declarations import OVERRUN_DEFAULT, OVERRUN_POLICIES
from teleop_rt.errors import ConfigError, RecordingFailure, TeleopError
from teleop_rt.exit_signals import Terminated, exit_on_signals
from teleop_rt.std_streams import guarded
from teleop_rt.version import software_version


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="teleop-rt",
        description="1 kHz haptic bilateral teleoperation (Kuschel & Buss architecture).",
    )
    # what the logs record: the release with the git commit when run from a checkout
    parser.add_argument("--version", action="version", version=f"teleop-rt {software_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def add_overrun_arg(p: argparse.ArgumentParser, what: str) -> None:
        p.add_argument("--overrun", choices=OVERRUN_POLICIES, default=OVERRUN_DEFAULT,
                       help=f"{what} (default: {OVERRUN_DEFAULT})")  # fmt: skip

    def add_backend_arg(p: argparse.ArgumentParser, one_robot: bool = False) -> None:
        # a site runs one robot: its backend is just NAME (hsi:/to: would name the other too)
        p.add_argument(
            "--backend",
            type=_backend_arg,
            action="append",
            default=[],
            metavar="NAME" if one_robot else "[hsi:|to:]NAME",
            help="backend of this site's robot instead of the config's: --backend can"
            if one_robot
            else "backend instead of the config's, for both robots or one of them "
            "(repeatable): --backend can, --backend hsi:can --backend to:sim",
        )

    def add_config_args(p: argparse.ArgumentParser) -> None:
        p.add_argument("config", help="session config (YAML), e.g. configs/paper_experiment.yaml")
        add_set_arg(p, "override a config value, e.g. --set channel.delay_ms=50 (repeatable)")

    run = sub.add_parser("run", help="run a session and print its summary")
    add_config_args(run)
    run.add_argument("--duration", type=_positive_float, metavar="S", help="seconds to run")
    run.add_argument(
        "--realtime",
        action="store_true",
        help="pace ticks to the wall clock (default: fast mode, as fast as possible)",
    )
    add_overrun_arg(run, "what a late tick does in real-time mode")
    run.add_argument(
        "--max-missed",
        type=_non_negative_int,
        metavar="N",
        help="real-time mode: a safety stop (exit 3) at the (N+1)th missed deadline",
    )
    add_backend_arg(run)
    run.add_argument(
        "--link",
        choices=["inprocess", "zenoh"],
        help="what joins the two sites: one process (default, the config's link.kind) or two "
        "processes over Zenoh (teleop-rt site hsi / to as children; needs --realtime)",
    )
    run.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    add_keys_arg(run)
    add_log_args(run)
    run.add_argument(
        "--live",
        nargs="?",
        const="127.0.0.1:8765",
        metavar="[HOST:]PORT",
        help="serve the session live to Foxglove (WebSocket; default 127.0.0.1:8765, port 0: "
        "any free one), 3D included; with --link zenoh the HSI site at PORT, the TO at PORT+1",
    )
    run.add_argument(
        "--can-log",
        metavar="PATH",
        help="record every frame of every CAN bus (python-can's writers, format by extension: "
        ".asc, .blf, .log, .csv, .trc, .txt; never overwrites)",
    )

    site = sub.add_parser("site", help="run one site (hsi or to) against its peer over Zenoh")
    site.add_argument("site", choices=["hsi", "to"], help="which site this process runs")
    add_config_args(site)
    site.add_argument("--duration", type=_positive_float, metavar="S", help="seconds to run")
    add_overrun_arg(site, "what a late tick does")
    site.add_argument("--max-missed", type=_non_negative_int, metavar="N",
                      help="a safety stop (exit 3) at the (N+1)th missed deadline")  # fmt: skip
    add_backend_arg(site, one_robot=True)
    site.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    add_keys_arg(site)
    add_log_args(site, "logs/<name>-<UTC time>.<site>.mcap")
    site.add_argument(
        "--live", nargs="?", const="127.0.0.1:8765", metavar="[HOST:]PORT",
        help="serve this site live to Foxglove (WebSocket; default 127.0.0.1:8765, port 0: any "
        "free one), from its log's writer",
    )  # fmt: skip
    site.add_argument(
        "--cpu", type=_non_negative_int, metavar="N",
        help="pin the loop to CPU N (default: the HSI the last CPU it may use, the TO the one "
        "before, so that two sites on one host spin on different CPUs)",
    )  # fmt: skip
    site.add_argument("--record-ticks", metavar="NPZ", help=argparse.SUPPRESS)  # for run --link

    check = sub.add_parser("check", help="validate a config (and load its robots) without running")
    add_config_args(check)
    add_backend_arg(check)
    check.add_argument(
        "--print",
        dest="print_config",
        action="store_true",
        help="print the resolved config (overrides applied, every default filled in) as YAML",
    )

    info = sub.add_parser("info", help="what a log holds: start, duration, topics, session, status")
    info.add_argument("log", help="an MCAP log written by teleop-rt run, site or replay")
    info.add_argument("--json", action="store_true", help="print it as JSON")

    metrics = sub.add_parser(
        "metrics", help="transparency, energy and timing figures of a log, or of two sites' logs"
    )
    metrics.add_argument(
        "log", nargs="+", metavar="LOG",
        help="an MCAP log written by teleop-rt run or replay, or the two logs of one session's "
        "sites (teleop-rt site, run --link zenoh): HSI.mcap TO.mcap",
    )  # fmt: skip
    metrics.add_argument("--json", action="store_true", help="print the figures as JSON")
    metrics.add_argument("--from", dest="t_from", type=float, metavar="S", help="start time, s")
    metrics.add_argument("--to", dest="t_to", type=float, metavar="S", help="end time, s")

    replay = sub.add_parser(
        "replay", help="re-simulate a log with its operator input (and --set overrides)"
    )
    replay.add_argument(
        "log", help="an MCAP log written by teleop-rt run, or a site's log (teleop-rt site)"
    )
    add_set_arg(replay, "change the logged session, e.g. --set channel.delay_ms=100 (repeatable)")
    replay.add_argument("--json", action="store_true", help="print both summaries as JSON")
    replay.add_argument(
        "--plot", metavar="IMAGE", help="also plot the replay (format by extension: .png, .pdf)"
    )
    add_force_arg(replay, "--plot")
    add_log_args(replay, "logs/<name>-replay-<UTC time>.mcap")

    plot = sub.add_parser(
        "plot", help="plot HSI vs TO angles and torques, tool paths and the channel energy"
    )
    plot.add_argument(
        "log", nargs="+", help="an MCAP log, or the two logs of one session's sites (HSI, TO)"
    )
    plot.add_argument(
        "-o",
        "--output",
        metavar="IMAGE",
        help="image to write, format by extension: .png, .pdf, .svg, ... (default: LOG.png)",
    )
    add_force_arg(plot, "the image")
    plot.add_argument("--from", dest="t_from", type=float, metavar="S", help="start time, s")
    plot.add_argument("--to", dest="t_to", type=float, metavar="S", help="end time, s")

    bode = sub.add_parser(
        "bode", help="measure the displayed impedance Z_h(j omega) and compare with the models"
    )
    add_config_args(bode)
    bode.add_argument("--json", dest="json_out", metavar="OUT", help="write JSON ('-': stdout)")
    bode.add_argument(
        "--plot", metavar="IMAGE", help="magnitude and phase plot (format by extension)"
    )
    add_force_arg(bode, "the --json and --plot files")
    bode.add_argument("--joint", type=int, default=1, help="excited joint, 0-based (default 1)")
    bode.add_argument("--omegas", metavar="W1,W2,...", help="frequencies, rad/s")
    bode.add_argument("--omega-min", type=float, default=0.5, help="rad/s (default 0.5)")
    bode.add_argument("--omega-max", type=float, default=50.0, help="rad/s (default 50)")
    bode.add_argument("--points", type=int, default=20, help="log-spaced points (default 20)")
    bode.add_argument(
        "--amplitude", type=float, default=0.05, help="omega_o amplitude, rad/s (default 0.05)"
    )
    for name, unit in (("stiffness", "N m/rad"), ("damping", "N m s/rad"), ("mass", "kg m^2")):
        bode.add_argument(
            f"--env-{name}",
            type=float,
            default=None,
            help=f"joint-space environment Z_e of the excited joint, {unit} (default: the "
            "config's environment at the TO's start pose; any --env-* replaces all of it, "
            "the others 0)",
        )
    bode.add_argument(
        "--max-seconds",
        type=float,
        default=60.0,
        help="simulated seconds per frequency (at least 3 windows) before it counts as not "
        "settled (default 60, at most 3600)",
    )
    return parser


def add_set_arg(p: argparse.ArgumentParser, help_text: str) -> None:
    p.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE", help=help_text
    )


def add_keys_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--keys", action="store_true",
        help="the terminal's keys are the operator's inputs: space or c toggles the clutch, p "
        "the presence (mapping.keys; give it to both sites: the TO follows the HSI's)",
    )  # fmt: skip


def keys_override(args: argparse.Namespace) -> None:
    """--keys as the config's ``mapping.keys``: in the log's config and overrides, and passed on
    to the sites of ``run --link zenoh``."""
    if getattr(args, "keys", False):
        args.overrides = [*args.overrides, "mapping.keys=true"]


def add_force_arg(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--force", action="store_true", help=f"overwrite {what} if it exists")


def add_log_args(p: argparse.ArgumentParser, default: str = "logs/<name>-<UTC time>.mcap") -> None:
    group = p.add_mutually_exclusive_group()
    group.add_argument(
        "--log",
        dest="log_out",
        metavar="PATH",
        type=_log_path,
        help=f"MCAP log to write (default: {default}; never overwrites)",
    )
    group.add_argument("--no-log", action="store_true", help="do not record this run")


def _log_path(text: str) -> str:
    """An empty --log would fall back to the default path: refused instead."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path; give a file name (or --no-log)")
    return text


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive finite number, got {text!r}")
    return value


def _backend_arg(value: str) -> tuple[str, str]:
    """``NAME`` (both robots) or ``hsi:NAME`` / ``to:NAME``: (side or '', name)."""
    side, sep, name = value.rpartition(":")
    if sep and side not in ("hsi", "to"):
        raise argparse.ArgumentTypeError(f"{value!r}: the robot is 'hsi' or 'to' (hsi:NAME)")
    if not name:
        raise argparse.ArgumentTypeError(f"{value!r}: a backend name is missing")
    return side, name


def _backend_overrides(choices: list[tuple[str, str]]) -> list[str]:
    """--backend choices as config overrides: a name for both replaces each robot's too."""
    out = []
    for side, name in choices:
        sides = [side] if side else ["hsi", "to"]
        out += ([] if side else [f"backend={name}"]) + [f"{s}.backend={name}" for s in sides]
    return out


def _non_negative_int(text: str) -> int:
    if not text.isdigit() or len(text) > 18:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 0, got {text!r}")
    return int(text)


def _load_config(args: argparse.Namespace, extra: list[str] | None = None):
    from teleop_rt import config

    backends = _backend_overrides(getattr(args, "backend", None) or [])
    return config.load(args.config, [*args.overrides, *backends, *(extra or [])])


def _backends_text(cfg) -> str:
    hsi, to = cfg.backend_for("hsi"), cfg.backend_for("to")
    return hsi if hsi == to else f"hsi {hsi}, to {to}"


def _cmd_check(args: argparse.Namespace) -> int:
    from teleop_rt.session import Session

    cfg = _load_config(args)
    session = Session(cfg)  # builds models and backends: catches joint-count mismatches too
    if cfg.link.kind == "zenoh":  # what each site refuses at its start (run --link zenoh too)
        from teleop_rt.cli_sites import check_network

        check_network(cfg)
    _start_within_limits(session)
    _print_warnings(session)
    from teleop_rt.analysis.free_space_probe import free_space_stop

    stop = free_space_stop(cfg)
    if stop is not None:
        raise ConfigError(
            f"channel.wave_filter_hz: null: this unfiltered wave channel (delay "
            f"{cfg.delay_ticks} ticks) stops in free space on a clean link ({stop}); set "
            "channel.wave_filter_hz (30 damps it)"
        )
    if args.print_config:
        import yaml

        print(yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False), end="")
        return 0
    print(
        f"{args.config}: ok ({session.n} joints, {cfg.n_ticks} ticks at {cfg.rate_hz} Hz, "
        f"delay {cfg.delay_ticks} ticks, backends {_backends_text(cfg)})"
    )
    return 0


def _start_within_limits(session) -> None:
    """ConfigError for a simulated robot whose start (``robot.q0_rad``, default zeros) is
    outside its joint limits: its guard would stop the run at its first tick, so ``check``
    refuses what ``run`` would end in a safety stop at once."""
    cfg = session.cfg
    for site in session.sites:
        if cfg.backend_for(site.name) != "sim" or not site.guard.enabled:
            continue
        q0 = getattr(cfg, site.name).robot.q0_rad or [0.0] * site.n
        lo, hi = site.guard.lo, site.guard.hi  # infinite with safety.position_limits off
        for j, angle in enumerate(q0):
            if not lo[j] <= angle <= hi[j]:
                raise ConfigError(
                    f"{site.name}.robot.q0_rad: {angle:g} rad for joint {j} "
                    f"({site.model.joint_names[j]}) is outside its limits [{lo[j]:g}, "
                    f"{hi[j]:g}] rad: the safety layer would stop the run at its first tick"
                )


def _print_warnings(session) -> None:
    from teleop_rt.analysis.contact import contact_warnings
    from teleop_rt.cli_sites import insecure_warnings
    from teleop_rt.config import DeadbandSpec
    from teleop_rt.safety import safety_warnings

    cfg = session.cfg
    lines = [*safety_warnings(cfg), *contact_warnings(cfg, session.to.model),
             *insecure_warnings(cfg)]  # fmt: skip
    if cfg.can is not None and "can" not in cfg.backends.values():
        lines.append(
            f"the config's can section is not used: the backends are {_backends_text(cfg)!r} "
            "(--backend can, or hsi:can / to:can, uses it)"
        )
    if cfg.channel.codec == "none" and cfg.channel.deadband != DeadbandSpec():
        # the section is read only with the codec on: a tuned deadband with the codec left off
        # would otherwise run every tick's packet without a word
        lines.append("channel.deadband is set but not used: channel.codec is 'none' "
                     "(--set channel.codec=deadband uses it)")  # fmt: skip
    for line in lines:
        print(f"teleop-rt: warning: {line}", file=sys.stderr)


def _cmd_run(args: argparse.Namespace) -> int:
    from teleop_rt.keys import key_reader
    from teleop_rt.report import progress_bar
    from teleop_rt.session import Session

    extra = []
    if args.duration is not None:
        extra.append(f"duration_s={args.duration}")
    if args.max_missed is not None and not args.realtime:
        raise ConfigError("--max-missed counts missed deadlines: it needs --realtime")
    if args.keys and not args.realtime:
        raise ConfigError("--keys reads the operator's keys as the robots move: add --realtime")
    keys_override(args)
    live = live_arg(args)
    can_path = None
    if args.can_log is not None:
        from teleop_rt.hal.can.canlog import check_can_log_path

        can_path = check_can_log_path(args.can_log)
    cfg = _load_config(args, extra)
    if (args.link or cfg.link.kind) == "zenoh":
        from teleop_rt.cli_sites import run_two_sites

        return run_two_sites(args, cfg)
    session = Session(cfg)
    _print_warnings(session)
    if args.realtime and not args.json:
        # no live bar in real time: its refresh thread would compete with the loop for the GIL
        print(
            f"running {cfg.duration_s:g} s in real time at {cfg.rate_hz} Hz (Ctrl-C stops)",
            file=sys.stderr,
        )
    # no deadline in fast mode with simulated robots: a full ring may wait for the writer
    lossless = not args.realtime and set(cfg.backends.values()) == {"sim"}
    metadata = {"config": str(args.config), "overrides": json.dumps([*args.overrides, *extra])}
    can_log = None
    if can_path is not None:
        from teleop_rt.hal.can.canlog import open_can_log

        emulated = cfg.can is not None and cfg.can.emulate  # nothing real waits in fast mode
        can_log = open_can_log(session, can_path, wait_for_room=emulated and not args.realtime)
    try:
        recorder = (
            None
            if args.no_log
            else _recorder(
                session, args.log_out, wait_for_room=lossless, metadata=metadata, live=live
            )
        )
    except BaseException:
        if can_log is not None:  # no session ran: no CAN log either
            can_log.close()
            can_log.path.unlink()
        raise
    if recorder is not None and recorder.live is not None:
        print(
            f"live: ws://{recorder.live} (Foxglove: Open connection, Foxglove WebSocket)",
            file=sys.stderr,
            flush=True,
        )
    try:
        with (
            _closed_on_error(recorder),
            progress_bar(cfg.n_ticks, enabled=not (args.json or args.realtime)) as progress,
        ):
            with key_reader(session.hsi):
                summary = session.run(
                    realtime=args.realtime, overrun=args.overrun, progress=progress,
                    recorder=recorder, max_missed=args.max_missed,
                )  # fmt: skip
    finally:
        can_status = can_log.close() if can_log is not None else None
    _print_summary(summary, args.json, recorder, can_status)
    code = exit_code(summary, recorder)
    if can_status is not None and not can_status["complete"]:
        return RecordingFailure.exit_code  # as for the session's log: before 3 and 130 / 143
    return code


def _cmd_site(args: argparse.Namespace) -> int:
    from teleop_rt.cli_sites import cmd_site

    keys_override(args)
    return cmd_site(args, _load_config, live_arg(args))


@contextlib.contextmanager
def _closed_on_error(recorder):
    """A signal or an error before the run's own handling starts (between starting the
    log's writer and the loop's first tick) still ends the writer: the file is finished and
    the process does not wait at exit for a writer nobody will close."""
    try:
        yield
    except BaseException as exc:
        if recorder is not None and not recorder.closed:
            # a readable log of no tick that says why (info: "never started"), rather than
            # one that reads as killed
            why = str(exc) if isinstance(exc, Terminated) else f"{type(exc).__name__}: {exc}"
            recorder.close({"ticks": 0, "stopped_early": f"{why} before the first tick"})
        raise


def _recorder(
    session,
    log: str | Path | None,
    suffix: str = "",
    wait_for_room: bool = False,
    metadata=None,
    live=None,
):
    from teleop_rt.recording.recorder import Recorder, default_log_path

    path = Path(log) if log else default_log_path(session.cfg.name + suffix)
    return Recorder(session, path, wait_for_room=wait_for_room, metadata=metadata, live=live)


def _print_summary(summary, as_json: bool, recorder, can_status: dict | None = None) -> None:
    from teleop_rt.report import print_summary

    status = recorder.status() if recorder else None
    if as_json:
        out = summary.to_dict()
        out["log"] = str(recorder.path) if recorder else None
        out["recording"] = status
        if can_status is not None:
            out["can_log"] = can_status
        json.dump(out, sys.stdout, indent=2)
        print()
    else:
        print_summary(summary)
        if status is not None:
            print(f"log: {recorder.path}" + ("" if status["complete"] else " (INCOMPLETE)"))
        if can_status is not None:
            whole = "" if can_status["complete"] else ", INCOMPLETE"
            print(f"CAN log: {can_status['path']} ({can_status['frames']} frames{whole})")
    _say_if_incomplete(recorder)
    if can_status is not None:
        from teleop_rt.hal.can.canlog import status_line

        line = status_line(can_status)
        if line:
            print(line, file=sys.stderr)


def _say_if_incomplete(recorder) -> None:
    """One line on stderr when the log lacks ticks (why, and how many were dropped)."""
    status = recorder.status() if recorder else None
    if status is not None and not status["complete"]:
        print(incomplete_line(recorder.path, status), file=sys.stderr)


def exit_code(summary, recorder=None) -> int:
    """The exit code of a run or replay that recorded with ``recorder`` (``ending_code``)."""
    return ending_code(summary, recorder.status() if recorder is not None else None)


def _cmd_metrics(args: argparse.Namespace) -> int:
    from teleop_rt.recording.metrics import metrics_main

    if len(args.log) > 2:
        raise ConfigError(
            f"metrics takes one log or the two logs of one session's sites, not {len(args.log)}"
        )
    if len(args.log) == 2:
        from teleop_rt.recording.pair import pair_main

        return pair_main(args.log[0], args.log[1], args.json, args.t_from, args.t_to)
    return metrics_main(args.log[0], args.json, args.t_from, args.t_to)


def _cmd_info(args: argparse.Namespace) -> int:
    from teleop_rt.recording.info import info_main

    return info_main(args.log, args.json)


def _cmd_plot(args: argparse.Namespace) -> int:
    from teleop_rt.recording.plot import plot_main

    if len(args.log) > 2:
        raise ConfigError(
            f"plot takes one log or the two logs of one session's sites, not {len(args.log)}"
        )
    partner = args.log[1] if len(args.log) == 2 else None
    return plot_main(args.log[0], args.output, args.force, args.t_from, args.t_to, partner)


def _cmd_replay(args: argparse.Namespace) -> int:
    import tempfile

    from teleop_rt.output import check_output
    from teleop_rt.recording.metrics import log_metrics
    from teleop_rt.recording.reader import read_log
    from teleop_rt.recording.replay import before_first_gap, build_replay
    from teleop_rt.report import print_comparison, progress_bar

    if args.plot:  # before the replay, which can take minutes
        check_output(args.plot, "--plot", force=args.force, image=True, inputs=(args.log,))
    data, gap_note = before_first_gap(read_log(args.log))
    if data.site:  # a site's own log: against its partner's logged packets
        return _replay_site(args, data, gap_note)
    if gap_note:
        print(f"teleop-rt: warning: {gap_note}", file=sys.stderr)
    original = log_metrics(data)
    session, ticks = build_replay(data, args.overrides)
    recorded_on = data.meta.get("backend", "sim")
    metadata = {
        "replay_of": str(args.log),
        "replay_of_backend": recorded_on,
        "overrides": json.dumps(args.overrides),
        **({"config": data.meta["config"]} if "config" in data.meta else {}),
    }
    scratch = None
    if not args.no_log:  # its own log, never the input (Recorder refuses existing files)
        recorder = _recorder(
            session, args.log_out, suffix="-replay", wait_for_room=True, metadata=metadata
        )
    elif args.plot:  # a plot is drawn from a log: a temporary one, removed afterwards
        scratch = tempfile.TemporaryDirectory(prefix="teleop-rt-replay-")
        recorder = _recorder(
            session, Path(scratch.name) / "replay.mcap", wait_for_room=True, metadata=metadata
        )
    else:
        recorder = None
    kept = None if args.no_log else recorder
    notes = []
    if data.truncated:
        notes.append(f"{args.log} was cut short ({data.cut_reason}); replayed what it holds")
    if recorded_on != "sim":
        notes.append(
            f"{args.log} was recorded on the {recorded_on} backend; "
            "the replay runs on the simulated backend (sim)"
        )
    try:
        with _closed_on_error(recorder), progress_bar(ticks, enabled=not args.json) as progress:
            summary = session.run(ticks=ticks, progress=progress, recorder=recorder)
        if args.plot:
            from teleop_rt.recording.plot import plot_log

            plot_log(read_log(recorder.path), args.plot, force=args.force, option="--plot",
                     original=data)  # fmt: skip
    finally:
        if scratch is not None:
            scratch.cleanup()
    if args.json:
        out = {
            "original": original,
            "replay": summary.to_dict(),
            "overrides": args.overrides,
            "backend": "sim",
            "recorded_backend": recorded_on,
            "log": str(kept.path) if kept else None,
            "plot": args.plot,
            "truncated_input": data.truncated,
            "notes": notes,
        }
        json.dump(out, sys.stdout, indent=2)
        print()
    else:
        for note in notes:
            print(f"note: {note}")
        print_comparison(original, summary, args.overrides)
        if kept is not None:
            print(f"replay log: {kept.path}")
        if args.plot:
            print(f"plot: {args.plot}")
    _say_if_incomplete(recorder)
    return exit_code(summary, recorder)


def _replay_site(args: argparse.Namespace, data, gap_note: str | None) -> int:
    """``teleop-rt replay SITE.mcap``: both logs' figures side by side; the exit code (0; 3 a
    safety stop; 4 the replay's log is incomplete; 130 a signal ended it)."""
    from teleop_rt.recording.site_replay import replay_site
    from teleop_rt.report import print_site_comparison

    if args.plot:
        raise ConfigError("--plot draws both robots; a site's log holds one: plot a session's log")
    if gap_note:
        print(f"teleop-rt: warning: {gap_note}", file=sys.stderr)
    done = replay_site(data, args.overrides, args.log_out, not args.no_log, str(args.log))
    out = done.figures
    if args.json:
        json.dump(out, sys.stdout, indent=2)
        print()
    else:
        if data.truncated:
            print(f"note: {args.log} was cut short ({data.cut_reason}); replayed what it holds")
        print_site_comparison(out)
        if out["log"]:
            print(f"replay log: {out['log']}")
    if done.summary["safety_stop"]:
        return 3
    if not done.log_status["complete"]:
        print(f"teleop-rt: log {done.log_path} is incomplete: {done.log_status['failure']}",
              file=sys.stderr)  # fmt: skip
        return 4
    return 130 if done.summary["stopped_early"] else 0


def _cmd_bode(args: argparse.Namespace) -> int:
    import math

    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from teleop_rt.analysis.bode import (
        MAX_POINT_SECONDS,
        default_omegas,
        measure_displayed_impedance,
        plot_bode,
        setup_from_config,
    )
    from teleop_rt.errors import ConfigError
    from teleop_rt.output import check_output, distinct, write_text

    if args.omegas is not None:
        try:
            omegas = [float(x) for x in args.omegas.split(",") if x.strip()]
        except ValueError:
            raise ConfigError(f"--omegas {args.omegas!r}: expected numbers a,b,c (rad/s)") from None
    else:
        if not 0 < args.omega_min <= args.omega_max or args.points < 1:
            raise ConfigError("need 0 < --omega-min <= --omega-max and --points >= 1")
        omegas = default_omegas(args.omega_min, args.omega_max, args.points).tolist()
    if not omegas or not all(w > 0 and math.isfinite(w) for w in omegas):
        raise ConfigError("frequencies must be positive finite numbers (rad/s)")
    if not 0 < args.max_seconds <= MAX_POINT_SECONDS:
        raise ConfigError(
            f"--max-seconds must be > 0 and at most {MAX_POINT_SECONDS:g} s, got {args.max_seconds}"
        )
    to_stdout = args.json_out == "-"
    json_file = None if to_stdout else args.json_out
    # every output path is checked before the sweep, which can take minutes
    distinct(("--json", json_file), ("--plot", args.plot))
    if json_file:
        check_output(json_file, "--json", force=args.force, inputs=(args.config,))
    if args.plot:
        check_output(args.plot, "--plot", force=args.force, image=True, inputs=(args.config,))
    cfg = _load_config(args)
    env, env_source, env_elements = _bode_environment(cfg, args)
    setup = setup_from_config(cfg, args.joint, *env)
    p = setup.params
    if p.delay_s == 0 and p.env_mass == p.env_damping == p.env_stiffness == 0:
        raise ConfigError(
            "bode: free space at T_d = 0 displays Z_h = 0 at every frequency (eq 29: "
            "Z_h = G_tau b T_d s), nothing to plot: give a delay (--set channel.delay_ms=50) or "
            "an environment (--env-stiffness K)"
        )
    setup.info["environment_source"] = env_source
    setup.info["environment_elements"] = env_elements
    columns = (
        TextColumn("[bold]frequencies"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(),
    )
    console = _console(stderr=True)
    with Progress(
        *columns, console=console, transient=True, disable=not console.is_terminal
    ) as bar:
        task = bar.add_task("bode", total=len(omegas))
        result = measure_displayed_impedance(
            setup.params,
            omegas,
            args.joint,
            args.amplitude,
            dt=setup.dt,
            max_seconds=args.max_seconds,
            chain_kwargs=setup.chain_kwargs,
            progress=lambda done, _total: bar.update(task, completed=done),
        )
    params = {"config": str(args.config), "overrides": args.overrides}
    params.update(result.params_dict())
    params.update(setup.info)
    doc = result.to_dict(params)
    # why a point is not a number: "settled", or changing / growing / diverged / slow / marginal
    doc["measured"]["reason"] = [pt.reason for pt in result.points]
    if to_stdout:
        print(json.dumps(doc, indent=2))
    elif json_file:
        write_text(json_file, json.dumps(doc, indent=2) + "\n", "--json", args.force)
    if not to_stdout:
        _print_bode(result, setup.info)
        if json_file:
            print(f"json: {json_file}")
    if args.plot:
        plot_bode(result, args.plot, force=args.force)
        if not to_stdout:
            print(f"plot: {args.plot}")
    return 0


def _bode_environment(cfg, args) -> tuple[tuple[float, float, float], str, list[str]]:
    """(mass, damping, stiffness) of the excited joint, where they came from, and per config
    element how it was used: the command line's --env-* if any is given, else the config's
    environment linearised at the TO's start pose (``teleop_rt.analysis.joint_env``)."""
    from teleop_rt.analysis.joint_env import joint_environment

    given = (args.env_mass, args.env_damping, args.env_stiffness)
    if any(v is not None for v in given):
        mass, damping, stiffness = (0.0 if v is None else float(v) for v in given)
        env = (mass, damping, stiffness)
        ignored = "; the config's environment not used"
        return env, "command line (joint space)" + (ignored if cfg.environment else ""), []
    if args.joint < 0:
        return (0.0, 0.0, 0.0), "free space", []  # setup_from_config says what is wrong
    found = joint_environment(cfg, args.joint)
    return (found.mass, found.damping, found.stiffness), found.source, found.elements


def _console(stderr: bool = False):
    """A rich Console that, writing to a file or a pipe, does not cut lines at 80 columns."""
    from rich.console import Console

    console = Console(stderr=stderr)
    return console if console.is_terminal else Console(stderr=stderr, width=240)


def _print_bode(result, info: dict) -> None:
    import numpy as np
    from rich.table import Table

    p = result.params
    table = Table(
        title=f"displayed impedance Z_h, joint {result.joint}, T_d = {p.delay_s * 1000:g} ms, "
        f"b = {p.b:g} N m s/rad, wave filter "
        f"{f'{p.wave_filter_hz:g} Hz' if p.wave_filter_hz and p.delay_s > 0 else 'off'}\n"
        f"Z_o = {p.z_o:g} N m s/rad: {info.get('z_o_source', '?')}\n"
        f"Z_e = {p.env_mass:g} s + {p.env_damping:g} + {p.env_stiffness:g}/s "
        f"(kg m^2, N m s/rad, N m/rad): {info.get('environment_source', '?')}",
        title_justify="left",
    )
    columns = ("omega rad/s", "|Z| meas.", "|Z| discr.", "|Z| cont.")
    for col in (*columns, "deg meas.", "deg discr.", "deg cont.", "settled"):
        table.add_column(col, justify="right", no_wrap=True)
    for pt, zd, za in zip(result.points, result.discrete, result.analytic, strict=True):
        settled = pt.settled
        meas = (f"{abs(pt.z):.4g}", f"{np.degrees(np.angle(pt.z)):.2f}") if settled else ("-", "-")
        table.add_row(
            f"{pt.omega:.4g}",
            meas[0],
            f"{abs(zd):.4g}",
            f"{abs(za):.4g}",
            meas[1],
            f"{np.degrees(np.angle(zd)):.2f}",
            f"{np.degrees(np.angle(za)):.2f}",
            "yes" if settled else f"[red]no ({pt.reason})",
        )
    _console().print(table)


def main(argv: Sequence[str] | None = None) -> int:
    # a closed stdout (`| head`, a killed parent) never changes the exit code (std_streams.py);
    # signals from the start: a running session has its own (exit_signals.py)
    with guarded(), exit_on_signals():
        try:
            return _main(argv)
        except Terminated as stop:
            print(f"teleop-rt: {stop}", file=sys.stderr)
            return stop.exit_code
        except KeyboardInterrupt:
            print("teleop-rt: interrupted", file=sys.stderr)
            return EXIT_INTERRUPTED


def _main(argv: Sequence[str] | None) -> int:
    parser = _build_parser()
    args = parser.parse_args(argv)
    handler = {
        "run": _cmd_run,
        "check": _cmd_check,
        "info": _cmd_info,
        "metrics": _cmd_metrics,
        "replay": _cmd_replay,
        "plot": _cmd_plot,
        "bode": _cmd_bode,
        "site": _cmd_site,
    }[args.command]
    try:
        return handler(args)
    except TeleopError as err:
        print(f"teleop-rt: error: {err}", file=sys.stderr)
        return err.exit_code


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
