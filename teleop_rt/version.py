"""The software version a log records: the package version, plus the git commit when the
package runs from a git checkout (``0.1.0+g1a2b3c4d5e6f``, ``.dirty`` with uncommitted changes
to tracked files). Asked of git once per process, never on the tick path."""

from __future__ import annotations

import functools
import subprocess
from pathlib import Path

from teleop_rt import __version__

_ROOT = Path(__file__).resolve().parents[1]  # the checkout, when the package is in one


@functools.lru_cache(maxsize=1)
def software_version() -> str:
    """``__version__`` with ``+g<commit>[.dirty]`` when the package is in a git checkout."""
    commit = git_commit()
    return __version__ if commit is None else f"{__version__}+g{commit}"


def git_commit(root: Path = _ROOT) -> str | None:
    """12 hex digits of HEAD (``.dirty`` appended if tracked files changed), or None when
    ``root`` is not the top of a git work tree or git is missing."""

    def git(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(
            ["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10
        )

    try:
        top = git("rev-parse", "--show-toplevel")
        # an installed package inside somebody else's repository must not take its commit
        if top.returncode != 0 or Path(top.stdout.strip()).resolve() != root.resolve():
            return None
        head = git("rev-parse", "--short=12", "HEAD")
        if head.returncode != 0:
            return None  # a repository without commits
        dirty = git("diff", "--quiet", "HEAD", "--").returncode == 1
    except (OSError, subprocess.SubprocessError):
        return None
    return head.stdout.strip() + (".dirty" if dirty else "")
