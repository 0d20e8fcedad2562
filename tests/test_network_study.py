"""tools/network_study.py from the outside (issue 17, the study): a quick run writes the report
and its figures where --out says, its tables hold finite numbers, and a run without --out
never touches the committed docs/; --out is checked before the work."""

from __future__ import annotations

import hashlib
import math
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TOOL = ROOT / "tools" / "network_study.py"
FIGURES = ("network_paper_experiment.png", "network_stiff_wall.png", "network_traces.png")
PNG = b"\x89PNG\r\n\x1a\n"
# columns that must hold a finite number in every row
NUMERIC = ("min port balance (J)", "min two-port energy (J)", "removed (J)", "acted (ticks)",
           "packets used (%)", "T_p (rad^2 s)", "T_tau (N^2 m^2 s)")  # fmt: skip


def run_quick(*args: str) -> subprocess.CompletedProcess:
    proc = subprocess.run(
        [sys.executable, str(TOOL), "--quick", *args],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def tables(report: str) -> list[list[dict[str, str]]]:
    """Every markdown table of the report as rows of {header: cell}."""
    out, lines = [], report.splitlines()
    for k, line in enumerate(lines):
        if line.startswith("| ") and k + 1 < len(lines) and lines[k + 1].startswith("| ---"):
            head = [c.strip() for c in line.strip("|").split("|")]
            rows = []
            for body in lines[k + 2 :]:
                if not body.startswith("|"):
                    break
                cells = [c.strip() for c in body.strip("|").split("|")]
                assert len(cells) == len(head), body
                rows.append(dict(zip(head, cells, strict=True)))
            out.append(rows)
    return out


def docs_state() -> dict[str, tuple[int, str]]:
    return {
        str(p.relative_to(ROOT)): (p.stat().st_mtime_ns, hashlib.sha256(p.read_bytes()).hexdigest())
        for p in sorted((ROOT / "docs").rglob("*"))
        if p.is_file()
    }


def test_quick_run_writes_the_report_and_figures_into_out(tmp_path: Path) -> None:
    out = tmp_path / "study"
    proc = run_quick("--out", str(out))
    assert re.search(r"wall time \d+\.\d s", proc.stdout)
    assert re.search(r"^\[1/\d+\] ", proc.stdout, re.M)  # a line per run: the progress
    for name in FIGURES:
        data = (out / "figures" / name).read_bytes()
        assert data.startswith(PNG) and len(data) > 10_000, name
    report = (out / "network_study.md").read_text()
    # no empty parentheses where a quick run lacks a sweep (the fixed-jitter playout's D list)
    assert not re.search(r"\(\s*\)", report.replace("protection()", "")), "empty ()"
    for name in FIGURES:
        assert f"(figures/{name})" in report
    found = tables(report)
    # per task: stability and transparency, each a row per run
    assert len(found) == 4
    runs = int(re.search(r"; (\d+) runs\)", report).group(1))
    assert sum(len(t) for t in found) == 2 * runs
    checked = 0
    for rows in found:
        assert rows
        for row in rows:
            for head, cell in row.items():
                assert not re.search(r"\b(nan|inf)\b", cell, re.I), (head, cell)
                if head in NUMERIC:
                    assert math.isfinite(float(cell)), (head, cell)
                    checked += 1
    assert checked >= runs * len(NUMERIC)
    # the quick run is long enough for the paper task (its last waypoint at 11.5 s): with no
    # network it is done, a time, not "not done"
    reference = [r for r in found[1] if r["network"].startswith("no network")]
    assert reference and all(re.fullmatch(r"\d+\.\d\d", r["task time (s)"]) for r in reference)
    # the unprotected hold is the one channel whose balance goes below zero here
    balances = {}
    for row in found[0] + found[2]:
        if "min port balance (J)" in row:
            balances.setdefault(row["channel"], []).append(float(row["min port balance (J)"]))
    assert min(balances["unprotected wave (hold)"]) < -1e-6
    for ch in ("wave, zero wave on loss", "protected wave (bounded)", "TDPA"):
        assert min(balances[ch]) >= -1e-9, ch


def test_quick_run_without_out_never_touches_docs() -> None:
    before = docs_state()
    proc = run_quick()
    assert docs_state() == before
    where = Path(re.search(r"^writing into (.+)$", proc.stdout, re.M).group(1))
    try:
        assert not where.resolve().is_relative_to(ROOT)
        assert (where / "network_study.md").is_file()
        assert all((where / "figures" / name).is_file() for name in FIGURES)
    finally:
        shutil.rmtree(where)


@pytest.mark.parametrize("target", ["docs", str(ROOT / "docs")])
def test_a_quick_run_into_docs_is_refused_before_the_work(target: str) -> None:
    proc = subprocess.run(
        [sys.executable, str(TOOL), "--quick", "--out", target],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert proc.returncode == 2
    assert proc.stderr == (
        f"network_study: error: --out {target}: a quick run never writes over the committed "
        "report\n"
    )
    assert "writing into" not in proc.stdout


def test_out_is_checked_before_the_work(tmp_path: Path) -> None:
    afile = tmp_path / "report.md"
    afile.write_text("x")
    for target, reason in ((afile, "is a file, not a folder"), (afile / "sub", "cannot create")):
        proc = subprocess.run(
            [sys.executable, str(TOOL), "--quick", "--out", str(target)],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert proc.returncode == 2
        assert proc.stderr.startswith(f"network_study: error: --out {target}: {reason}")
        assert len(proc.stderr.splitlines()) == 1


def _inside(box, outer, slack: float = 1.0) -> bool:
    return (box.x0 >= outer.x0 - slack and box.x1 <= outer.x1 + slack
            and box.y0 >= outer.y0 - slack and box.y1 <= outer.y1 + slack)  # fmt: skip


def test_the_study_grid_legend_holds_every_line_and_no_text_is_clipped() -> None:
    """The full 6 x 6 grid drawn from made-up figures (every channel of every sweep, one run
    stopped): one legend, outside every panel, naming each channel, the no-network reference
    and the stop mark; no legend inside a panel; the titles (wrapped) and every label inside
    the figure; the fonts at the study's size."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    sys.path.insert(0, str(ROOT / "tools"))
    import network_study as ns

    st, name = ns.FULL, "paper_experiment"
    figures = {"t_p": 1e-3, "t_tau": 0.1, "mass": [0.05, 0.05], "stiffness": 300.0,
               "drift_end_rad": 1e-3, "min_balance_j": -1e-6}  # fmt: skip
    rows = [{"config": name, "case": ns.make_case("delay", 0).__class__("reference", 0.0),
             "channel": "zero", "complete": True, "diverged": False, **figures}]  # fmt: skip
    for sweep, values in st.grid[name].items():
        for ch in st.channels:
            for v in values:
                rows.append({"config": name, "case": ns.make_case(sweep, v), "channel": ch,
                             "complete": ch != "direct", "diverged": False, **figures})  # fmt: skip
    fig = ns.sweep_figure({"rows": rows}, st, name)
    panels = list(fig.axes)
    assert len(panels) == len(ns.PANELS) * len(st.grid[name]) == 36
    assert all(ax.get_legend() is None for ax in panels) and len(fig.legends) == 1
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert labels == [ns.CHANNEL[ch].label for ch in st.channels] + [
        "no network (D = 0)", "safety stop or divergence"]  # fmt: skip
    canvas = FigureCanvasAgg(fig)  # as print_png draws it: then the boxes are final
    canvas.draw()
    renderer = canvas.get_renderer()
    whole = fig.bbox
    legend = fig.legends[0].get_window_extent(renderer)
    assert _inside(legend, whole)
    assert not any(legend.overlaps(ax.get_window_extent(renderer)) for ax in panels)
    titles = {ax: ax._left_title for ax in panels}  # set_title(loc="left"): not ax.title
    texts = [fig._suptitle, *titles.values(), *(ax.xaxis.label for ax in panels),
             *(ax.yaxis.label for ax in panels)]  # fmt: skip
    for text in texts:
        if text is not None and text.get_text():
            assert _inside(text.get_window_extent(renderer), whole), text.get_text()
    tops = panels[:: len(ns.PANELS)]  # made column by column: each column's first is on top
    columns = [titles[ax].get_window_extent(renderer) for ax in tops]
    assert all(titles[ax].get_text() for ax in tops)
    for left, right in zip(columns, columns[1:], strict=False):
        assert left.x1 < right.x0  # a column's title ends before the next one's begins
    assert titles[panels[0]].get_fontsize() >= ns.FONT_PT
