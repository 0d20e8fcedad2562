"""plot_log: a PNG with one angle and one torque axis per joint and the channel energy."""

from __future__ import annotations

import numpy as np
import pytest
from log_fixtures import write_synthetic_log
from matplotlib.image import imread

from teleop_rt.recording import plot
from teleop_rt.recording.plot import make_figure, plot_log, plot_main
from teleop_rt.recording.reader import read_log


@pytest.mark.parametrize("n", [1, 3])
def test_figure_content(tmp_path, n):
    log = write_synthetic_log(tmp_path / "a.mcap", 800, n)
    data = read_log(log.path)
    fig = make_figure(data)
    axes = fig.axes
    assert len(axes) == 2 * n + 1
    t = log.field("/hsi", "t")[:, 0]
    for j in range(n):
        angle, torque = axes[2 * j], axes[2 * j + 1]
        to, hsi = angle.get_lines()  # TO drawn first, HSI dashed on top
        assert hsi.get_linestyle() == "--" and to.get_linestyle() == "-"  # paper's Fig 6
        np.testing.assert_array_equal(hsi.get_xdata(), t)
        np.testing.assert_array_equal(hsi.get_ydata(), log.field("/hsi", "q")[:, j])
        np.testing.assert_array_equal(to.get_ydata(), log.field("/to", "q")[:, j])
        tau_e, tau_h = torque.get_lines()
        np.testing.assert_array_equal(tau_h.get_ydata(), log.field("/hsi", "tau_ext")[:, j])
        np.testing.assert_array_equal(tau_e.get_ydata(), -log.field("/to", "tau_ext")[:, j])
    (energy,) = axes[-1].get_lines()
    np.testing.assert_array_equal(energy.get_ydata(), log.field("/channel", "total_energy")[:, 0])
    assert "synthetic" in fig.get_suptitle() and "800 ticks" in fig.get_suptitle()


def test_png_written(tmp_path):
    log = write_synthetic_log(tmp_path / "a.mcap", 500)
    out = plot_log(read_log(log.path), tmp_path / "out.png", title="my title")
    assert out == tmp_path / "out.png" and out.stat().st_size > 20_000
    image = imread(out)
    height, width = image.shape[:2]
    # figsize (11, 2 n + 1.5 + 1.2) at 100 dpi: no tool path (the fixture's URDF has no joints)
    assert (width, height) == (1100, 670)
    assert image.std() > 0.05  # not a blank canvas


def test_long_log_is_an_envelope(tmp_path, monkeypatch):
    monkeypatch.setattr(plot, "MAX_POINTS", 100)
    energy = np.zeros(2000)
    energy[1234] = -3.0  # a one-tick spike survives decimation
    log = write_synthetic_log(tmp_path / "a.mcap", 2000, channel_total_energy=energy)
    fig = make_figure(read_log(log.path))
    for ax in fig.axes:
        for line in ax.get_lines():
            assert len(line.get_ydata()) <= 100
    assert fig.axes[-1].get_lines()[0].get_ydata().min() == -3.0
    q = log.field("/hsi", "q")[:, 0]
    hsi = fig.axes[0].get_lines()[1].get_ydata()
    assert hsi.min() == q.min() and hsi.max() == q.max()


def test_plot_main_default_path(tmp_path, capsys):
    log = write_synthetic_log(tmp_path / "run.mcap", 300, with_summary=False)
    assert plot_main(log.path) == 0
    assert (tmp_path / "run.png").stat().st_size > 20_000
    captured = capsys.readouterr()
    assert "wrote" in captured.out and "warning" in captured.err
    assert plot_main(log.path, tmp_path / "x.png") == 0 and (tmp_path / "x.png").exists()


def test_title_legend_and_zero_energy(tmp_path):
    """The delay in ms; one figure legend outside the axes (none inside covering data); a
    channel energy that is zero throughout (no delay) is not drawn, the title says so."""
    log = write_synthetic_log(
        tmp_path / "a.mcap", 400, delay=50, channel_total_energy=0 * np.ones(400)
    )
    fig = make_figure(read_log(log.path))
    assert len(fig.axes) == 4  # two joints' angles and torques, no energy panel
    assert all(ax.get_legend() is None for ax in fig.axes) and len(fig.legends) == 1
    title = fig.get_suptitle()
    assert "delay 50 ms" in title and "ticks" not in title.split("delay")[1]
    assert "channel energy 0 throughout" in title


