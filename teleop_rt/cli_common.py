"""What both command modules use (``teleop_rt.cli`` and ``teleop_rt.cli_sites``), so that
neither imports the other: a run's exit code and the ``--live`` argument."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from teleop_rt.errors import ConfigError, RecordingFailure, SafetyStop

if TYPE_CHECKING:
    from teleop_rt.recording.live import LiveAddress

EXIT_INTERRUPTED = 130


def ending_code(summary, log_status: dict | None) -> int:
    """How a run (a session's, a site's, a replay's) ended, as its exit code: 4 if its log is
    incomplete, whatever else happened (the summary and stderr still say a safety stop or a
    signal: a lost log is what a script must not miss, and it may have lost the record of
    the rest); else 3 for a safety stop; 128 + the signal number for a run a signal ended
    (129, 130, 143); 0 for a complete run and log."""
    if log_status is not None and not log_status["complete"]:
        return RecordingFailure.exit_code
    if summary.safety_stop:
        return SafetyStop.exit_code
    if summary.stop_signal:
        return 128 + summary.stop_signal
    return EXIT_INTERRUPTED if summary.stopped_early else 0


def live_arg(args: argparse.Namespace) -> LiveAddress | None:
    """--live's address (None without it), checked before any work."""
    if args.live is None:
        return None
    from teleop_rt.recording.live import parse_address

    live = parse_address(args.live)
    if args.no_log:
        raise ConfigError("--live is served by the log's writer: it cannot go with --no-log")
    return live


def incomplete_line(path: object, status: dict) -> str:
    """The one stderr line for a log that lacks ticks: why, the ticks dropped before the
    writer (``dropped_rows``) and, read back from the file, how many ticks it does hold: a
    writer that failed loses the rows it had taken but not yet put on disk, which
    ``dropped_rows`` cannot count."""
    from teleop_rt.errors import TeleopError
    from teleop_rt.recording.reader import read_log

    try:
        held = f"; the file holds {read_log(str(path)).ticks} ticks"
    except (TeleopError, OSError, ValueError):  # unreadable: the reason above says why
        held = ""
    return (
        f"teleop-rt: log {path} is incomplete: {status['failure']} "
        f"(ticks dropped: {status['dropped_rows']}{held})"
    )
