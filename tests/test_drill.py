"""The drill that keeps a strategy's code warm before a slip (identifier/drill.py), and the slip
detector's running sums: neither may change what the TCU identifies."""
import dataclasses
import math
from collections import deque


import numpy as np
import pytest

from identifier import TractionIdentifier
from identifier.drill import Drill
from identifier.tcu import SlipDetector

from .conftest import case_seed


@pytest.fixture(scope="module")
def ffcc_a_run():
    """FFCC-a's scenario and the sensor readings of one real plant run (seed 3)."""
    from hil.benchmarks.identify import generate
    from hil.config import load_scenario
    from tests.conftest import SCENARIOS

    sc = load_scenario(SCENARIOS / "ffcc_a.toml")
    return sc, generate(sc, 3).readings


def identify(settings, strategy, readings):
    ident = TractionIdentifier(settings, strategy, 3)
    events = []
    for r in readings:
        events.extend(ident.on_sensor(r).events)
        if ident.strategy.confirmed or ident.strategy.gave_up:
            break
    return ident, events


@pytest.mark.parametrize("strategy, cycles", [("proposed", 10), ("mdipf", 10), ("proposed_fast", 10),
                                              ("gp", 5)])      # gp's slip: ~100 samples a cycle
def test_the_drill_runs_while_monitoring_and_changes_no_result(ffcc_a_run, strategy, cycles):
    sc, readings = ffcc_a_run
    with_drill = sc.identifier_settings()
    assert with_drill.drill_particles > 0                       # on by default
    without = dataclasses.replace(with_drill, drill_particles=0)
    ident, events = identify(with_drill, strategy, readings)
    plain, plain_events = identify(without, strategy, readings)
    assert plain.drill is None
    assert ident.drill.error is None
    # ~500 monitoring readings: the drill went through whole identifications, not just their start
    assert ident.drill.cycles >= cycles
    assert ident.strategy.confirmed and plain.strategy.confirmed
    assert [(e.step, e.kind, e.params, e.peak_mu_ci, e.peak_creep_ci) for e in events] == \
        [(e.step, e.kind, e.params, e.peak_mu_ci, e.peak_creep_ci) for e in plain_events]


def test_the_speed_drill_goes_through_the_peak_and_confirms():
    """gp's drill (a slip of speed readings on the prior curve): its copy draws the peak and confirms
    within the tolerance of the prior curve's own peak, so the code a real slip runs is the code it
    keeps warm; the copy is small (the drill's draws, not the strategy's)."""
    from hil.config import load_scenario
    from identifier.curve import peak
    from tests.conftest import SCENARIOS

    settings = load_scenario(SCENARIOS / "ffcc_a.toml").identifier_settings()
    drill = Drill(settings, "gp", 64, seed=case_seed())
    assert drill._template.normals.shape[1] == 64
    kinds = []
    for _ in range(600):
        drill.tick()
        s = drill.strategy
        if s is not None and s.confirmed and not kinds:
            kinds.append("confirmed")
            creep_kmh, mu = peak(np.asarray(settings.initial_guess, float))
            assert abs(s.theta_peak[0] / mu - 1) < 0.03 and abs(s.theta_peak[1] / creep_kmh - 1) < 0.1
    assert drill.error is None and kinds == ["confirmed"] and drill.cycles >= 1
    assert Drill(settings, "gp", 4)._template.normals.shape[1] == 50     # gp's fewest draws, not an error


@pytest.mark.parametrize("strategy", ["proposed", "gp"])
def test_the_drill_stops_once_the_strategy_has_samples(ffcc_a_run, strategy):
    sc, readings = ffcc_a_run
    ident = TractionIdentifier(sc.identifier_settings(), strategy, 3)
    ticks_at_first_sample = None
    for r in readings:
        ident.on_sensor(r)
        drill = ident.drill
        state = (drill.cycles, drill._next, id(drill.strategy))
        if ident.strategy.samples and ticks_at_first_sample is None:
            ticks_at_first_sample = state       # (gp takes the samples since the slip's start at once)
        elif ident.strategy.samples:
            assert state == ticks_at_first_sample                # nothing moved after the first sample
        if ident.strategy.samples > 8:
            break
    assert ticks_at_first_sample is not None


@pytest.mark.parametrize("strategy", ["nlls", "proposed_mu0", "proposed_raw", "proposed_oa", "bayes"])
def test_no_drill_for_strategies_with_costly_samples_or_their_own_feed(ffcc_a_run, strategy):
    sc, _ = ffcc_a_run
    assert TractionIdentifier(sc.identifier_settings(), strategy, 3).drill is None


def test_a_failing_drill_stops_and_says_why_without_raising(ffcc_a_run):
    sc, _ = ffcc_a_run
    drill = Drill(sc.identifier_settings(), "proposed", 16)
    for _ in range(40):
        drill.tick()
    assert drill.error is None and drill.strategy is not None
    drill.strategy._v = None              # a broken state: the next sample cannot be stored
    for _ in range(5):
        drill.tick()                      # never raises
    assert drill.error is not None and "NoneType" in drill.error
    assert drill.strategy is None


