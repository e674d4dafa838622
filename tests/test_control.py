"""Closed-loop traction control (issue 36): real runs on scenarios/wet_patch.toml (dry -> wet -> dry, the
driver asking 0.25 of the axle load where the wet patch carries 0.12), the figures checked against an
independent computation from the log's true states, the demand frame, options checked at load."""
from __future__ import annotations

import ast
import math
from pathlib import Path

import numpy as np
import pytest

from hil.bus.frames import FrameCodec
from hil.config import load_scenario
from hil.exchange import run
from hil.log.read import read_log
from hil.tcu_node import TcuNode
from hil.testing import last_line, run_hil
from identifier.control import LAWS
from identifier.messages import DriverDemand, SensorReading

ROOT = Path(__file__).resolve().parent.parent
WET = ROOT / "scenarios" / "wet_patch.toml"
CLOSED_LOOP = [law for law in LAWS if law != "demand"]


def _run(tmp_path_factory, law: str, overrides=None, **kw):
    scenario = load_scenario(WET, {"control.law": law, **(overrides or {})})
    out = tmp_path_factory.mktemp(f"wet-{law}")
    summary = run(scenario, "gp", 1, bus="inprocess", out_dir=out, progress=False, **kw)
    return scenario, summary, read_log(summary["mcap"])


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return {law: _run(tmp_path_factory, law) for law in LAWS}


def _arrays(log):
    st, rail = log.topic("/plant/state"), log.topic("/plant/rail")
    assert len(st) == len(rail) > 0
    return {"t": np.array([m.t_s for m in st]), "creep": np.array([m.creep_speed_kmh for m in st]),
            "mu": np.array([m.mu for m in st]), "torque": np.array([m.torque_nm for m in st]),
            "peak_mu": np.array([m.peak_mu for m in rail]), "peak_creep": np.array([m.peak_creep_kmh for m in rail]),
            "demand_mu": np.array([m.demand_mu for m in rail])}


def test_open_loop_demand_slips_into_macro_slip_on_the_wet_patch(runs):
    """The scenario is a real test: with the demand passed through, the wheelset runs away on the patch."""
    _, summary, _ = runs["demand"]
    assert summary["control"] == "demand"
    assert summary["macro_slip_count"] >= 1 and summary["macro_slip_s"] > 1.0


@pytest.mark.parametrize("law", CLOSED_LOOP)
def test_each_closed_loop_law_keeps_out_of_macro_slip_and_passes_the_demand_where_the_rail_allows(runs, law):
    scenario, summary, log = runs[law]
    a = _arrays(log)
    assert summary["control"] == law
    # macro-slip, from the log's truth: creep above twice the current peak creep for more than 50 ms
    over = a["creep"] > 2 * a["peak_creep"]
    longest = run_len = 0
    for x in over:
        run_len = run_len + 1 if x else 0
        longest = max(longest, run_len)
    assert longest <= 50, f"{law}: {longest} ms above twice the peak creep"
    assert summary["macro_slip_count"] == 0
    demand_nm = a["demand_mu"] * scenario.vehicle.torque_per_mu_nm
    for lo, hi in ((0.5, 1.9), (5.2, 6.0)):          # dry, before the patch and after it
        sel = (a["t"] >= lo) & (a["t"] < hi)
        ratio = a["torque"][sel] / demand_nm[sel]
        assert np.median(ratio) > 0.97, f"{law}: torque {np.median(ratio):.3f} of the demand on dry rail {lo}-{hi} s"
    wet = (a["t"] >= 2.5) & (a["t"] < 4.0)
    assert np.all(a["torque"][wet] < 0.7 * demand_nm[wet]), f"{law}: did not cut the torque on the wet patch"


def test_rail_truth_in_the_log_is_the_scenarios_peaks(runs):
    """/plant/rail holds the peaks the scenario gave each segment (0.30 dry, 0.12 wet at their creeps)."""
    _, _, log = runs["identified"]
    a = _arrays(log)
    for lo, hi, mu, creep in ((0.0, 2.0, 0.30, 1.4), (2.1, 4.0, 0.12, 0.9), (4.2, 6.0, 0.30, 1.4)):
        sel = (a["t"] >= lo) & (a["t"] < hi)
        assert np.allclose(a["peak_mu"][sel], mu, atol=2e-4)
        assert np.allclose(a["peak_creep"][sel], creep, atol=0.01)
    assert np.allclose(a["demand_mu"], 0.25)


@pytest.mark.parametrize("law", ["demand", "constant_creep", "identified"])
def test_figures_match_an_independent_computation_from_the_log(runs, law):
    scenario, summary, log = runs[law]
    a = _arrays(log)
    n_force = scenario.vehicle.axle_load_kg * scenario.vehicle.gravity_ms2
    f_x, cap = a["mu"] * n_force, np.minimum(a["demand_mu"], a["peak_mu"]) * n_force
    assert summary["adhesion_utilisation"] == pytest.approx(f_x.sum() / cap.sum(), rel=1e-9)
    low = (a["demand_mu"] > a["peak_mu"]) | ((a["t"] >= 2.0) & (a["t"] < 3.0)) | ((a["t"] >= 4.0) & (a["t"] < 5.0))
    assert summary["adhesion_utilisation_low"] == pytest.approx(f_x[low].sum() / cap[low].sum(), rel=1e-9)
    metrics = log.topic("/control/metrics")
    assert len(metrics) == 1 and metrics[0].control == law
    assert metrics[0].adhesion_utilisation_low == pytest.approx(summary["adhesion_utilisation_low"])


def test_identified_acts_on_the_identified_curve_and_rearms(runs):
    _, summary, log = runs["identified"]
    events = log.topic("/tcu/identification")
    # a final answer after the drop (confirmed, or unconfirmed with its best estimate: the law reads both);
    # in closed loop gp confirms only a peak the new rail's samples span (test_in_closed_loop_gp_...)
    assert any(e.kind in ("confirmed", "unconfirmed") and e.t_s >= 2.0 for e in events), "no curve to act on"
    assert summary["tcu_rearms"] >= 1          # re-armed once the demand passed through on dry rail again
    assert summary["adhesion_utilisation_low"] > runs["demand"][1]["adhesion_utilisation_low"] + 0.3


