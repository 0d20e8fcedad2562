"""Shared fixtures: paths and small helpers for measuring responses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
SCARA_URDF = ROOT / "robots" / "urdf" / "scara_2dof.urdf"
# how long a started run (or pair of sites) may take to reach its loop before a test calls it
# hung: a hang detector, not a timing assertion. Warm, 8-10 s on this loaded 2-core VM; from an
# empty kernel cache or behind another process's compile (the cache lock) minutes have been
# seen (2 min 35 s once); each wait ends early when the run exits
START_LIMIT_S = 300.0


@pytest.fixture
def configs_dir() -> Path:
    return CONFIGS


@pytest.fixture(autouse=True)
def _logs_in_tmp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Runs that log by default write to the test's own folder, never into the checkout."""
    import teleop_rt.recording.recorder as recorder

    monkeypatch.setattr(recorder, "DEFAULT_LOG_DIR", tmp_path / "logs")


def lock_in(signal: np.ndarray, omega: float, dt: float) -> complex:
    """Complex amplitude of the omega component of a sampled signal (whole periods assumed)."""
    t = np.arange(len(signal)) * dt
    return 2.0 / len(signal) * complex(np.sum(signal * np.exp(-1j * omega * t)))


# The markers (registered in pyproject.toml), declared here once per test file rather than in
# each file: what a test needs decides whether the README's fast subset runs it.
MARKS_BY_FILE = {
    "test_zenoh_attacks.py": ("zenoh",),
    "test_zenoh_impairment.py": ("zenoh", "realtime"),
    "test_zenoh_sites.py": ("zenoh", "realtime"),
    "test_zenoh_tls.py": ("zenoh",),
    "test_loopback_link.py": ("zenoh",),  # (a ZenohLink's config needs zenoh, not a session)
    "test_site_logs.py": ("zenoh", "realtime"),
    "test_outside_s37.py": ("zenoh", "realtime"),
    "test_can_backend.py": ("can",),
    "test_can_codec.py": ("can",),
    "test_can_log.py": ("can",),
    "test_can_session.py": ("can",),
    "test_can_tools.py": ("can",),
    "test_live.py": ("realtime",),
    "test_keys.py": ("realtime",),  # a pseudo-terminal's keys during a real-time run
    "test_can_inputs.py": ("can",),  # the clutch and presence bits of emulated CAN drives
    "test_missed_deadlines.py": ("realtime",),
    "test_recording_failures.py": ("realtime",),
    "test_reproduce_paper.py": ("slow",),
    "test_network_study.py": ("slow",),
    "test_bench_instructions.py": ("slow",),
    "test_passive_channels.py": ("slow",),
    "test_backend_entry_points.py": ("slow",),  # pip-installs a package into a new venv
}
# single tests of otherwise fast files (the function's name, without parameters)
MARKS_BY_TEST = {
    "test_recording.py::test_a_signal_stops_a_realtime_run_with_a_complete_log": ("realtime",),
    "test_recording.py::test_a_hard_kill_leaves_a_readable_log": ("realtime",),
    "test_early_stop.py::test_sigterm_before_the_first_tick_leaves_a_log_or_none": ("realtime",),
    "test_closed_output.py::test_a_site_keeps_its_exit_code": ("zenoh", "realtime"),
    "test_keys.py::test_two_sites_with_the_keys_replay_the_tos_log_bit_for_bit": ("zenoh",),
    "test_zenoh_attacks.py::test_reflected_and_sequence_jumping_packets_are_rejected_by_reason": (
        "realtime",
    ),
    "test_zenoh_sites.py::test_a_killed_parent_leaves_no_site_running": ("zenoh", "realtime"),
    "test_site_logs.py::test_run_link_zenoh_refuses_a_log_pair_that_exists": ("realtime",),
    "test_outside_s36.py::test_check_and_run_refuse_a_network_link_without_delay": (
        "zenoh",
        "realtime",
    ),
    "test_two_sites.py::test_a_can_robot_against_a_simulated_one": ("can",),
    "test_backend_lifecycle.py::test_a_can_session_ends_with_both_robots_unconfigured": ("can",),
    "test_late_packets.py::test_a_site_log_with_late_packets_used_replays_bit_for_bit": (
        "zenoh",
        "realtime",
    ),
    # each starts fresh interpreters that load every kernel: over a minute on a loaded host
    "test_cli.py::test_python_dash_m_teleop_rt": ("slow",),
    "test_cli.py::test_bode_piped_is_not_cut_at_80_columns": ("slow",),
    "test_heterogeneous_pairs.py::test_a_pair_stays_passive_under_every_impairment": ("slow",),
    "test_task_space_3d.py::test_a_3d_pair_stays_passive_under_every_impairment": ("slow",),
    "test_posture.py::test_a_pair_with_the_posture_stays_passive_under_every_impairment": ("slow",),
    "test_frames.py::test_a_turned_scaled_pair_stays_passive_under_every_impairment": ("slow",),
    "test_frames.py::test_a_turned_offset_3d_pair_stays_passive_under_every_impairment": ("slow",),
    "test_cli.py::test_console_script_check": ("slow",),
    # two processes compile every site kernel from an empty cache: about 75 s here
    "test_kernel_cache.py::test_two_sites_warming_up_at_once_from_an_empty_cache_both_succeed": (
        "slow",
    ),
    "test_closed_output.py::test_a_safety_stop_stays_exit_3": ("slow",),
    "test_bad_input.py::test_a_fifo_is_refused_without_blocking": ("slow",),
    "test_bad_input.py::test_a_broken_urdf_is_one_line_with_urdfdoms_reason": ("slow",),
    "test_outside_s38.py::test_a_site_held_off_longer_than_the_peer_timeout_stops_and_says_so": (
        "zenoh",
    ),
}

