"""Output files of the command line (plots, JSON), one rule for all of them.

A path is checked before any work is done (a sweep or a replay can take minutes): its folder
must exist, it must not be a folder itself, an image's format comes from its extension (one
matplotlib can write; anything else is refused), and an existing file is refused unless
``--force`` is given. The write itself is exclusive without ``--force``, so a file that appeared
meanwhile is not overwritten either. Logs are not outputs of this kind: they are never
overwritten (``teleop_rt.recording.recorder``).
"""

from __future__ import annotations

import functools
import os
import textwrap
from pathlib import Path
from typing import IO, TYPE_CHECKING

from teleop_rt.errors import TeleopError
from teleop_rt.inputs import shown

if TYPE_CHECKING:
    from matplotlib.figure import Figure


class OutputError(TeleopError):
    """An output path that cannot or must not be written (exit code 2)."""

    exit_code = 2


@functools.lru_cache(maxsize=1)
def image_formats() -> tuple[str, ...]:
    """The extensions matplotlib writes (png, pdf, svg, ...), without the dot."""
    from matplotlib.backend_bases import FigureCanvasBase

    return tuple(sorted(FigureCanvasBase.get_supported_filetypes()))


def image_format(path: Path, option: str) -> str:
    """The format of an image path, from its extension; OutputError if there is none."""
    fmt = path.suffix.lower().removeprefix(".")
    if fmt not in image_formats():
        what = f"unknown image format '.{fmt}'" if fmt else "no extension to choose a format by"
        known = ", ".join(f".{x}" for x in ("png", "pdf", "svg", "jpg", "eps"))
        raise OutputError(f"{option} {path}: {what} (use {known}, ...)")
    return fmt


def check_output(
    path: str | Path,
    option: str,
    *,
    force: bool = False,
    image: bool = False,
    inputs: tuple[str | Path, ...] = (),
) -> Path:
    """Check an output path before the work that fills it; return it as a Path.

    ``option`` names it in the message (``--plot``, ``-o``); ``inputs`` are files it must
    not be (the log being read), with ``--force`` too."""
    out = Path(path)
    if image:
        image_format(out, option)
    try:
        _check_output_path(out, option, force, inputs)
    except OSError as err:  # ENAMETOOLONG, ELOOP: what stat says of the path
        raise OutputError(f"{option} {shown(out)}: cannot be written ({err.strerror})") from None
    return out


def _check_output_path(out: Path, option: str, force: bool, inputs: tuple[str | Path, ...]) -> None:
    if out.is_dir():
        raise OutputError(f"{option} {out}: is a folder; give a file name")
    folder = out.parent
    if not folder.is_dir():
        what = "is not a folder" if folder.exists() else "does not exist"
        raise OutputError(f"{option} {out}: the folder {folder} {what}")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputError(f"{option} {out}: cannot write into {folder} (permission denied)")
    for other in inputs:
        if out.exists() and Path(other).exists() and out.samefile(other):
            raise OutputError(f"{option} {out}: that is the input file; choose another path")
    if out.exists() and not force:
        raise OutputError(
            f"{option} {out}: the file exists; pass --force to overwrite it or choose another path"
        )


def distinct(*outputs: tuple[str, str | Path | None]) -> None:
    """Refuse two options naming one output file (``--json x --plot x``)."""
    seen: dict[Path, str] = {}
    for option, path in outputs:
        if path is None:
            continue
        key = Path(path).resolve()
        if key in seen:
            raise OutputError(f"{option} {path}: {seen[key]} writes the same file")
        seen[key] = option


def open_output(path: Path, option: str, force: bool = False) -> IO[bytes]:
    """Open for writing: exclusively unless ``force``."""
    try:
        return open(path, "wb" if force else "xb")
    except FileExistsError:
        raise OutputError(
            f"{option} {path}: the file exists; pass --force to overwrite it or choose another path"
        ) from None
    except OSError as err:
        raise OutputError(f"{option} {path}: cannot write ({err.strerror})") from None


CHARS_PER_INCH = 9.0  # of a title at matplotlib's default 12 pt suptitle: wrap before the edge


def wrap_title(text: str, width_in: float, scale: float = 1.0) -> str:
    """``text`` broken into lines that fit a figure ``width_in`` inches wide (each of its own
    lines wrapped at words; ``scale``: the font's size against the default)."""
    chars = max(20, int(width_in * CHARS_PER_INCH / scale))
    return "\n".join(textwrap.fill(line, chars) for line in text.splitlines())


def save_figure(fig: Figure, path: str | Path, option: str = "--plot", force: bool = False) -> Path:
    """Write a matplotlib figure in the format its extension names (PNG bytes only in a .png)."""
    out = Path(path)
    fmt = image_format(out, option)
    try:
        with open_output(out, option, force) as stream:
            fig.savefig(stream, format=fmt)
    except OutputError:
        raise
    except BaseException:
        out.unlink(missing_ok=True)  # no half-written image left behind
        raise
    return out


def write_text(path: str | Path, text: str, option: str, force: bool = False) -> Path:
    out = Path(path)
    with open_output(out, option, force) as stream:
        stream.write(text.encode())
    return out


def report_folder_problem(out: Path) -> str | None:
    """A report's folder (``tools/reproduce_paper.py``, ``tools/network_study.py``): DIR and
    DIR/figures created before the work; the reason it cannot be used, else None."""
    if out.exists() and not out.is_dir():
        return f"--out {out}: is a file, not a folder"
    try:
        (out / "figures").mkdir(parents=True, exist_ok=True)
    except OSError as err:
        return f"--out {out}: cannot create {out / 'figures'} ({err.strerror})"
    if not os.access(out, os.W_OK) or not os.access(out / "figures", os.W_OK):
        return f"--out {out}: cannot write into it (permission denied)"
    return None