def test_identified_jumps_to_a_confirmed_peak_creep_the_creep_passed_well_beyond_once():
    """The law alone, fed readings: at a confirmation whose peak creep the creep exceeds 1.5-fold, the
    set-point becomes 0.98 x that peak creep clipped to its interval, once; a claimed peak just below the
    creep reached (what a change of rail looks like) moves nothing; extremum seeking does the rest."""
    from identifier.control import make_controller
    from identifier.control.base import ControlInput
    from identifier.settings import VehicleModel

    law = make_controller("identified", VehicleModel(120.0, 9000.0, 4.0, 0.5), 1.2)
    assert law.v_hat == 1.2                                     # extremum seeking's start: the nominal peak creep

    def x(step, creep, confirmed=False, peak=math.nan, ci=None):
        return ControlInput(step, step * 1e-3, 1e-3, 20000.0, creep, 5200.0, 0.05, True, ci, None, confirmed, peak)

    law.torque_nm(x(0, 0.9))
    before = law.v_hat                                          # ES's, 0.9 + 2 dithers while not yet limited
    law.torque_nm(x(1, 0.9, True, 0.70, (0.60, 0.80)))          # 0.9 < 1.5 x 0.686: not acted on
    assert law.v_hat == pytest.approx(before, abs=1e-3) and before > 0.9   # one ES step at most
    law.torque_nm(x(2, 1.3))                                    # re-armed: nothing confirmed
    law.torque_nm(x(3, 1.3, True, 0.70, (0.60, 0.80)))
    assert law.v_hat == pytest.approx(0.98 * 0.70, abs=1e-3)
    law.v_hat = 0.5                                             # as if extremum seeking had moved it
    law.torque_nm(x(4, 1.3, True, 0.70, (0.60, 0.80)))
    assert law.v_hat == pytest.approx(0.5, abs=1e-3)            # the same confirmation: no second jump
    law.torque_nm(x(5, 1.6))
    law.torque_nm(x(6, 1.6, True, 0.95, (0.60, 0.90)))          # a peak outside its interval is clipped to it
    assert law.v_hat == pytest.approx(0.98 * 0.90, abs=1e-3)


def test_extremum_seekings_slope_estimate_restarts_at_a_change_of_rail():
    """The law alone: mu^ falls from 0.30 to 0.06 over 15 ms (a wet patch seen through the observer) at four
    phases of the 8 Hz dither, the creep held.  The demodulated step is a slope of the phase's sign: with
    ``reset_mu = 0`` it moves the set-point by more than 0.5 km/h at some phase within 150 ms; with the
    default (0.05) the estimate restarts and the set-point stays within 0.25 km/h of where it was."""
    from identifier.control import make_controller
    from identifier.control.base import ControlInput
    from identifier.settings import VehicleModel

    def excursion(options, k_step):
        law = make_controller("extremum_seeking", VehicleModel(120.0, 9000.0, 4.0, 0.5), 1.2, options)
        moved = 0.0
        for k in range(k_step + 150):
            mu = 0.30 if k < k_step else 0.30 - 0.24 * min(1.0, (k - k_step) / 15)
            law.torque_nm(ControlInput(k, k * 1e-3, 1e-3, 20000.0, 1.2, mu * 10000, mu, True))
            if k == k_step - 1:
                before = law.v_hat
            elif k >= k_step:
                moved = max(moved, abs(law.v_hat - before))
        return moved

    steps = [200 + round(1000 * i / 32) for i in range(4)]        # quarter periods of the dither
    assert max(excursion({"reset_mu": 0.0}, k) for k in steps) > 0.5
    assert max(excursion(None, k) for k in steps) < 0.25

