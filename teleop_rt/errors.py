"""One error tree for everything a user can cause or meet.

The CLI turns any ``TeleopError`` into a single line on stderr and a non-zero exit code;
anything else is a bug and keeps its traceback.
"""


class TeleopError(Exception):
    """Base of all errors a user should see as one clear line."""

    exit_code = 1


class ConfigError(TeleopError):
    """A session config is malformed or names something impossible (exit code 2)."""

    exit_code = 2


class ModelError(ConfigError):
    """A robot description cannot be loaded or does not fit the per-joint parameters."""


class BackendError(TeleopError):
    """A hardware (or simulated) backend failed."""


class SafetyStop(TeleopError):
    """The session was stopped to keep the hardware safe (exit code 3)."""

    exit_code = 3


def quote(text: str, limit: int = 60) -> str:
    """A user's value for a one-line message: its repr, cut in the middle when long."""
    if len(text) <= limit:
        return repr(text)
    half = limit // 2 - 2
    return f"{text[:half]!r}...{text[-half:]!r} ({len(text)} characters)"


class RecordingFailure(TeleopError):
    """The log cannot record every tick (writer stalled, dead or unable to write): the session
    stops at the tick boundary (``recording.on_loss: stop``); a session whose log is incomplete
    exits with code 4 either way."""

    exit_code = 4