def test_tool_paths_in_the_plane_with_the_environment(tmp_path):
    from teleop_rt.cli import main
    from teleop_rt.model import RobotModel
    from tests.conftest import CONFIGS

    path = tmp_path / "paper.mcap"
    argv = ["run", str(CONFIGS / "paper_experiment.yaml"), "--duration", "0.5", "--log", str(path)]
    assert main([*argv, "--set", "channel.delay_ms=10"]) == 0
    data = read_log(path)
    fig = make_figure(data)
    (ax,) = [a for a in fig.axes if a.get_title().startswith("tool paths")]
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("x (m)", "y (m)")  # the SCARA's plane
    to_line = ax.get_lines()[0]
    model = RobotModel.from_spec(data.config().to.robot, "to")
    end = model.ee_position(data.topics["/to"]["q"][-1])
    assert (to_line.get_xdata()[-1], to_line.get_ydata()[-1]) == pytest.approx(tuple(end[:2]))
    # the foam's surface x = 0.40 and the wall's y = -0.06, both drawn and filled
    lines = [(line.get_xdata(), line.get_ydata()) for line in ax.get_lines()[3:]]
    assert any(np.allclose(x, 0.40) for x, _ in lines) and any(
        np.allclose(y, -0.06) for _, y in lines
    )
    assert len(ax.patches) == 2
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert "foam 300 N/m" in labels and "wall 5000 N/m" in labels
    assert ax.get_ylim()[0] < -0.06 < ax.get_ylim()[1]  # the wall is inside the view


def _captured_figures(monkeypatch) -> list:
    """The figures ``plot_log`` draws (make_figure wrapped), to look into what the CLI drew."""
    figures = []
    draw = plot.make_figure

    def keep(*args, **kwargs):
        figures.append(draw(*args, **kwargs))
        return figures[-1]

    monkeypatch.setattr(plot, "make_figure", keep)
    return figures


def test_replay_plot_draws_the_original_run_under_the_replay(tmp_path, monkeypatch, capsys):
    """``replay LOG --set ... --plot IMG``: every angle and torque axis holds the original
    run's HSI and TO (wide, faint: ``ORIGINAL_STYLE``) under the replay's, each with its own
    data; the channel energy both; the legend names the four."""
    from teleop_rt.cli import main
    from tests.conftest import CONFIGS

    log, out = tmp_path / "run.mcap", tmp_path / "replay.png"
    argv = ["run", str(CONFIGS / "paper_experiment.yaml"), "--duration", "1", "--log", str(log)]
    assert main([*argv, "--set", "channel.delay_ms=10"]) == 0
    figures = _captured_figures(monkeypatch)
    code = main(["replay", str(log), "--set", "channel.delay_ms=60", "--plot", str(out),
                 "--no-log", "--json"])  # fmt: skip
    assert code == 0 and out.stat().st_size > 20_000
    capsys.readouterr()
    (fig,) = figures
    original = read_log(log)
    n = original.layout.n
    for j in range(n):
        angle, torque = fig.axes[2 * j], fig.axes[2 * j + 1]
        for ax, field, sign in ((angle, "q", 1.0), (torque, "tau_ext", None)):
            was_to, was_hsi, now_to, now_hsi = ax.get_lines()
            for line in (was_to, was_hsi):
                assert line.get_alpha() == plot.ORIGINAL_STYLE["alpha"]
                assert line.get_linewidth() == plot.ORIGINAL_STYLE["lw"]
            assert now_hsi.get_alpha() is None and now_hsi.get_linestyle() == "--"
            to_sign = -1.0 if sign is None else 1.0
            np.testing.assert_array_equal(was_hsi.get_ydata(), original.topics["/hsi"][field][:, j])
            np.testing.assert_array_equal(
                was_to.get_ydata(), to_sign * original.topics["/to"][field][:, j]
            )
            assert not np.array_equal(now_hsi.get_ydata(), was_hsi.get_ydata())  # 60 ms, not 10
    energy_axis = fig.axes[2 * n + 1]  # after the tool paths
    assert energy_axis.get_ylabel() == "channel energy (J)" and len(energy_axis.get_lines()) == 2
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert labels[:4] == ["HSI (q_h, tau_h)", "TO (q_t, tau_e)", "HSI, original run",
                          "TO, original run"]  # fmt: skip
    assert "replay of" in fig.get_suptitle()