# tests of about 2 s or more each on this machine (measured with --durations): left out of
# the README's fast subset, run by the whole suite
SLOW_TESTS = {
    "test_skip_debt.py": (
        "test_the_foam_sawtooth_row_meets_t_tau_with_the_skip_debt",
        "test_the_ports_are_passive_at_any_skip_time_constant",
    ),
    "test_task_gain_limit.py": (
        "test_the_limit_separates_the_runs_that_hold_from_those_that_stop",
    ),
    "test_backend_lifecycle.py": ("test_the_transitions_and_their_states",),
    "test_bad_input.py": ("test_damaged_logs_work_or_are_one_line",),
    "test_bode.py": (
        "test_bode_of_free_space_without_delay_is_one_line_not_an_empty_plot",
        "test_bode_plot_title_is_wrapped_inside_the_figure",
        "test_measured_matches_the_discrete_model_to_0_1_percent",
    ),
    "test_channel.py": ("test_delay_lines_output_zeros_until_filled_then_the_sample_d_ticks_ago",),
    "test_codec.py": (
        "test_a_look_ahead_of_the_room_stays_passive_for_any_delays_losses_and_arrivals",
        "test_ports_with_the_codec_are_passive_for_any_delays_losses_and_inputs",
        "test_sessions_with_the_codec_stay_passive_under_impairments",
    ),
    "test_docs.py": (
        "test_every_teleop_rt_command_runs",
        "test_the_fast_subset_deselects_exactly_the_marked_tests",
    ),
    "test_frames.py": (
        "test_a_turned_offset_tool_tracks_r_x_h_plus_the_offset",
        "test_a_turned_stroke_of_the_hsi_gives_the_turned_to_stroke",
        "test_an_offset_the_start_does_not_meet_moves_no_robot",
        "test_through_a_turned_3d_frame_the_power_is_unchanged_and_the_operator_feels_r_t_f",
    ),
    "test_heterogeneous_pairs.py": (
        "test_a_pair_of_one_joint_count_in_the_plane_runs_fused_as_read_write",
        "test_the_displayed_mass_in_task_space_is_lambda_plus_b_t",
        "test_twenty_re_engagements_in_the_plane",
    ),
    "test_late_packets.py": ("test_newest_uses_a_late_packet_once_it_arrives_and_never_before_d",),
    "test_log_pairs.py": (
        "test_a_pair_records_each_robot_with_its_joints",
        "test_metrics_info_plot_and_replay_of_a_pair_log",
    ),
    "test_mapping.py": (
        "test_scaled_channel_is_passive",
        "test_the_offset_is_taken_up",
    ),
    "test_playout.py": ("test_the_ring_equals_the_rule_on_random_schedules",),
    "test_posture.py": (
        "test_a_null_space_offset_decays_as_exp_minus_kp_t_and_the_tool_stays",
        "test_off_by_default_and_in_a_session_the_posture_is_the_start",
        "test_the_posture_does_no_work_on_the_wall",
    ),
    "test_reflected.py": (
        "test_reflected_ports_are_passive_for_any_delays_losses_reorderings_and_inputs",
    ),
    "test_safety.py": ("test_safety_off_still_never_sends_a_nan_torque",),
    "test_safety_task_space.py": (
        "test_a_virtual_wall_holds_the_tool_as_a_spring",
        "test_the_tool_speed_limit_holds_and_the_map_stays_lossless",
    ),
    "test_session.py": ("test_default_integrator_is_converged_for_the_stiff_wall",),
    "test_sim_tick.py": ("test_the_fused_tick_equals_plants_on_their_own_buffers_bit_for_bit",),
    "test_static_checks.py": (
        "test_mypy_finds_nothing",
        "test_mypy_sees_block_fields",
    ),
    "test_task_space_3d.py": (
        "test_the_displayed_mass_in_3d_is_lambda_plus_b_t",
        "test_the_orientation_converges_to_a_rotated_target_at_the_closed_form_rate",
        "test_the_panda_follows_the_ur5_and_the_operator_feels_the_table",
        "test_the_scaled_two_port_s_energy_is_the_channel_s",
    ),
    "test_wave_drift.py": ("test_corrected_ports_are_passive_for_any_delays_losses_and_inputs",),
    "test_wire.py": ("test_a_decoder_binds_no_encoder",),  # (a fresh interpreter loads kernels)
    "test_wave_schedule.py": (
        "test_the_schedule_follows_its_closed_form",
        "test_scheduled_ports_are_passive_for_any_b_delays_losses_and_inputs",
    ),
}


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        name = item.path.name
        function = getattr(item, "originalname", item.name)
        for mark in MARKS_BY_FILE.get(name, ()) + MARKS_BY_TEST.get(f"{name}::{function}", ()):
            item.add_marker(mark)
        if function in SLOW_TESTS.get(name, ()):
            item.add_marker("slow")
