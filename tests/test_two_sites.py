"""The two-sites shape (issue 15): a one-process session is two sites joined by an in-process
link, and it computes what main computed before the split, bit for bit (the reference figures
of tests/reference_figures.py, recorded from main before the restructure); a site stepped
alone against a Link gives the same numbers as the lock-step session."""

from __future__ import annotations

import json

import numpy as np
import pytest

from teleop_rt import config
from teleop_rt.com.link import InProcessLink
from teleop_rt.session import Session
from tests.conftest import CONFIGS
from tests.reference_figures import REFERENCE, cases, figures, key

REFERENCE_FIGURES = json.loads(REFERENCE.read_text())


@pytest.mark.parametrize("path, delay_ms", cases(), ids=[key(p, d) for p, d in cases()])
def test_every_config_gives_mains_figures_bit_for_bit(path, delay_ms) -> None:
    """T_p, T_tau, the channel energy and every logged field, exactly as main logged them
    before the split (the same arithmetic in the same order)."""
    ref, now = REFERENCE_FIGURES[key(path, delay_ms)], figures(path, delay_ms)
    assert now["ticks"] == ref["ticks"]
    for name in ("t_p", "t_tau", "channel_energy_j", "min_channel_energy_j"):
        assert now[name] == ref[name], name
    # fields logged since are additions (issue 17: the ports' balances and the protection's
    # removed energy); every field main logged must be there, bit for bit
    added = now["fields"].keys() - ref["fields"].keys()
    assert ref["fields"].keys() <= now["fields"].keys()
    assert added <= {"/channel.balance_hsi", "/channel.balance_to", "/channel.removed_hsi",
                     "/channel.removed_to"}  # fmt: skip
    differ = [f for f in ref["fields"] if now["fields"][f]["sha256"] != ref["fields"][f]["sha256"]]
    assert not differ, differ


def sites_alone(cfg: config.SessionConfig) -> tuple[Session, InProcessLink]:
    """A session's two sites on buffers of their own, to be stepped through a Python link."""
    session = Session(cfg, fuse=False)
    for site in session.sites:
        site.bind(type(session.packed)(site.blocks))
    return session, InProcessLink(session.n, cfg.delay_ticks)


@pytest.mark.parametrize("delay_ms", [0, 20])
def test_sites_stepped_alone_over_a_link_equal_the_lock_step_session(delay_ms) -> None:
    """The sites' own entry points (sense, update) against the Link interface compute what the
    lock-step kernels compute, tick by tick: what a site in a process of its own will run."""
    cfg = config.load(
        CONFIGS / "paper_experiment.yaml", ["duration_s=2", f"channel.delay_ms={delay_ms}"]
    )
    lockstep = Session(cfg)
    alone, link = sites_alone(cfg)
    hsi, to = alone.hsi, alone.to
    for k in range(cfg.n_ticks):
        lockstep.step()
        hsi.sense(link)
        to.sense(link)
        hsi.update(link)
        to.update(link)
        for a, b in ((lockstep.hsi, hsi), (lockstep.to, to)):
            assert np.array_equal(a.tau_cmd, b.tau_cmd), k
            assert np.array_equal(a.port.f, b.port.f), k
            assert np.array_equal(a.feedback.q, b.feedback.q), k
    assert np.abs(to.port.flow).max() > 0.01 and hsi.tick == to.tick == cfg.n_ticks


def test_logged_signals_obey_the_laws_that_name_them(tmp_path) -> None:
    """Every /channel column, and the controllers' outputs, against the equation that defines
    it, on a logged run: two swapped field declarations (or a kernel index that disagrees with
    a name) log one signal under another's name, and break one of these."""
    from teleop_rt.recording.reader import read_log
    from teleop_rt.recording.recorder import Recorder

    cfg = config.load(CONFIGS / "paper_experiment.yaml", ["duration_s=3", "channel.delay_ms=20"])
    session = Session(cfg)
    session.run(recorder=Recorder(session, tmp_path / "laws.mcap"))
    log = read_log(tmp_path / "laws.mcap")
    h, t, c = log.topics["/hsi"], log.topics["/to"], log.topics["/channel"]
    b = cfg.channel.wave_impedance
    s2b, s2ob = np.sqrt(2.0 * b), np.sqrt(2.0 / b)
    wc, tc, wt, tt = c["omega_c"], c["tau_c"], c["omega_t"], c["tau_t"]
    assert np.array_equal(wc, h["v"]) and np.array_equal(tt, -t["tau_ext"])  # eq 8's ports
    assert np.array_equal(tc, b * wc - s2b * c["v_l"])  # eq 9, HSI side
    assert np.array_equal(c["u_l"], s2b * wc - c["v_l"])
    assert np.array_equal(wt, (s2b * c["u_r"] - tt) / b)  # eq 9, TO side
    assert np.array_equal(c["v_r"], c["u_r"] - s2ob * tt)
    assert np.array_equal(c["power"], wc * tc - wt * tt)  # eq 8
    np.testing.assert_allclose(np.cumsum(c["power"], axis=0) * cfg.dt, c["energy"], atol=1e-12)
    np.testing.assert_array_equal(c["total_energy"], c["energy"].sum(axis=1))
    kp_h, kp_t = cfg.hsi.controller.kp, cfg.to.controller.kp
    assert np.array_equal(h["a_ref"], kp_h * (h["tau_ext"] - tc))  # eq 4: C1(tau_h - tau_c)
    assert np.array_equal(t["a_ref"], kp_t * (wt - t["v"]))  # eq 14: C2(omega_t - v_t)
    for name in ("omega_c", "tau_c", "u_l", "v_l", "u_r", "v_r", "power"):
        assert np.abs(c[name]).max() > 1e-3, name  # none of them trivially zero