def test_identified_drops_to_a_safe_creep_at_a_change_of_rail_and_climbs_to_the_new_peak():
    """The law alone, its creep following its set-point (a 7 ms lag, as the creep loop's) on a curve
    mu(v) = 2 mu_p (v / v_p) / (1 + (v / v_p)^2) (peak mu_p at v_p), mu^ = mu(creep).  A wet patch (0.30 at
    0.9 km/h -> 0.10 at 1.8 km/h) brings the set-point to half the one held (``drop_ratio``) or below within 20 ms,
    and the climb ends within 0.2 km/h of the patch's peak creep within 0.6 s; the dry rail again (mu^ rising)
    brings it to half the one held or below within 20 ms: below twice the dry peak creep (1.8), which the creep the
    patch carried (1.8) reached.  The same with the estimate withheld (``blind``: the drop is what the law
    measured).  ``max_kmh`` is extremum seeking's 12: the bound on the creep held has its own test."""
    from identifier.control import make_controller
    from identifier.control.base import ControlInput
    from identifier.settings import VehicleModel

    def mu(v, mu_p, v_p):
        return 2 * mu_p * (v / v_p) / (1 + (v / v_p) ** 2)

    for blind in (0, 1):
        law = make_controller("identified", VehicleModel(120.0, 9000.0, 4.0, 0.5), 0.9,
                              {"max_kmh": 12.0, "blind": blind})
        creep, dt, seen = 0.9, 1e-3, {}
        rails = ((0.30, 0.9), (0.10, 1.8), (0.30, 0.9))          # dry, then the patch from 1 s, dry again from 2 s
        for k in range(3000):
            mu_p, v_p = rails[k // 1000]
            m = mu(creep, mu_p, v_p)
            law.torque_nm(ControlInput(k, k * dt, dt, 20000.0, creep, m * 10000, m, True))
            creep += (law.v_hat - creep) * dt / 0.007
            seen[k] = law.v_hat
        assert max(seen[k] for k in range(1005, 1025)) <= 0.5 * seen[999] + 1e-9, "no drop at the patch"
        assert abs(seen[1600] - 1.8) < 0.2, seen[1600]
        assert max(seen[k] for k in range(2005, 2025)) <= 0.5 * seen[1999] + 1e-9, "no drop at the dry rail's return"
        assert max(seen[k] for k in range(2005, 2025)) < 1.8


def test_identified_lifts_the_set_point_to_the_estimates_low_end_and_blind_does_not():
    """The law alone, its creep following its set-point (a 7 ms lag) on mu(v) = 2 mu_p (v / v_p) / (1 + (v / v_p)^2),
    peak 0.30 at 1.8 km/h, the set-point at 0.6 km/h, and an estimate of this rail (dated 0.2 s before, so
    settled) whose 90 % peak-creep interval is [1.5, 2.2] km/h: the estimate is sure the peak lies above the
    set-point.  ``identified`` with ``lift = 1`` holds 0.6 km/h while the creep loop has set the torque for less than ``settle_s``
    (0.1 s), then lifts the set-point to 1.5 km/h at once (what follows is the law's other tests': the creep
    loop's step then exceeds the demand and the rise test sees mu^ rise, docs/design/control.md); ``blind`` (the
    estimate withheld) stays below 1.2 km/h for the 0.15 s (the dither alone climbs slowly); with the default
    ``lift = 0`` the same."""
    from identifier.control import make_controller
    from identifier.control.base import ControlInput
    from identifier.peak_estimate import PeakEstimate
    from identifier.settings import VehicleModel

    def mu(v):
        return 2 * 0.30 * (v / 1.8) / (1 + (v / 1.8) ** 2)

    def set_points(options):
        law = make_controller("identified", VehicleModel(120.0, 9000.0, 4.0, 0.5), 0.9,
                              {"max_kmh": 12.0, "startup_s": 10.0, **options})   # no change test: the lift alone
        law.v_hat, creep, dt, out = 0.6, 0.6, 1e-3, []
        for k in range(150):
            m = mu(creep)
            est = PeakEstimate(k, k * dt, 1.8, (1.5, 2.2), 0.30, (0.25, 0.35), k - 200, 40)
            law.torque_nm(ControlInput(k, k * dt, dt, 20000.0, creep, m * 10000, m, False, estimate=est))
            creep += (law.v_hat - creep) * dt / 0.007
            out.append(law.v_hat)
        return out

    lifted = set_points({"lift": 1})
    assert max(lifted[:95]) < 1.0 and max(lifted[95:110]) >= 1.5 - 1e-9, lifted[95:110]
    assert max(set_points({"lift": 1, "blind": 1})) < 1.2
    assert max(set_points({})) < 1.2                      # the default: off (docs/design/control.md)


def test_identified_drops_when_the_dither_finds_it_past_a_peak_that_mu_hat_never_showed():
    """The law alone, its creep following its set-point with the dither (v^ + 0.05 sin(2 pi 8 t), a 7 ms lag)
    on mu(v) = 2 mu_p (v / v_p) / (1 + (v / v_p)^2), peak 0.30 at 0.9 km/h.  The set-point is put at 2.6 km/h,
    on the curve's tail, with mu^'s mean already there: no change of rail for the change test to see.  The
    dither's slope estimate goes negative and the set-point drops below 1.3 km/h (half the one held, ``drop_ratio``:
    below twice the peak creep) within 0.5 s; with
    ``past_slope = 0`` and ``rise_mu = 0`` (the dither walking down the tail raises mu^ too) the dither alone
    is still above twice the peak creep (1.8 km/h) then.  ``max_kmh`` is extremum seeking's 12 throughout (the
    bound on the creep held has its own test)."""
    from identifier.control import make_controller
    from identifier.control.base import ControlInput
    from identifier.settings import VehicleModel

    def mu(v):
        return 2 * 0.30 * (v / 0.9) / (1 + (v / 0.9) ** 2)

    def set_point_after(options, seconds):
        law = make_controller("identified", VehicleModel(120.0, 9000.0, 4.0, 0.5), 0.9,
                              {"max_kmh": 12.0, **(options or {})})
        law.v_hat, creep, dt = 2.6, 2.6, 1e-3
        law._mu_mean = mu(creep)                          # mu^'s mean already on the tail: no change of rail
        law._was_slipping = True                          # and no drop of the slip detector's
        lowest = law.v_hat
        for k in range(round(seconds / dt)):
            m = mu(creep)
            law.torque_nm(ControlInput(k, k * dt, dt, 20000.0, creep, m * 10000, m, True))
            set_point = law.v_hat + law.options["dither_kmh"] * math.sin(2 * math.pi * 8.0 * k * dt)
            creep += (set_point - creep) * dt / 0.007
            lowest = min(lowest, law.v_hat)
        return lowest

    assert set_point_after(None, 0.5) <= 1.3 + 1e-9
    assert set_point_after({"rise_mu": 0.0}, 0.5) <= 1.3 + 1e-9          # the past-a-peak test alone
    assert set_point_after({"past_slope": 0.0, "rise_mu": 0.0}, 0.5) > 1.8


def test_identified_drops_when_a_recovering_rail_raises_mu_hat_a_little_at_the_creep_held():
    """The law alone (change test and past-a-peak test off, so only the rise test acts), its creep following
    its set-point with a 7 ms lag, on mu(v) = 2 mu_p (v / v_p) / (1 + (v / v_p)^2).  A patch (peak 0.19 at
    2.9 km/h) with the creep held at 2.3 km/h for 0.4 s: the set-point stays above 2 km/h.  Then over 0.1 s
    the rail blends into a dry one (peak 0.30 at 0.9 km/h): mu^ at 2.3 km/h rises only from 0.185 to 0.204.
    The set-point is at half the one held (``drop_ratio``: 1.15 km/h, below twice the dry peak creep) or below by the
    end of the blend; with ``rise_mu = 0`` it is still above
    1.8 km/h (twice the dry peak creep) then.  ``max_kmh`` is extremum seeking's 12 (the bound on the creep
    held has its own test)."""
    from identifier.control import make_controller
    from identifier.control.base import ControlInput
    from identifier.settings import VehicleModel

    def mu(v, mu_p, v_p):
        return 2 * mu_p * (v / v_p) / (1 + (v / v_p) ** 2)

    def set_points(options):
        law = make_controller("identified", VehicleModel(120.0, 9000.0, 4.0, 0.5), 0.9,
                              {"change_mu": 0.0, "past_slope": 0.0, "max_kmh": 12.0, **options})
        law.v_hat, creep, dt = 2.3, 2.3, 1e-3
        law._mu_mean = mu(creep, 0.19, 2.9)               # on the patch already
        law._was_slipping = True                          # and no drop of the slip detector's
        out = []
        for k in range(500):
            blend = min(max((k - 400) / 100, 0.0), 1.0)
            m = (1 - blend) * mu(creep, 0.19, 2.9) + blend * mu(creep, 0.30, 0.9)
            law.torque_nm(ControlInput(k, k * dt, dt, 20000.0, creep, m * 10000, m, True))
            creep += (law.v_hat - creep) * dt / 0.007
            out.append(law.v_hat)
        return out

    default, off = set_points({}), set_points({"rise_mu": 0.0})
    assert min(default[:400]) > 2.0, "a drop on a steady rail"
    assert min(default[400:]) <= 0.5 * max(default) + 1e-9 < 1.8
    assert min(off) > 1.8


def test_a_bound_on_the_creep_held_keeps_a_quick_return_to_dry_rail_out_of_macro_slip(tmp_path_factory):
    """tests/data/far_patch.toml: a patch peaking at 2.81 km/h, the demand just above its peak, then a dry
    rail peaking at 0.89 km/h within 79 ms.  With today's defaults (issue 50: no bound taken from a family's
    extreme; the estimate bounds the creep by the *current* rail's peak) the law holds the creep near the
    patch's peak (above 2 km/h) and the return puts it past twice the dry peak creep for more than 50 ms
    before mu^ has moved: the estimate cannot know the next rail (docs/design/control.md).  With the family's
    bound given as an option (``max_kmh`` 1.6 km/h, issue 36's default) the creep on the patch stays within the
    bound plus the dither and no macro-slip follows.  Both from the log's true states."""
    far = ROOT / "tests" / "data" / "far_patch.toml"

    def longest_over_and_patch_creep(overrides):
        scenario = load_scenario(far, overrides)
        summary = run(scenario, "gp", 1, bus="inprocess", out_dir=tmp_path_factory.mktemp("far"), progress=False)
        a = _arrays(read_log(summary["mcap"]))
        over, longest, run_len = a["creep"] > 2 * a["peak_creep"], 0, 0
        for x in over:
            run_len = run_len + 1 if x else 0
            longest = max(longest, run_len)
        patch = (a["t"] >= 2.5) & (a["t"] < 5.3)
        return summary, longest, float(np.median(a["creep"][patch])), float(np.max(a["creep"][patch]))

    summary, longest, median_kmh, top_kmh = longest_over_and_patch_creep({"control.options.identified.max_kmh": 1.6})
    assert longest <= 50 and summary["macro_slip_count"] == 0, (longest, summary["macro_slip_s"])
    assert top_kmh < 1.6 + 0.15 and median_kmh > 1.3, (median_kmh, top_kmh)
    summary, longest, median_kmh, top_kmh = longest_over_and_patch_creep({})
    print("defaults:", longest, summary["macro_slip_s"], median_kmh)
    assert longest > 50 and summary["macro_slip_count"] >= 1, (longest, summary["macro_slip_s"])
    assert median_kmh > 2.0, median_kmh


def test_a_tcu_process_on_the_bus_gets_the_demand_frame_and_is_judged_the_same(runs, tmp_path_factory):
    """The TCU as its own process on the default bus: lockstep is deterministic, so the same figures."""
    scenario = load_scenario(WET, {"control.law": "constant_creep"})
    summary = run(scenario, "gp", 1, out_dir=tmp_path_factory.mktemp("proc"), progress=False,
                  set_args=["control.law=\"constant_creep\""])
    assert summary["transport"] == "process"
    ref = runs["constant_creep"][1]
    for key in ("adhesion_utilisation", "adhesion_utilisation_low", "macro_slip_s", "recovery_s"):
        assert summary[key] == ref[key], key


def test_the_tcu_commands_what_the_demand_frame_says():
    scenario = load_scenario(ROOT / "scenarios" / "ffcc_a.toml")
    codec = FrameCodec(scenario.run.exchange_period_s)
    node = TcuNode(scenario, "nlls", 1, codec=codec)
    own = scenario.identifier_settings().torque_demand_nm
    omega = 10.0 * scenario.vehicle.gear_ratio / scenario.vehicle.wheel_radius_m
    for step, demand in enumerate((own, 1234.5, 777.0)):
        assert node.handle(codec.demand(DriverDemand(step, demand))) == []
        frame, _ = codec.classify(node.handle(codec.sensor(SensorReading(step, omega, 10.0)))[0])
        assert frame.name == "TorqueCommand" and frame.value.torque_nm == demand
    assert node.handle(codec.demand(DriverDemand(1, 5.0))) == [] and node.rejected["bad_sequence"] == 1


def test_a_control_option_out_of_range_is_one_line_at_load(tmp_path):
    r = run_hil("run", str(WET), "--bus", "inprocess", "--out", str(tmp_path),
                "--set", "control.options.readhesion.cut_fraction=2")
    assert r.returncode == 2
    line = last_line(r.stderr)
    assert "[control.options.readhesion]" in line and "cut_fraction" in line and "Traceback" not in r.stderr
    r = run_hil("run", str(WET), "--control", "oracle", "--out", str(tmp_path))
    assert r.returncode == 2 and "unknown control law" in last_line(r.stderr)
    assert not list(tmp_path.glob("*.mcap"))


def test_the_control_bench_takes_set_and_refuses_a_bad_one_in_one_line_before_any_run(tmp_path):
    """``hil bench control --set``: a field its scenario refuses is one line naming it, before the first run; a
    good one reaches every run (the oracle's rail, scored by the bench, is not the law's) and the report's
    command carries it."""
    import json

    r = run_hil("bench", "control", "--draws", "1", "--duration-s", "13", "--laws", "blind", "--speed-s", "0",
                "--seed", "1", "--set", "identifier.options.gp.change_slow_window=7")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "change_slow_window" in last_line(r.stderr) and "%" not in r.stderr
    args = ["bench", "control", "--draws", "1", "--duration-s", "13", "--laws", "constant_creep", "--speed-s", "0",
            "--seed", "1", "--json"]
    plain = json.loads(run_hil(*args).stdout)
    held = json.loads(run_hil(*args, "--set", "control.options.constant_creep.set_fraction=0.3").stdout)
    assert held["written"]["command"].endswith("--set control.options.constant_creep.set_fraction=0.3")
    eta = [x["results"]["constant_creep"]["eta_low_median"] for x in (plain, held)]
    print("eta_low, default and 0.3 of the nominal peak creep:", eta)
    assert eta[0] != eta[1]


def test_rail_segments_are_addressed_by_set_and_checked():
    sc = load_scenario(WET, {"rail.1.peak_mu": 0.08})
    assert sc.rail.segments[1].curve.peak()[1] == pytest.approx(0.08, abs=1e-6)
    assert sc.fault_curve is sc.rail.segments[1].curve and sc.run.fault_time_s == 2.0
    from hil.errors import ConfigError
    with pytest.raises(ConfigError, match=r"rail has segments 0\.\.2"):
        load_scenario(WET, {"rail.7.peak_mu": 0.08})
    with pytest.raises(ConfigError, match=r"\[\[rail\]\]: rail segment at 1 s starts before the previous one"):
        load_scenario(WET, {"rail.2.start_s": 1.0})
    with pytest.raises(ConfigError, match=r"\[\[rail\]\] 1 start_s: must be > 0"):
        load_scenario(WET, {"rail.1.start_s": -1.0})


def test_only_the_bench_reads_the_truth():
    """No control law can reach the plant: identifier/control imports nothing of plant/ or hil/ (the oracle
    lives in hil/benchmarks/control.py and is no law)."""
    assert "oracle" not in LAWS
    for path in (ROOT / "identifier" / "control").glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
                for name in names:
                    assert not name.split(".")[0] in ("plant", "hil"), f"{path.name} imports {name}"


def test_degraded_adhesion_recovers_with_the_energy_dissipated():
    """A contaminated segment that recovers to dry: its peak rises as the slipping wheel dissipates energy."""
    from plant import WheelsetPlant
    sc = load_scenario(WET, {"rail.1.recovers_to": 0, "rail.1.energy_clean_j": 2e5})
    plant = WheelsetPlant(sc.plant_config())
    peaks = []
    for k in range(1, 4001):
        s = plant.step(0.25 * sc.vehicle.torque_per_mu_nm)
        if k in (2500, 3000, 3500, 4000):           # on the patch (2-4 s), slipping
            peaks.append(sc.rail.peak(s.t_s, s.train_speed_ms, plant.cleaned)[1])
    rho = plant.cleaned[0]
    assert 0.0 < rho < 1.0 and plant.dissipated_j[0] > 0
    assert peaks[3] > peaks[2] > peaks[1] > peaks[0] > 0.12 + 1e-4, peaks      # recovering towards 0.30
    assert math.isclose(rho, 1 - math.exp(-plant.dissipated_j[0] / 2e5), rel_tol=1e-12)


def test_the_rerun_view_shows_the_true_peak_and_the_torque_against_the_demand(runs, tmp_path):
    import subprocess

    from hil import view

    from .test_view import rerun_exe, rrd_rows

    _, summary, log = runs["identified"]
    rrd, _ = view.write_rrd(summary["mcap"], tmp_path / "w.rrd")
    rows, _ = rrd_rows(rrd)
    n = len(log.topic("/plant/rail"))
    for entity in ("/creep/true_peak_kmh", "/mu/true_peak", "/torque/demand_nm", "/torque/applied_nm"):
        assert rows.get((entity, "Scalars:scalars")) == n, entity
    n_estimates = len(log.topic("/tcu/estimate"))        # the TCU's estimate of the rail's peak, and its interval
    assert n_estimates > 0
    for entity in view.ESTIMATE_ENTITIES:
        assert rows.get((entity, "Scalars:scalars")) == n_estimates, entity
    v = subprocess.run([rerun_exe(), "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=120)
    assert v.returncode == 0, v.stderr


def test_checks_judge_a_closed_loop_run_with_windows_from_rail_segments(runs):
    """The control figures are checks (hil.checks.limit) and a rail segment's start is an event; the open-loop
    run fails the same checks the closed-loop one passes."""
    from hil.checks import CheckFailed, in_range, limit, require

    checks = (limit("adhesion_utilisation_low", lo=0.9, req="CTL-1"), limit("macro_slip_s", hi=0.0, req="CTL-2"),
              in_range("/plant/state.creep_speed_kmh", hi=1.8, during=("rail.1", 0.0, 2.0), req="CTL-3"))
    results = require(runs["identified"][1]["mcap"], *checks)
    assert all(r.passed for r in results)
    with pytest.raises(CheckFailed) as e:
        require(runs["demand"][1]["mcap"], *checks)
    text = str(e.value)
    assert "[CTL-1]" in text and "[CTL-2]" in text and "[CTL-3]" in text and "rail.1" in text


@pytest.fixture(scope="module")
def static_rail_run(tmp_path_factory):
    """``identified`` with gp told not to date changes of rail (``rail_changes = false``): it then confirms
    during the change, as every strategy did before."""
    return _run(tmp_path_factory, "identified", {"identifier.options.gp.rail_changes": False})


def test_in_closed_loop_gp_confirms_no_peak_from_the_change_of_rail(runs, static_rail_run):
    """On the wet patch (peak creep 0.9 km/h), ``identified`` holds the creep while the rail changes.  Not
    dating the change, gp confirms within 30 ms of the drop a peak creep more than 10 % off the wet rail's;
    dating it (the default in closed loop), it confirms none before the change has settled (0.2 s), and
    whatever it confirms on the patch is within 10 % of the wet rail's peak creep."""
    for (_, summary, log), wrong in ((static_rail_run, True), (runs["identified"], False)):
        a = _arrays(log)
        conf = [e for e in log.topic("/tcu/identification") if e.kind == "confirmed" and 2.0 <= e.t_s < 4.0]
        first = min(e.t_s for e in log.topic("/tcu/identification") if e.t_s >= 2.0)
        errs = [abs(0.5 * sum(e.peak_creep_ci) / a["peak_creep"][int(np.searchsorted(a["t"], e.t_s))] - 1)
                for e in conf]
        print("rail_changes", not wrong, [(round(e.t_s, 3), tuple(e.peak_creep_ci)) for e in conf], errs)
        if wrong:
            assert conf and conf[0].t_s < 2.03 and errs[0] > 0.10
        else:
            assert all(e.t_s >= first + 0.2 for e in conf) and all(x <= 0.10 for x in errs)


def test_in_closed_loop_gps_interval_holds_the_peak_the_law_holds_the_creep_at(tmp_path_factory):
    """Draw 37 of ``hil bench control``'s seed 1885060422 (a patch from 11.87 s peaking at 0.491 km/h), 13 s
    of it: gp confirms on the patch while ``identified`` holds the creep near the peak.  With the train-speed
    line extrapolated from the restart and no interval floors (the closed-loop options off) the creep drifts
    low and the 90 % interval misses the true peak creep from below; with the defaults (the line refitted
    every sample, the floors) it holds the true peak, mu and creep."""
    from hil.benchmarks.control import BASE, draw_text
    from hil.config import parse_scenario

    text, drawn = draw_text((ROOT / BASE).read_text(), 1885060422, 37, 30.0, "narrow")   # issue 36's family
    assert 0.45 < drawn["patches"][-1]["peak_creep_kmh"] < 0.55

    # the law this was measured with (issue 36's identified: replay's options for logs before the peak estimate),
    # so the check stays one of gp's options
    from hil.replay import NEWER_THAN_SOME_LOGS
    law_then = next(o for key, _, o in NEWER_THAN_SOME_LOGS if key == "identified_peak_estimate")

    def confirmed(overrides):
        scenario = parse_scenario(text, "draw 37", {"control.law": "identified", "run.duration_s": 13.0, **law_then,
                                                    **overrides})
        summary = run(scenario, "gp", 1885060422 % 1000 + 37, bus="inprocess", out_dir=tmp_path_factory.mktemp("d37"),
                      progress=False)
        log = read_log(summary["mcap"])
        rows = [r for r in summary["drop_identification"] if r["t_identified_s"] is not None and r["t_s"] > 11.0]
        assert len(rows) == 1, summary["drop_identification"]
        e = next(e for e in log.topic("/tcu/identification") if e.kind == "confirmed" and e.t_s > 11.0)
        return rows[0], e

    # (and gp's one_rail off: it would restart the window whose creep drifts, and confirm later, right)
    off = {"identifier.options.gp.track_train_speed": False, "identifier.options.gp.floor_peak_mu": 0.0,
           "identifier.options.gp.floor_peak_creep_kmh": 0.0, "identifier.options.gp.one_rail": False}
    row, e = confirmed(off)
    print("off:", e.t_s, e.peak_mu_ci, e.peak_creep_ci, row)
    assert row["interval_holds_truth"] is False and e.peak_creep_ci[1] < 0.48
    row, e = confirmed({})
    print("defaults:", e.t_s, e.peak_mu_ci, e.peak_creep_ci, row)
    assert row["interval_holds_truth"] is True and row["peak_creep_err_percent"] < 5.0


def test_identification_is_reported_per_drop_against_the_rail_then(static_rail_run):
    _, summary, log = static_rail_run        # a run that confirms on the patch (the figures are the point here)
    rows = summary["drop_identification"]
    assert [r["t_s"] for r in rows] == [2.0]                     # one drop: dry -> wet at 2 s ("dry again" is none)
    conf = next(e for e in log.topic("/tcu/identification") if e.kind == "confirmed" and 2.0 <= e.t_s < 4.0)
    assert rows[0]["t_identified_s"] == pytest.approx(conf.t_s)
    grid = np.linspace(0.0, 10.0, 200_001)
    p = np.asarray(conf.params)
    mu = p[0] + p[1] * np.exp(p[3] * grid) + p[2] * np.exp(p[4] * grid)
    i = int(np.argmax(mu))
    a = _arrays(log)
    j = int(np.searchsorted(a["t"], conf.t_s))
    assert rows[0]["peak_mu_err_percent"] == pytest.approx(100 * abs(mu[i] - a["peak_mu"][j]) / a["peak_mu"][j],
                                                           rel=1e-3)
    assert rows[0]["peak_creep_err_percent"] == pytest.approx(
        100 * abs(grid[i] - a["peak_creep"][j]) / a["peak_creep"][j], rel=1e-3, abs=0.01)
    (m0, m1), (c0, c1) = conf.peak_mu_ci, conf.peak_creep_ci
    holds = not conf.peak_open and m0 <= a["peak_mu"][j] <= m1 and c0 <= a["peak_creep"][j] <= c1
    assert rows[0]["interval_holds_truth"] is bool(holds)


def test_an_external_tcu_gets_the_demand_frame_and_is_judged_the_same(runs, tmp_path):
    """``hil tcu --control constant_creep`` on a bus, ``hil run --tcu external`` on it: the plant judges the
    external TCU from its own truth, with the figures of the built-in one (lockstep is deterministic)."""
    import json
    import subprocess

    from hil.bus.link import Hub
    from hil.testing import hil_command, subprocess_env

    hub = Hub()
    url = f"remote:ws://127.0.0.1:{hub.port}/"
    tcu = None
    try:
        tcu = subprocess.Popen(hil_command() + ["tcu", str(WET), "--bus", url, "--control", "constant_creep", "--json"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=subprocess_env(), cwd=ROOT)
        r = run_hil("run", str(WET), "--bus", url, "--tcu", "external", "--out", str(tmp_path), "--json", "--no-rrd",
                    "--control", "constant_creep")
        out, err = tcu.communicate(timeout=120)
    finally:
        if tcu is not None and tcu.poll() is None:
            tcu.kill()
        hub.stop()
    assert r.returncode == 0, r.stderr
    assert tcu.returncode == 0, err
    s, ref = json.loads(r.stdout), runs["constant_creep"][1]
    assert s["control"] == "external"
    for key in ("adhesion_utilisation", "adhesion_utilisation_low", "macro_slip_s", "recovery_s", "reaction_ms"):
        assert s[key] == ref[key], key
    assert json.loads(out)["rejected_frames"] == {}


def test_the_control_bench_reports_every_law_with_the_oracle_on_top_and_the_identification_per_drop(tmp_path):
    """`hil bench control` as a user runs it, on one short draw (seed drawn now, printed): the keys scripts read,
    the report written, the oracle's ceiling, and the identifier's confirmations per drop."""
    import json

    from .conftest import case_seed

    seed = case_seed("control bench")
    r = run_hil("bench", "control", "--draws", "1", "--duration-s", "12", "--speed-s", "0", "--seed", str(seed),
                "--family", "narrow", "--laws", "extremum_seeking,identified,blind,oracle", "--json", "--doc",
                str(tmp_path), timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout)
    assert out["seed"] == seed and out["draws"] == 1
    for law in ("extremum_seeking", "identified", "oracle"):
        res = out["results"][law]
        for key in ("eta_low_median", "eta_low_p5", "eta_median", "macro_slip_fraction", "reaction_median_ms",
                    "recovery_median_s", "torque_ripple_median_percent", "runs"):
            assert key in res, (law, key)
        assert len(res["runs"]) == 1
        for key in ("confirmations", "wrong_confirmation_fraction", "estimate_coverage", "lead_time_median_ms",
                    "lead_time_within_100ms_fraction"):
            assert key in res, (law, key)
    ident, blind = out["results"]["identified"], out["results"]["blind"]
    assert out["family"]["name"] == "narrow"
    assert ident["blind_eta_low_median"] == blind["eta_low_median"]
    assert ident["contribution_eta_low_median"] == pytest.approx(
        ident["runs"][0]["adhesion_utilisation_low"] - blind["runs"][0]["adhesion_utilisation_low"])
    assert ident["contribution_eta_low_p5"] == pytest.approx(ident["contribution_eta_low_median"])
    assert 0.0 <= ident["estimate_coverage"] <= 1.0
    oracle = out["results"]["oracle"]
    assert oracle["macro_slip_fraction"] == 0.0 and oracle["eta_low_median"] > 0.9, oracle
    a = out["results"]["identified"]["runs"][0]
    # the identification per drop, counted here from the run's rows
    rows = a["drop_identification"]
    confirmed = [d for d in rows if d["t_identified_s"] is not None]
    assert out["results"]["identified"]["identification"] == {
        "drops": len(rows), "confirmed": len(confirmed),
        "holding_truth": sum(1 for d in confirmed if d["interval_holds_truth"] is True),
        "peak_creep_within_10_percent": sum(1 for d in confirmed if d["peak_creep_err_percent"] <= 10.0)}
    report = (tmp_path / "control-narrow.md").read_text()          # another family than the default: its name
    assert f"seed {seed}" in report
    assert "| 60 s logged run >= 10 x real time | not measured |" in report      # --speed-s 0: no speed run
    assert f"the identifier confirmed {len(confirmed)} of {len(rows)} drops" in report
    assert (tmp_path / "control-narrow-eta-low.png").stat().st_size > 1000
    # the estimate under each law: its changes of rail counted here from the runs, its lead time within 100 ms
    for law in ("extremum_seeking", "oracle"):
        leads = out["results"][law]["runs"][0]["lead_times_ms"]
        within = sum(1 for x in leads if x is not None and x <= 100.0) / len(leads) if leads else None
        cell = "-" if within is None else f"{within:.0%}"
        assert f"| {law} | {len(leads)} | {cell} | " in report, law


def test_macro_slip_counts_a_wheel_sliding_backwards():
    """|creep| against twice the peak creep: a wheel at -48 km/h for 0.2 s under a torque of the wrong sign is
    0.2 s of macro-slip, one episode (issue 50)."""
    from hil.traction import metrics

    n = 1000
    t = np.arange(n) * 1e-3
    creep = np.full(n, 0.5)
    creep[400:600] = -48.0
    c = {"t_s": t, "creep_speed_kmh": creep, "mu": np.full(n, 0.2), "torque_nm": np.full(n, 100.0),
         "demand_mu": np.full(n, 0.2), "peak_mu": np.full(n, 0.3), "peak_creep_kmh": np.full(n, 1.0),
         "train_speed_ms": np.full(n, 10.0)}
    m = metrics(c, (), 1e-3, 1.3e5, 1000.0)
    assert m["macro_slip_count"] == 1 and m["macro_slip_s"] == pytest.approx(0.2)


# -- issue 50: the peak estimate and the law acting on it --------------------------------------------------------
def _rail_run(tmp_path_factory, name, overrides, law="identified"):
    return _run(tmp_path_factory, law, {"run.duration_s": 6.0, **overrides})


def test_identified_holds_the_creep_near_a_heavy_haul_rails_peak(tmp_path_factory):
    """A heavy-haul dry rail (peak creep 3.2 km/h, flat top) around a wet patch, the driver asking more than the
    dry rail carries: over the last second, on dry rail again, ``identified`` holds the creep within 10 % of the
    true peak creep (the estimate's interval puts the peak there; the dither alone creeps towards it slowly)."""
    _, summary, log = _rail_run(tmp_path_factory, "heavy", {
        "rail.0.peak_creep_kmh": 3.2, "rail.2.peak_creep_kmh": 3.2, "control.demand_mu": [[0.0, 0.26], [0.5, 0.34]]})
    a = _arrays(log)
    last = a["t"] >= a["t"][-1] - 1.0
    assert np.all(a["demand_mu"][last] > a["peak_mu"][last])       # the law, not the demand, sets the creep
    creep = float(np.median(a["creep"][last]))
    peak = float(np.median(a["peak_creep"][last]))
    print("heavy haul: creep held", creep, "true peak creep", peak, summary["adhesion_utilisation_low"])
    assert peak == pytest.approx(3.2, rel=0.02)
    assert abs(creep - peak) <= 0.10 * peak


def test_identified_keeps_a_leaf_patch_out_of_macro_slip(tmp_path_factory):
    """A leaf patch (peak mu 0.05 at 0.3 km/h) after a dry rail held near 1.4 km/h: no macro-slip, in either
    direction (|creep| above twice the peak creep for 50 ms)."""
    _, summary, log = _rail_run(tmp_path_factory, "leaf", {"rail.1.peak_mu": 0.05, "rail.1.peak_creep_kmh": 0.3})
    a = _arrays(log)
    on_patch = (a["t"] > 2.1) & (a["t"] < 3.9)
    assert float(np.median(a["peak_creep"][on_patch])) == pytest.approx(0.3, rel=0.05)
    print("leaf:", summary["macro_slip_s"], summary["adhesion_utilisation_low"])
    assert summary["macro_slip_s"] == 0.0 and summary["macro_slip_count"] == 0


def test_the_estimate_agrees_with_its_numpy_reference():
    """The compiled recursion (identifier/kernels.py) and the numpy reference give the same estimates, through
    a change of rail (the run length pruned, the change dated)."""
    from identifier.peak_estimate import PeakEstimator

    rng = np.random.default_rng(50)
    a, b = PeakEstimator(1e-3), PeakEstimator(1e-3, compiled=False)
    for k in range(3000):
        v = 0.6 + 0.4 * math.sin(k / 60.0)
        m = (0.25 if k < 1500 else 0.1) * 2 * v / (1 + v * v) + 0.001 * rng.standard_normal()
        ea, eb = a.add(k, k * 1e-3, v, m), b.add(k, k * 1e-3, v, m)
        assert ea.peak_creep_ci == pytest.approx(eb.peak_creep_ci, rel=1e-9)
        assert ea.peak_mu == pytest.approx(eb.peak_mu, rel=1e-9) and ea.since_step == eb.since_step
    assert 1500 <= ea.since_step < 1600                      # the change dated, the dry samples forgotten
    assert ea.peak_mu_ci[0] < 0.1 < ea.peak_mu_ci[1]


def test_the_estimates_90_percent_intervals_cover_drawn_curves():
    """300 curves of the ``default`` fault family (seed printed), each swept from 0.05 km/h to 1.5 x its peak creep
    over 0.6 s with the sensors' noise: the final 90 % peak-creep interval holds the true peak creep in at least
    70 % of them and at most 98 % (measured 85 %: issue 50's 85-95 % target on static rails; a correct
    implementation at 85 % falls below 70 % of 300 with probability < 1e-5)."""
    from plant.families import sample_curves
    from identifier.peak_estimate import PeakEstimator

    from .conftest import case_seed

    seed = case_seed("estimate coverage")
    print("seed", seed)
    rng = np.random.default_rng(seed)
    batch = sample_curves("default", 300, rng, 10.0)
    hits = 0
    for i in range(300):
        v = np.linspace(0.05, 1.5 * batch.peak_creep_kmh[i], 600)
        mu = batch.mu(v)[i]
        e = PeakEstimator(1e-3)
        for k in range(600):
            est = e.add(k, k * 1e-3, v[k] + 0.0075 * rng.standard_normal(), mu[k] + 0.001 * rng.standard_normal())
        hits += est.peak_creep_ci[0] <= batch.peak_creep_kmh[i] <= est.peak_creep_ci[1]
    print("coverage", hits / 300)
    assert 0.70 * 300 <= hits <= 0.98 * 300


@pytest.mark.slow
def test_blind_differs_from_identified_where_the_estimate_came_in_time():
    """On drawn bench cases (seed printed), the draws where an estimate held the true peak creep within 10 %
    inside 100 ms of a change of rail: ``identified`` with the lift on (``lift = 1``; the default acts on no
    estimate, docs/design/control.md) and ``blind`` (the same law, the estimate withheld) do not score the same
    on at least one of them.  One such draw is not enough: the lift acts only where the estimate's interval lies
    above the set-point held, which an estimate in time need not show (seed 807890090: equal on draws 1 and 2)."""
    from hil.benchmarks.control import BASE, draw_text, run_point

    from .conftest import case_seed

    seed = case_seed("blind")
    print("seed", seed)
    in_time = 0
    for index in range(12):
        text, drawn = draw_text((ROOT / BASE).read_text(), seed, index, 13.0)
        if not drawn["patches"]:            # a draw may hold no patch (one dry rail: no change)
            continue
        item = {"index": index, "text": text, "run_seed": seed % 1000 + index,
                "set": {"control.options.identified.lift": 1}}
        ident = run_point({**item, "law": "identified"})
        if any(x is not None and x <= 100.0 for x in ident["lead_times_ms"]):
            in_time += 1
            blind = run_point({**item, "law": "blind"})
            print(index, ident["adhesion_utilisation_low"], blind["adhesion_utilisation_low"])
            if ident["adhesion_utilisation_low"] != blind["adhesion_utilisation_low"]:
                return
    assert in_time, f"no estimate in time on 12 draws of seed {seed}"
    pytest.fail(f"identified scored as blind on all {in_time} draws of seed {seed} with an estimate in time")


def test_the_tcus_peak_estimate_travels_in_its_frame_is_logged_and_summarised_in_either_transport(runs, tmp_path):
    """Issue 50: the TCU's estimate of the current rail's peak goes on the bus (TcuEstimate, every tenth period in
    closed loop) and the plant logs it (``/tcu/estimate``) and judges it (``peak_estimate`` per rail change).
    The logged estimates are the identifier's own to the bit (the same TCU run again on the log's plant frames,
    as ``hil replay`` runs it), and a TCU in its own process on the local bus gives the same log rows and
    summary as the in-process one."""
    import json

    from hil.replay import load_mcap

    scenario, summary, log = runs["identified"]
    rows = [(m.step, m.peak_creep_kmh, (m.peak_creep_lo_kmh, m.peak_creep_hi_kmh), m.peak_mu,
             (m.peak_mu_lo, m.peak_mu_hi), m.since_step) for m in log.topic("/tcu/estimate")]
    assert len(rows) > 100
    src = load_mcap(summary["mcap"])
    node = TcuNode(scenario, "gp", 1, codec=FrameCodec(scenario.run.exchange_period_s))
    for msg in src.frames:
        node.handle(msg)
    own = [(e.step, e.peak_creep_kmh, tuple(e.peak_creep_ci), e.peak_mu, tuple(e.peak_mu_ci), e.since_step)
           for e in node.identifier.estimate_trace]
    assert rows == own
    changes = [x["change_s"] for x in summary["peak_estimate"]]
    assert changes == [s.start_s for s in scenario.rail.segments[1:]]
    r = run_hil("run", str(WET), "--set", "control.law=identified", "--bus", "local", "--json", "--out",
                str(tmp_path), timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    other = json.loads(r.stdout)
    assert other["transport"] == "process" and summary["transport"] == "inprocess"
    assert other["peak_estimate"] == summary["peak_estimate"]
    other_rows = [(m.step, m.peak_creep_kmh, (m.peak_creep_lo_kmh, m.peak_creep_hi_kmh), m.peak_mu,
                   (m.peak_mu_lo, m.peak_mu_hi), m.since_step) for m in read_log(other["mcap"]).topic("/tcu/estimate")]
    assert other_rows == rows


def test_gp_confirms_nothing_from_samples_that_straddle_a_change_of_rail_and_the_bench_judges_the_span(tmp_path_factory):
    """Draw 2 of ``hil bench control``'s seed 939869376 (the default family), ``identified``: the rail changes
    through a transition of tenths of a second from about 2.4 s.  With gp's ``one_rail`` off it confirms, tens of
    milliseconds after a restart, from samples over which the true peak moves beyond its interval (a blend,
    attributed to no one rail segment); with the default, no confirmation's samples straddle a change and it
    confirms later from the new rail's samples alone, its interval holding the true peak over their whole span.
    The log carries each confirmation's span (``samples_from_s``, ``samples_to_s``, through the TcuInterval frame),
    and the bench's judgement (``confirmation_figures``) reads it: the same confirmation said to rest on samples
    from before the change is wrong, though right at its publish time."""
    import dataclasses

    from hil.benchmarks.control import BASE, DEFAULT_FAMILY, confirmation_figures, draw_text
    from hil.config import parse_scenario
    from identifier.messages import IdentificationEvent

    text, _ = draw_text((ROOT / BASE).read_text(), 939869376, 2, 13.0, DEFAULT_FAMILY)

    def confirmations(overrides):
        scenario = parse_scenario(text, "draw 2", {"control.law": "identified", "run.duration_s": 3.3, **overrides})
        summary = run(scenario, "gp", 939869376 % 1000 + 2, bus="inprocess", mode="lockstep",
                      out_dir=tmp_path_factory.mktemp("d2"), progress=False)
        log = read_log(summary["mcap"])
        rail = log.topic("/plant/rail")
        truth = {"t_s": np.array([m.t_s for m in rail]), "peak_mu": np.array([m.peak_mu for m in rail]),
                 "peak_creep_kmh": np.array([m.peak_creep_kmh for m in rail])}
        conf = [e for e in log.topic("/tcu/identification") if e.kind == "confirmed"]
        return truth, conf

    def span_holds(truth, e):
        span = (truth["t_s"] >= e.samples_from_s - 1e-9) & (truth["t_s"] <= e.samples_to_s + 1e-9)
        mu, v = truth["peak_mu"][span], truth["peak_creep_kmh"][span]
        return bool(span.any() and np.all((e.peak_mu_ci[0] <= mu) & (mu <= e.peak_mu_ci[1])
                                          & (e.peak_creep_ci[0] <= v) & (v <= e.peak_creep_ci[1])))

    truth, off = confirmations({"identifier.options.gp.one_rail": False})
    print("one_rail off:", [(e.samples_from_s, e.samples_to_s, tuple(e.peak_creep_ci)) for e in off])
    assert off and all(e.samples_from_s < e.samples_to_s == pytest.approx(e.t_s) for e in off)
    blend = [e for e in off if not span_holds(truth, e)]
    assert blend
    span = (truth["t_s"] >= blend[0].samples_from_s) & (truth["t_s"] <= blend[0].samples_to_s)
    moved = np.ptp(truth["peak_mu"][span])
    assert moved > blend[0].peak_mu_ci[1] - blend[0].peak_mu_ci[0]          # the true peak moved beyond the interval
    assert confirmation_figures(truth, off)["wrong"] >= len(blend)

    truth, on = confirmations({})
    print("default:", [(e.samples_from_s, e.samples_to_s, tuple(e.peak_creep_ci)) for e in on])
    assert on and all(span_holds(truth, e) for e in on)
    assert confirmation_figures(truth, on) == {"confirmations": len(on), "wrong": 0, "zero_width": 0,
                                               "wrong_at_publish": 0, "span_not_stated": 0}
    e = on[0]
    as_event = IdentificationEvent(e.step, e.t_s, e.kind, e.correction, tuple(e.params), e.j_ef, e.samples,
                                   tuple(e.peak_mu_ci), tuple(e.peak_creep_ci), e.peak_open, e.samples_from_s,
                                   e.samples_to_s)
    before_change = dataclasses.replace(as_event, samples_from_s=2.0)      # the dry rail's samples too
    fig = confirmation_figures(truth, [before_change])
    assert fig["wrong"] == 1 and fig["wrong_at_publish"] == 0
    unstated = dataclasses.replace(as_event, samples_from_s=math.nan, samples_to_s=math.nan)
    assert confirmation_figures(truth, [unstated])["span_not_stated"] == 1
