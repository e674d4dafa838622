import fcntl
import hashlib
import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hil.testing import hil_command, subprocess_env
from hil.testing import run_hil as hil

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "scenarios"

# what tests import from here
__all__ = ["ROOT", "SCENARIOS", "bare_env", "case_seed", "hil", "hil_command", "once_per_session", "subprocess_env"]

# -- seeds of generated cases --------------------------------------------------------------------------
# HIL_TEST_SEED unset: the fixed base seed below (a run is reproducible); an integer: that base seed;
# "random": a base seed drawn once when the session starts (printed in the header and the summary, and
# handed to xdist's workers through the environment).  tests/run.sh sets "random" under CI=true.
FIXED_BASE_SEED = 20240601
_SEED_COUNTS: dict = {}
_SEED_MODE = {"": "fixed", "random": "drawn at random"}.get(os.environ.get("HIL_TEST_SEED", "").strip(), "pinned")


def _base_seed() -> int:
    value = os.environ.get("HIL_TEST_SEED", "").strip()
    if value == "":
        return FIXED_BASE_SEED
    if value == "random":           # only when this process is not under a session that resolved it
        value = os.environ["HIL_TEST_SEED"] = str(secrets.randbits(31))
    try:
        return int(value)
    except ValueError:
        raise pytest.UsageError(f"HIL_TEST_SEED={value!r}: expected unset, an integer or 'random'") from None


def case_seed(what: str = "") -> int:
    """The seed of a generated case in the running test: a hash of the base seed (HIL_TEST_SEED), the
    test's node id and ``what``, in [0, 2**31).  The n-th call with the same ``what`` in one test gets
    its own seed (n is part of the hash), so a test drawing several cases draws different ones, the
    same on every run with the same base seed.  Printed to stderr (shown with a failing test's output;
    stdout stays the tested command's) with what reproduces it: ``HIL_TEST_SEED=<base> pytest <node id>``."""
    current = os.environ.get("PYTEST_CURRENT_TEST", "outside a test (setup)")
    node = current.rsplit(" (", 1)[0]           # "<node id> (setup|call|teardown)"
    base = _base_seed()
    n = _SEED_COUNTS.get((node, what), 0)
    _SEED_COUNTS[node, what] = n + 1
    digest = hashlib.blake2b(f"{base}|{node}|{what}|{n}".encode(), digest_size=8).digest()
    seed = int.from_bytes(digest, "little") % (1 << 31)
    print(f"{what + ': ' if what else ''}seed {seed} (HIL_TEST_SEED={base} pytest {node})", file=sys.stderr)
    return seed


def pytest_configure(config):
    if not hasattr(config, "workerinput"):          # the controller (or a run without xdist) resolves "random"
        _base_seed()


def pytest_report_header(config):
    return f"test seeds: HIL_TEST_SEED={_base_seed()} ({_SEED_MODE})"


def pytest_terminal_summary(terminalreporter):
    terminalreporter.write_line(f"test seeds: HIL_TEST_SEED={_base_seed()} ({_SEED_MODE}) reproduces this run's "
                                "generated cases")