def test_every_block_declares_each_field_once_where_its_kernels_find_it() -> None:
    """The field tuples are derived from the declarations, and every named view sits where the
    kernels' index says (vector k at k n, scalar k after the vectors)."""
    session = Session(config.load(CONFIGS / "paper_experiment.yaml", ["duration_s=0.01"]))
    for block in session.packed.blocks:
        cls = type(block)
        names = [*cls.VECTORS, *cls.SCALARS, *cls.INTS]
        assert len(names) == len(set(names)), cls.__name__
        for k, name in enumerate(cls.VECTORS):
            view = getattr(block, name)
            assert np.shares_memory(view, block.f[k * block.n : (k + 1) * block.n]), name
            declared = vars(cls).get(name)
            assert declared is None or declared.k == k, (cls.__name__, name)
        for k, name in enumerate(cls.SCALARS):
            block.f[len(cls.VECTORS) * block.n + k] = 0.25 + k
            assert getattr(block, name) == 0.25 + k, (cls.__name__, name)


@pytest.mark.parametrize("can_side", ["hsi", "to"])
def test_a_can_robot_against_a_simulated_one(can_side, tmp_path) -> None:
    """The lab's usual set-up: one robot on CAN (here its emulated drives), the other simulated,
    from the command line; the run completes and tracks like the all-simulated one (the CAN
    side adds one tick of command delay, so the figures are close, not equal)."""
    import subprocess
    import sys

    def run(*extra: str) -> dict:
        out = subprocess.run(
            [sys.executable, "-m", "teleop_rt.cli", "run", str(CONFIGS / "paper_experiment.yaml"),
             "--duration", "2", "--no-log", "--json", "--set", "can.emulate=true", *extra],
            capture_output=True, text=True, timeout=600, cwd=tmp_path,
        )  # fmt: skip
        assert out.returncode == 0, out.stderr[-2000:]
        return json.loads(out.stdout)

    mixed, sim = run("--backend", f"{can_side}:can"), run()
    assert mixed["ticks"] == sim["ticks"] == 2000 and mixed["stopped_early"] is None
    differs = [k for k in ("t_p_total", "t_tau_total") if mixed[k] != sim[k]]
    assert differs, "the CAN side did not run"
    assert mixed["t_tau_total"] == pytest.approx(sim["t_tau_total"], rel=0.2)
    assert mixed["t_p_total"] == pytest.approx(sim["t_p_total"], rel=0.5)


def impaired(*extra: str, seconds: float = 3.0) -> config.SessionConfig:
    return config.load(
        CONFIGS / "paper_experiment.yaml",
        [f"duration_s={seconds}", "channel.delay_ms=20", *extra],
    )


def test_an_impaired_link_that_does_nothing_equals_the_in_process_one() -> None:
    """link.impairment: {} sends every packet through the wire codec, the impairment stage and
    the playout rule: with nothing to impair, exactly what the delay lines give."""
    plain = Session(impaired()).run()
    through = Session(impaired("link.impairment={}"))
    assert not through.compiled_link
    summary = through.run()
    assert (summary.t_p, summary.t_tau) == (plain.t_p, plain.t_tau)
    assert summary.channel_energy_j == plain.channel_energy_j
    assert summary.link["to"]["lost"] == 0 and summary.link["to"]["used"] == 3000 - 20


def test_impaired_runs_are_seeded_and_count_what_the_network_did() -> None:
    """The same seed gives the same run bit for bit, another seed another run; 5 % loss shows
    as about 5 % of the packets lost (binomial: 3 sigma of 2980 draws is 1.2 %)."""
    lossy = ["link.impairment={loss_percent: 5.0, seed: 7}"]
    a, b = Session(impaired(*lossy)).run(), Session(impaired(*lossy)).run()
    c = Session(impaired("link.impairment={loss_percent: 5.0, seed: 8}")).run()
    assert (a.t_p, a.t_tau, a.channel_energy_j) == (b.t_p, b.t_tau, b.channel_energy_j)
    assert a.t_tau != c.t_tau
    for site in ("hsi", "to"):
        lost = a.link[site]["lost"] / (3000 - 20)
        assert 0.05 - 0.012 < lost < 0.05 + 0.012, (site, lost)


def test_a_snapshot_is_the_state_and_restoring_it_replays_the_same_ticks() -> None:
    """Parameters apart from state: ``snapshot`` copies the state of every block (the sites',
    the link's, the plants' when fused) and ``restore`` puts it back; the ticks after it repeat
    bit for bit, and a parameter (a gain) is not part of it."""
    session = Session(config.load(CONFIGS / "paper_experiment.yaml", ["channel.delay_ms=20"]))
    assert session.fused
    for _ in range(1500):
        session.step()
    snap = session.snapshot()
    first = []
    for _ in range(500):
        session.step()
        first.append(session.to.tau_cmd.copy())
    kp = session.to.controller.kp.copy()
    session.restore(snap)
    for k in range(500):
        session.step()
        assert np.array_equal(session.to.tau_cmd, first[k]), k
    assert np.array_equal(session.to.controller.kp, kp)
    fs, is_ = session.packed.state_index()
    kp_at = session.packed.index_of(session.to.controller, "kp")
    assert kp_at not in set(fs.tolist()) and len(fs) < session.packed.f.size
