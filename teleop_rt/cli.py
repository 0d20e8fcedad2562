"""Command line: ``teleop-rt run | check``.

Anything that is the user's input's fault ends as one line on stderr and a non-zero exit code
(2 for a bad config or argument), never a traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence

from teleop_rt import __version__
from teleop_rt.errors import TeleopError

EXIT_INTERRUPTED = 130


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="teleop-rt",
        description="1 kHz haptic bilateral teleoperation (Kuschel & Buss architecture).",
    )
    parser.add_argument("--version", action="version", version=f"teleop-rt {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def add_config_args(p: argparse.ArgumentParser) -> None:
        p.add_argument("config", help="session config (YAML), e.g. configs/paper_experiment.yaml")
        p.add_argument(
            "--set",
            dest="overrides",
            action="append",
            default=[],
            metavar="KEY=VALUE",
            help="override a config value, e.g. --set channel.delay_ms=50 (repeatable)",
        )

    run = sub.add_parser("run", help="run a session and print its summary")
    add_config_args(run)
    run.add_argument("--duration", type=_positive_float, metavar="S", help="seconds to run")
    run.add_argument(
        "--realtime",
        action="store_true",
        help="pace ticks to the wall clock (default: fast mode, as fast as possible)",
    )
    run.add_argument(
        "--overrun",
        choices=["catch_up", "skip", "stop"],
        default="catch_up",
        help="what a late tick does in real-time mode (default: catch_up)",
    )
    run.add_argument("--backend", metavar="NAME", help="backend to use instead of the config's")
    run.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")

    check = sub.add_parser("check", help="validate a config (and load its robots) without running")
    add_config_args(check)
    return parser


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive finite number, got {text!r}")
    return value


def _load_config(args: argparse.Namespace, extra: list[str] | None = None):
    from teleop_rt import config

    return config.load(args.config, [*args.overrides, *(extra or [])])


def _cmd_check(args: argparse.Namespace) -> int:
    from teleop_rt.session import Session

    cfg = _load_config(args)
    session = Session(cfg)  # builds models and backends: catches joint-count mismatches too
    print(
        f"{args.config}: ok ({session.n} joints, {cfg.n_ticks} ticks at {cfg.rate_hz} Hz, "
        f"delay {cfg.delay_ticks} ticks, backend {cfg.backend})"
    )
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    from teleop_rt.report import print_summary, progress_bar
    from teleop_rt.session import Session

    extra = []
    if args.duration is not None:
        extra.append(f"duration_s={args.duration}")
    if args.backend is not None:
        extra.append(f"backend={args.backend}")
    cfg = _load_config(args, extra)
    session = Session(cfg)
    if args.realtime and not args.json:
        # no live bar in real time: its refresh thread would compete with the loop for the GIL
        print(
            f"running {cfg.duration_s:g} s in real time at {cfg.rate_hz} Hz (Ctrl-C stops)",
            file=sys.stderr,
        )
    with progress_bar(cfg.n_ticks, enabled=not (args.json or args.realtime)) as progress:
        summary = session.run(realtime=args.realtime, overrun=args.overrun, progress=progress)
    if args.json:
        json.dump(summary.to_dict(), sys.stdout, indent=2)
        print()
    else:
        print_summary(summary)
    return EXIT_INTERRUPTED if summary.stopped_early else 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = _build_parser()
    args = parser.parse_args(argv)
    handler = {"run": _cmd_run, "check": _cmd_check}[args.command]
    try:
        return handler(args)
    except TeleopError as err:
        print(f"teleop-rt: error: {err}", file=sys.stderr)
        return err.exit_code
    except KeyboardInterrupt:
        print("teleop-rt: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