def once_per_session(tmp_path_factory, name: str, make):
    """``make(directory)`` (JSON-able: paths as strings) made once in the test session and read back by
    every other caller, under xdist by the first worker to ask (the others wait on a lock for it, then
    read it): an expensive recorded run that tests on both workers read is made once, not once per
    worker.  Its files stay in ``directory`` (under the making worker's base temporary directory) for
    the session; a ``make`` that raises leaves nothing, so the next caller tries again (and fails the same)."""
    base = tmp_path_factory.getbasetemp()
    root = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base     # the session's, shared by workers
    done = root / f"{name}.once.json"
    with open(root / f"{name}.once.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if done.exists():
            return json.loads(done.read_text())
        value = make(tmp_path_factory.mktemp(name))
        done.write_text(json.dumps(value))
        return value


# -- tiers -------------------------------------------------------------------------------------------
# The slow tests: out of the fast tier (``tests/run.sh --fast`` deselects -m slow).  Chosen from one full
# run's durations (pytest --durations, two workers, on the shared 2-core machine under load ~12-17): each
# took 10 s or more there (set-up included), or uses a module's expensive recorded run that only slow tests
# would otherwise share; and the gap diagnosis tests (each runs whole diagnoses).  A name without [...] is every
# parameter case.  The fast tier keeps one real two-process run over the local bus:
# test_bus.py::test_local_lockstep_polling_or_sleeping_gives_the_inprocess_frames[0].
SLOW = {
    "tests/test_bad_input.py::test_a_value_that_makes_the_plant_diverge_is_one_line_and_exit_2",
    "tests/test_bad_input.py::test_bad_scenarios_via_the_cli_are_one_line_and_exit_2",
    "tests/test_bad_input.py::test_mutated_scenarios_fail_in_one_line_or_load",
    "tests/test_bayes.py::test_intervals_cover_the_truth_about_as_often_as_they_say",
    "tests/test_bayes.py::test_unconfirmed_is_reported_on_the_bus_recorded_and_replayed",
    "tests/test_bench_identify.py::test_family_mode_draws_at_run_time_prints_its_seed_and_judges_against_the_oracle",
    "tests/test_bench_identify.py::test_form_limit_is_zero_on_its_own_form_and_not_on_a_flat_polach_peak",
    "tests/test_bench_identify.py::test_json_results_shape_same_data_for_every_strategy_and_plots",
    "tests/test_bench_identify.py::test_markdown_table_and_bad_input",
    "tests/test_bench_identify.py::test_observer_aware_strategy_reports_its_own_fit_beside_the_papers",
    "tests/test_bench_robustness.py::test_bad_arguments_are_one_line_and_exit_2",
    "tests/test_bench_robustness.py::test_every_part_at_small_counts_finds_no_failure",
    "tests/test_bus.py::test_a_killed_plant_leaves_no_hub_or_tcu_behind",
    "tests/test_bus.py::test_a_tcu_that_dies_mid_run_is_exit_3_and_json_still_prints_one_object",
    "tests/test_bus.py::test_bad_bus_table_names_the_field",
    "tests/test_bus.py::test_bus_load_above_70_percent_warns",
    "tests/test_bus.py::test_ctrl_c_stops_plant_tcu_and_hub_and_closes_the_mcap",
    "tests/test_bus.py::test_garbage_on_the_hub_is_counted_on_both_sides_and_changes_nothing",
    "tests/test_bus.py::test_inprocess_and_hub_give_identical_frames_and_identification",
    "tests/test_bus.py::test_json_keys_and_mcap_holds_every_frame_raw",
    "tests/test_bus.py::test_local_lockstep_polling_or_sleeping_gives_the_inprocess_frames[0.002]",
    "tests/test_bus.py::test_udp_multicast_lockstep_gives_the_inprocess_frames",
    "tests/test_bus.py::test_plant_and_tcu_started_separately",
    "tests/test_bus.py::test_sigterm_ends_a_run_like_ctrl_c",
    "tests/test_bus.py::test_silent_plant_ends_a_standalone_tcu",
    "tests/test_bus.py::test_silent_tcu_is_a_recorded_fault_and_exit_3",
    "tests/test_bus.py::test_unknown_bus_is_one_clear_line",
    "tests/test_families.py::test_a_draw_is_reproducible_and_indices_differ",
    "tests/test_families.py::test_draws_parse_and_slip_within_the_band",
    "tests/test_families.py::test_every_draw_slips_and_its_target_is_reachable",
    "tests/test_families.py::test_sample_curves_is_draws_prior",
    "tests/test_faults.py::test_a_disk_that_fills_mid_run_ends_it_in_one_line_with_the_tcu_stopped_and_the_log_readable",
    "tests/test_faults.py::test_a_full_disk_at_the_start_leaves_no_empty_log",
    "tests/test_fmu.py::test_a_folder_and_an_fmi1_fmu_get_the_right_line",
    "tests/test_fmu.py::test_a_model_identifier_that_is_a_path_is_refused_and_nothing_runs",
    "tests/test_fmu.py::test_a_zip_bomb_is_refused_before_unpacking",
    "tests/test_fmu.py::test_an_archive_member_outside_the_fmu_is_refused_before_unpacking",
    "tests/test_fmu.py::test_identification_identical_with_fmu_and_casadi_plant",
    "tests/test_gap.py::test_a_constant_power_limit_is_never_the_rail_nor_a_name",
    "tests/test_gap.py::test_a_creep_stretched_rail_is_the_nuisance_and_nothing_more_is_named",
    "tests/test_gap.py::test_a_held_out_bristle_is_not_named_as_another_class",
    "tests/test_gap.py::test_a_quantiser_is_named_beside_the_effect_that_explains_the_mean",
    "tests/test_gap.py::test_a_tachometer_gain_is_none_of_the_candidates_but_described_by_the_motor_speed",
    "tests/test_gap.py::test_blind_cases_with_a_seed_chosen_now",
    "tests/test_gap.py::test_can_log_diagnoses_like_its_mcap_twin",
    "tests/test_gap.py::test_can_log_with_garbage_frames_skips_and_counts_them",
    "tests/test_gap.py::test_can_log_with_many_steps_out_of_sequence_names_the_frame",
    "tests/test_gap.py::test_cli_gap_bad_inputs",
    "tests/test_gap.py::test_cli_gap_json_and_report",
    "tests/test_gap.py::test_nominal_run_has_no_gap",
    "tests/test_gap.py::test_polach_fault_curve_diagnosed_and_reported",
    "tests/test_gap.py::test_reader_drops_the_truth_even_from_the_scenario_text",
    "tests/test_gap.py::test_torque_lag_found_when_the_command_varies",
    "tests/test_gap.py::test_two_effects_at_once_found_by_forward_selection",
    "tests/test_gap.py::test_the_veto_in_time_keeps_a_true_delay_under_a_load_transfer",
    "tests/test_gap.py::test_a_pair_is_fitted_in_a_form_within_its_range",
    "tests/test_gap.py::test_a_small_delay_under_a_first_that_leaves_little_is_named",
    "tests/test_gap.py::test_a_drive_torque_that_falls_with_motor_speed_is_described_by_the_motor_speed",
    "tests/test_gap.py::test_a_second_effect_is_not_fitted_into_a_held_out_forms_misfit",
    "tests/test_gap.py::test_no_second_effect_within_twice_the_noise_after_a_first_that_removes_most",
    "tests/test_gap.py::test_a_pair_turned_away_only_against_the_rail_is_listed_not_named",
    "tests/test_gap.py::test_a_pair_whose_first_is_not_the_best_alone_is_found_from_another_first",
    "tests/test_gap.py::test_a_first_effect_only_most_likely_alone_is_named_when_the_pair_settles_it",
    "tests/test_gap.py::test_the_veto_in_time_rejects_a_pair_that_removes_next_to_none_of_a_large_gap",
    "tests/test_lockstep_progress.py::test_a_forged_sensor_frame_from_a_third_node_ends_the_run_naming_it",
    "tests/test_logread.py::test_a_flipped_byte_in_a_middle_chunk_loses_that_chunk_only",
    "tests/test_tcu_handover.py::test_the_api_hands_the_tcu_the_overrides_and_identifies_as_the_command_line",
    "tests/test_tcu_handover.py::test_a_sweep_point_on_a_tcu_process_identifies_as_the_api",
    "tests/test_tcu_handover.py::test_a_tcu_that_dies_mid_run_is_a_failure_named_a_crash_with_its_exit_code",
    "tests/test_tcu_handover.py::test_ten_failing_tests_print_a_few_lines_each",
    "tests/test_logread.py::test_a_log_closed_after_a_fault_is_not_called_damaged",
    "tests/test_logread.py::test_the_whole_log_reads_as_the_mcap_library_reads_it",
    "tests/test_noticed.py::test_replayed_and_forged_frames_are_counted_in_the_summary_and_warned_in_the_log",
    "tests/test_oracle.py::test_the_oracle_covers_the_truth_and_is_not_later_than_bayes",
    # a virtualenv with python-can and cantools made from the registry (about 20 s), then two runs
    "tests/test_python_can_tcu.py::test_a_tcu_with_python_can_alone_passes_the_example_suite_through_the_plugin",
    "tests/test_python_can_tcu.py::test_hil_run_with_the_tcu_external_and_hil_check_judge_its_slip",
    "tests/test_reality.py::test_cli_reality_flag",
    "tests/test_replay.py::test_another_strategy_on_the_same_run",
    "tests/test_replay.py::test_bad_strategy_is_one_line",
    "tests/test_replay.py::test_can_log_needs_a_scenario",
    "tests/test_replay.py::test_can_log_written_by_python_can_replays_the_same",
    "tests/test_replay.py::test_log_cut_at_50_byte_positions",
    "tests/test_replay.py::test_logs_recorded_before_the_redesign_replay_to_the_same_identification[ffcc_a-proposed-1-hub-7d64428.mcap-mcap-frames]",
    "tests/test_replay.py::test_replay_reproduces_the_logged_identification",
    "tests/test_replay.py::test_run_killed_with_sigkill_replays_up_to_the_kill",
    "tests/test_replay.py::test_text_output_reports_speed",
    "tests/test_run.py::test_json_has_the_promised_keys",
    "tests/test_run.py::test_log_names_keep_plant_and_reality_runs_apart_and_stay_inside_out",
    "tests/test_run.py::test_mcap_reads_back_with_the_standard_reader",
    "tests/test_run.py::test_no_scenario_name_puts_a_file_outside_out[../../elsewhere/pwned-False]",
    "tests/test_run.py::test_no_scenario_name_puts_a_file_outside_out[name4-False]",
    "tests/test_run.py::test_no_scenario_name_puts_a_file_outside_out[{tmp}/abs/pwned-False]",
    "tests/test_secoc.py::test_a_third_node_without_the_key_changes_nothing_and_is_counted",
    "tests/test_secoc.py::test_in_process_frames_are_not_authenticated_unless_asked",
    "tests/test_sweep.py::test_a_failing_point_is_a_row_and_the_sweep_goes_on",
    "tests/test_sweep.py::test_a_worker_sigkilled_mid_sweep_costs_only_a_rerun",
    "tests/test_sweep.py::test_bench_identify_on_two_workers_gives_the_serial_verdicts",
    "tests/test_sweep.py::test_eight_points_on_two_workers_equal_the_serial_run",
    "tests/test_sweep.py::test_resume_after_ctrl_c_runs_only_the_missing_points",
    "tests/test_view.py::test_headless_viewer_opens_the_recording_and_screenshots_it",
    "tests/test_view.py::test_hil_run_writes_a_verified_rrd_beside_the_mcap",
    "tests/test_view.py::test_hil_view_save_and_no_rrd",
    "tests/test_view.py::test_the_rrd_streams_in_batches_with_every_point_of_the_log",
    "tests/test_view.py::test_view_of_damaged_and_foreign_files",
    "tests/test_kernel_cache.py::test_hil_run_compiles_in_the_foreground_once",
}
# The tests that time the machine (CPU shares, pacing loops, heartbeats while busy, signals at a delay):
# tests/run.sh runs them alone, never beside another xdist worker (the real-time tests have their own marker).
SERIAL = {
    "tests/test_idle_loop.py::test_a_stall_of_the_pacing_loop_shows_as_late_wakes",
    "tests/test_idle_loop.py::test_two_paced_processes_merge_their_late_periods",
    "tests/test_idle_spin.py::test_a_resting_spinner_hands_its_rests_back_and_counts_no_rest_as_a_gap",
    "tests/test_idle_spin.py::test_a_process_preempting_a_spinner_is_never_time_away",
    "tests/test_idle_spin.py::test_spinners_take_nothing_from_a_process_at_normal_priority",
    "tests/test_vcpu_away.py::test_a_process_stopped_by_the_kernel_is_a_guest_gap_not_time_away",
    "tests/test_vcpu_away.py::test_measure_merges_one_spinner_per_cpu",
    "tests/test_tcu_heartbeats.py::test_heartbeats_keep_coming_while_the_tcu_is_held_by_long_work_and_come_from_its_loop_otherwise",
    # a signal sent a fixed delay after start-up: where it lands depends on the machine's speed (under two
    # workers and a loaded machine the 0.15 s and 0.7 s cases caught the interpreter still starting)
    "tests/test_run.py::test_ctrl_c_during_start_up_is_one_line_not_a_traceback",
    "tests/test_run.py::test_sigterm_of_the_tcu_process_is_one_line_not_a_traceback",
    # removes the kernels' compile stamp: a hil run beside it would say it compiles
    "tests/test_kernel_cache.py::test_hil_run_compiles_in_the_foreground_once",
}


def pytest_itemcollected(item):
    """Marks the SLOW and SERIAL tests."""
    name = item.nodeid.split("[", 1)[0]
    if name in SLOW or item.nodeid in SLOW:
        item.add_marker(pytest.mark.slow)
    if name in SERIAL:
        item.add_marker(pytest.mark.serial)


# Under xdist (--dist worksteal) each worker starts on its half of the tests in collection order and then
# steals from the end of the other's: the longest file first (test_gap.py: about half of the host tests'
# time) runs beside all the others instead of last, its longest test (a ``hil bench gap`` run on two Dask
# workers) first.
LONGEST_FIRST = ["tests/test_gap.py::test_blind_cases_with_a_seed_chosen_now",
                 "tests/test_gap.py"]


def pytest_collection_modifyitems(config, items):
    """Under xdist, LONGEST_FIRST's tests first, in its order (a test matches the first entry its node id
    starts with), so that the longest start at once and the workers steal the rest (``--dist worksteal``).
    A name in SLOW or SERIAL that no collected test has any more is an error (a renamed test would
    otherwise silently leave its tier)."""
    if hasattr(config, "workerinput"):
        def rank(item):
            return next((i for i, p in enumerate(LONGEST_FIRST) if item.nodeid.startswith(p)), len(LONGEST_FIRST))

        items.sort(key=rank)
    if any("::" in str(a) for a in config.args):        # tests picked by name: the rest are not collected
        return
    names = {item.nodeid.split("[", 1)[0] for item in items} | {item.nodeid for item in items}
    files = {name.split("::", 1)[0] for name in names}
    gone = {n for n in SLOW | SERIAL if n.split("::", 1)[0] in files and n not in names}
    if gone:
        raise pytest.UsageError(f"tests/conftest.py lists tests that no longer exist: {sorted(gone)}")


@pytest.fixture
def ffcc_a_path():
    return SCENARIOS / "ffcc_a.toml"


@pytest.fixture
def ffcc_b_path():
    return SCENARIOS / "ffcc_b.toml"


def kill_run_when_log_reaches(args, log_path: Path, min_bytes: int, timeout_s: float = 120.0) -> None:
    """Start ``hil ARGS``, SIGKILL it once ``log_path`` has grown to ``min_bytes`` (a run killed
    halfway, for the crash-recovery tests) and check it died of the signal."""
    proc = subprocess.Popen(hil_command() + list(args), env=subprocess_env(), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and (not log_path.exists() or log_path.stat().st_size < min_bytes):
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL


# -- a TCU maker's virtualenv: python-can and cantools alone (tests/test_python_can_tcu.py, test_tcu_variants.py)
EXAMPLE = ROOT / "docs" / "examples" / "python_can_tcu.py"
THEIR_DBC = SCENARIOS / "suites" / "their.dbc"
INSTALL_TIMEOUT_S = 900


def bare_env() -> dict:
    """This environment without anything that points Python at this project or at another virtualenv."""
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}


@pytest.fixture(scope="module")
def their_tcu(tmp_path_factory):
    """(python, directory): a virtualenv with python-can[multicast] and cantools alone, and a directory
    holding only the example TCU and their DBC; made once per test session (under xdist too)."""
    py, home = once_per_session(tmp_path_factory, "python_can_tcu_venv", _make_their_tcu)
    return Path(py), Path(home)


def _make_their_tcu(home):
    venv = home / "venv"
    py = venv / "bin" / "python"
    r = subprocess.run([sys.executable, "-m", "venv", str(venv)], capture_output=True, text=True, env=bare_env(),
                       timeout=300)
    assert r.returncode == 0, r.stderr
    r = subprocess.run([str(py), "-m", "pip", "install", "-q", "--disable-pip-version-check", "python-can[multicast]",
                        "cantools"], capture_output=True, text=True, env=bare_env(), cwd=home, timeout=INSTALL_TIMEOUT_S)
    if r.returncode != 0:
        why = f"pip could not install python-can and cantools from the registry: {r.stderr.strip()[-500:]}"
        assert os.environ.get("CI") != "true", f"CI=true: this test must run, but {why}"
        pytest.skip(why)
    shutil.copy(EXAMPLE, home)
    shutil.copy(THEIR_DBC, home)
    for module in ("hil", "identifier", "plant"):          # nothing of this project there
        r = subprocess.run([str(py), "-c", f"import {module}"], capture_output=True, text=True, env=bare_env(),
                           cwd=home, timeout=60)
        assert r.returncode != 0 and f"No module named '{module}'" in r.stderr, (module, r.stderr)
    r = subprocess.run([str(py), "-m", "pip", "list", "--format", "json"], capture_output=True, text=True,
                       env=bare_env(), timeout=120)
    names = {p["name"].lower() for p in json.loads(r.stdout)}
    assert {"python-can", "cantools", "msgpack"} <= names and "railway-hil" not in names, names
    print(f"their virtualenv: {', '.join(sorted(names))}")
    return [str(py), str(home)]