def reference_detection(creep, threshold, baseline, sigmas=6.0, consecutive=2, hold_sigmas=3.0):
    """The detector with numpy's mean and std of the baseline window at every reading."""
    hist, above = deque(maxlen=baseline), 0
    for step, c in enumerate(creep):
        if len(hist) == baseline:
            base = np.array(hist)
            if c - base.mean() > max(threshold, sigmas * base.std()):
                above += 1
                if above >= consecutive:
                    return step - consecutive + 1
                continue
            above = 0
            if c - base.mean() > hold_sigmas * base.std():
                continue
        hist.append(c)
    return None


def test_a_slip_whose_creep_rises_gently_is_detected():
    """Creep rising by less than the detection threshold per reading once lifted the baseline with
    it (its mean and std followed the rise) and was never detected."""
    seed = case_seed()
    rng = np.random.default_rng(seed)
    n, slip_at = 1500, 600
    creep = 0.33 + 0.007 * rng.standard_normal(n)
    creep[slip_at:] += 0.004 * np.arange(n - slip_at) + 1e-4 * np.arange(n - slip_at) ** 2
    detector = SlipDetector(0.03, 50)
    found = next((detector.detected_step for step, c in enumerate(creep) if detector.update(step, float(c))), None)
    assert found is not None and slip_at <= found <= slip_at + 25, found


@pytest.mark.parametrize("seed", range(6))
def test_slip_detector_running_sums_detect_where_numpy_statistics_do(seed):
    rng = np.random.default_rng(seed)
    n, slip_at = 3000, int(rng.integers(500, 2800))
    level = rng.uniform(0.1, 20.0)                     # creep speed km/h: cancellation grows with it
    noise = rng.uniform(1e-4, 0.02)
    creep = level + noise * rng.standard_normal(n) + 0.01 * np.sin(np.arange(n) / 300.0)
    creep[slip_at:] += 0.05 * np.arange(n - slip_at)                 # km/h per reading
    creep[int(rng.integers(100, slip_at))] += 5.0 * noise          # a lone outlier is not a slip
    threshold = 0.03
    detector = SlipDetector(threshold, 50)
    found = None
    for step, c in enumerate(creep):
        if detector.update(step, float(c)):
            found = detector.detected_step
            break
    assert found == reference_detection(creep, threshold, 50)
    assert found is not None and slip_at <= found <= slip_at + 10


def test_slip_detector_baseline_statistics_do_not_drift_over_a_long_run():
    rng = np.random.default_rng(11)
    detector = SlipDetector(0.03, 50)
    creep = 8.0 + 0.001 * rng.standard_normal(200_000)
    for step, c in enumerate(creep):
        assert not detector.update(step, float(c))
    window = np.array(detector._history)
    n = len(window)
    assert math.isclose(detector._sum / n, window.mean(), rel_tol=0, abs_tol=1e-12)
    std = math.sqrt(max(detector._sum_sq / n - (detector._sum / n) ** 2, 0.0))
    assert math.isclose(std, window.std(), rel_tol=1e-6)


@pytest.mark.parametrize("value, message", [("1", "drill_particles must be 0 (no drill) or at least 2, got 1"),
                                            ("-4", "drill_particles must be 0 (no drill) or at least 2, got -4"),
                                            ("many", "drill_particles: must be an integer, got 'many'")])
def test_a_bad_drill_size_is_refused_by_name(ffcc_a_path, value, message):
    from tests.conftest import hil

    p = hil("run", ffcc_a_path, "--strategy", "proposed", "--bus", "inprocess", "--set",
            f"identifier.drill_particles={value}", timeout=120)
    assert p.returncode == 2
    assert p.stderr.strip().splitlines()[-1].endswith(message) and "Traceback" not in p.stderr


def test_a_tcu_node_drills_in_real_time_only_and_answers_the_same_frames(ffcc_a_run):
    """The drill serves deadlines: a lockstep (or replay) node runs none, a real-time one does, and
    both send the same frames for the same readings (through the fault and the identification)."""
    from hil.bus.frames import FrameCodec
    from hil.tcu_node import TcuNode

    sc, readings = ffcc_a_run
    lockstep, realtime = TcuNode(sc, "proposed", 3), TcuNode(sc, "proposed", 3, realtime=True)
    assert lockstep.identifier.drill is None and realtime.identifier.drill is not None
    plant = FrameCodec(sc.run.exchange_period_s)
    replies = {"lockstep": [], "realtime": []}
    for r in readings:
        frame = plant.sensor(r)
        for name, node in (("lockstep", lockstep), ("realtime", realtime)):
            replies[name] += [(m.arbitration_id, bytes(m.data)) for m in node.handle(frame)]
    assert realtime.identifier.drill.cycles >= 1          # it did drill before the slip
    assert lockstep.events >= 1 and replies["lockstep"] == replies["realtime"]
