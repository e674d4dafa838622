"""hil gap: blind to the truth, right on runs whose effect it is not told.

Cases are drawn with a seed chosen when the test runs (printed, for reproduction:
``hil bench gap --seed S``), so the diagnosis cannot have been tuned to them.
"""
import json
import os
from collections import Counter
from pathlib import Path

import numpy as np
import pytest


from hil.benchmarks.gap import DEFAULT_MIX, draw_case, parse_mix
from hil.gap import diagnose, read_real_log
from hil.gap.data import describe
from hil.log.read import read_log
from hil.exchange import run
from hil.effects import EFFECTS, TRUTH_KEY
from hil.config import load_scenario

from .conftest import ROOT, SCENARIOS, case_seed, hil, once_per_session

FFCC_A = SCENARIOS / "ffcc_a.toml"
# A quantised speed steps at slightly different instants in the real run and in the augmented
# model's replay, so its held-out gap shrinks less, and by an amount that varies with the run's
# noise: quantum 0.0744 rad/s over run seeds 1001-1010 gave 73-100 % (median 92 %), the same
# with observer poles 400 and 500 rad/s; a local test run failed once on 62.9 % at quantum 0.0744.
# (The diagnosis only names an effect whose held-out shrink is >= 50 %, so the floor must sit above that.)


def fresh_seed() -> int:
    return case_seed("gap test")


@pytest.fixture(scope="module")
def scenario():
    return load_scenario(FFCC_A)


def test_nominal_run_has_no_gap(tmp_path, scenario):
    seed = fresh_seed() % 100000
    summary = run(scenario, "nlls", seed, bus="inprocess", out_dir=tmp_path, progress=False, log=print)
    out, _ = diagnose(read_real_log(summary["mcap"]), scenario, identify=False)
    assert out["which"]["named"] == "none"
    assert out["which"]["gap_present"] is False
    for s, v in out["where"]["per_signal"].items():
        assert v["rmse_in_noise_units"] < 1.3, s


# -- the blind bench: one ``hil bench gap`` run -----------------------------------------------------------
#: the cases of the bench run, by kind: three effects in the candidates' forms, one in a held-out form,
#: one rail curve 1-5 % off (drawn as ``hil bench gap`` draws them).  An effect outside every class is
#: tests/test_gap.py's tachometer test (its answer and its sparse description), not a case here.
BENCH_KINDS = {"library_form": 3, "held_out_form": 1, "rail": 1}
BENCH_MIX = ",".join(f"{k}={v}" for k, v in BENCH_KINDS.items())
BENCH_CASES = sum(BENCH_KINDS.values())


def bench_seed(seed: int) -> int:
    """The first bench seed from ``seed`` on whose ``BENCH_CASES`` cases under ``BENCH_MIX`` are
    ``BENCH_KINDS`` (no quantiser among the library forms: it is judged apart, ``which.quantiser``; no
    second-order lag either: its natural frequency trades against its damping, so the 20 % bound on a
    one-parameter form's error does not hold for it: 11.5 Hz at zeta 0.65 was fitted 13.4 Hz at zeta 0.73,
    the same 2 zeta / w within 3 %; the bench reports its error), from ``draw_case`` as the bench draws
    them: a pure function of the seed chosen when the test runs."""
    mix = parse_mix(BENCH_MIX)
    while True:
        cases = [draw_case(seed, i, mix)[:2] for i in range(BENCH_CASES)]
        if Counter(k for k, _ in cases) == BENCH_KINDS and not any(
                k == "library_form" and {"sensor_quantisation", "adhesion_lag2"} & set(e) for k, e in cases):
            return seed
        seed = (seed + 1) % (1 << 31)


def truth_classes(effects: dict) -> set:
    """The classes a right answer may name: those of the effects that are candidates."""
    return {EFFECTS[n].effect_class for n in effects if EFFECTS[n].candidate}


def test_blind_cases_with_a_seed_chosen_now(tmp_path):
    """``hil bench gap --workers 2`` (a local Dask cluster) on three effects in the candidates' forms, one
    in a held-out form and one rail curve 1-5 % off: no false-confident name on any, at least two of the three library forms named right, the rail reported as
    the rail (``rail_is_the_nuisance``); and its JSON and --doc files hold what they promise
    (``bench_json_keys``).  One bench run for the three checks (a diagnosis per case is what costs)."""
    seed = bench_seed(fresh_seed())
    print(f"bench: hil bench gap {FFCC_A} --cases {BENCH_CASES} --seed {seed} --mix {BENCH_MIX} --workers 2")
    r = hil("bench", "gap", FFCC_A, "--cases", BENCH_CASES, "--seed", seed, "--json", "--doc", tmp_path / "doc",
            "--mix", BENCH_MIX, "--workers", 2, timeout=1200, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    records = out["records"]
    for rec in records:
        print(rec["kind"], rec["effects"], "->", rec["named"], rec["confidence"], rec.get("param_err_percent"),
              rec["shrink_percent"], rec["verdict"][:200])
    by_kind = {k: [rec for rec in records if rec["kind"] == k] for k in BENCH_KINDS}
    assert {k: len(v) for k, v in by_kind.items()} == BENCH_KINDS, [rec["kind"] for rec in records]
    blind = by_kind["library_form"] + by_kind["held_out_form"] + by_kind["rail"]
    for rec in blind:
        false_confident = bool(set(rec["named_set"]) - truth_classes(rec["effects"]))
        assert rec["false_confident"] == false_confident, rec            # the bench scores it as we do
        assert not false_confident, rec
    lib = by_kind["library_form"]
    right = [rec["named"] == EFFECTS[next(iter(rec["effects"]))].effect_class for rec in lib]
    assert [rec["correct"] for rec in lib] == right, lib
    assert sum(right) >= 2, lib
    for rec, ok in zip(lib, right):
        if ok:
            assert rec["param_err_percent"] <= 20, rec
            assert rec["shrink_percent"] >= 80, rec
    rail_is_the_nuisance(*by_kind["rail"])
    bench_json_keys(out, r.stderr, seed, tmp_path / "doc")


def rail_is_the_nuisance(rec: dict) -> None:
    """The issue's most common real gap: the rail's curve 1-5 % off the scenario's (its creep sometimes
    scaled too) was named load_transfer with 99 % shrink.  Now it is the nuisance, reported with its size
    (or, at worst, 'not separable'), never a confident effect."""
    scale = rec["effects"]["rail_curve"]["peak_mu_scale"]
    assert rec["named"] == "none" and rec["named_set"] == [], rec
    assert rec["confidence"] in ("nuisance", "not_separable"), rec
    assert "rail_peak_mu_percent" in rec, rec                                     # reported ...
    assert rec["rail_peak_mu_percent"] == pytest.approx((scale - 1) * 100, abs=0.5), rec   # ... with its size


def bench_json_keys(out: dict, stderr: str, seed: int, doc) -> None:
    """``hil bench gap --json --doc``: the figures, the seed, the per-case records and the files."""
    for k in ("cases", "top1_accuracy", "none_accuracy", "median_shrink_percent", "median_param_err_percent",
              "confusion", "set_accuracy", "false_confident_rate", "two_effect_both_found", "seed"):
        assert k in out
    assert out["cases"] == BENCH_CASES and out["seed"] == seed and f"seed {seed}" in stderr
    for k in ("top1_accuracy", "none_accuracy", "false_confident_rate"):
        assert out[k] is None or 0 <= out[k] <= 1
    for rec in out["records"]:        # a diagnosis' CPU seconds beside its wall seconds (one process, two cores)
        assert 0 < rec["diagnosis_cpu_s"] <= 2 * rec["diagnosis_s"] + 0.5, rec
    assert out["median_diagnosis_cpu_s"] > 0 and "s of CPU)" in (doc / "gap.md").read_text()
    assert "false-confident" in (doc / "gap.md").read_text()
    assert f"--seed {seed} --mix {BENCH_MIX} --doc {doc}`" in (doc / "gap.md").read_text()   # the command as run
    assert json.loads((doc / "gap.json").read_text())["cases"] == BENCH_CASES
    assert sum(sum(row.values()) for row in out["confusion"].values()) == BENCH_CASES
    assert f"case {BENCH_CASES}/{BENCH_CASES}" in stderr
    # a held-out case: its form is not among the candidates (the class's other forms are); the truth
    # itself is scored as a candidate (the limit) wherever it has an exact model
    for k in ("held_out_separable", "held_out_beyond_the_log", "wrong_beyond_the_log", "wrong_separable"):
        assert isinstance(out[k], int)
    for rec in out["records"]:
        if rec["kind"] == "held_out_form":
            (form,) = rec["effects"]
            assert rec["excluded"] == [form] and form not in rec["ranked_candidates"]
            siblings = {n for n, s in EFFECTS.items() if s.candidate and n != form
                        and s.effect_class == EFFECTS[form].effect_class}
            assert siblings and siblings <= set(rec["ranked_candidates"])
            if rec["nominal_gap"] >= 0.5:
                assert isinstance(rec["oracle"]["separable"], bool) and rec["oracle"]["shrink_percent"] > 0
        else:
            assert rec["excluded"] == []


def test_cli_gap_json_and_report(tmp_path, scenario):
    from hil.effects import with_reality
    real = run(with_reality(scenario, {"adhesion_lag": {"tau_s": 0.008}}), "nlls", 12, bus="inprocess",
               out_dir=tmp_path / "r", progress=False, log=print)
    rep = tmp_path / "report"
    r = hil("gap", real["mcap"], "--model", FFCC_A, "--json", "--report", rep, timeout=600)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["which"]["named"] == "adhesion_lag" and out["which"]["named_set"] == ["adhesion_lag"]
    assert out["shrink"]["held_out_gap_shrink_percent"] >= 80
    top = out["which"]["ranking"][0]
    assert top["effect"] == "adhesion_lag" and top["form"] == "mu_lag" and 0.8 <= top["share"] <= 1
    assert top["at_bound"] == {"tau_s": False}
    lo, hi = top["param_ci"]["tau_s"]
    assert lo <= top["params"]["tau_s"] <= hi
    assert out["which"]["nuisances"][0]["name"] == "rail_curve"
    assert {u["effect"] for u in out["which"]["unobservable"]} == {"torque_lag", "compliance.backlash_rad"}
    for s in ("motor", "train", "mu_hat"):
        assert s in out["where"]["per_signal"] and s in out["shrink"]["per_signal"]
    assert set(out["where"]["per_stage"]) == {"normal", "early", "serious"}
    ident = out["identification"]
    assert {"real", "nominal_replay", "augmented_replay"} <= set(ident)
    # the augmented replay reproduces the real run's identified peak better than the nominal one
    assert abs(ident["curve_shift"]["real_vs_augmented_peak_mu_percent"]) <= \
        abs(ident["curve_shift"]["real_vs_nominal_peak_mu_percent"]) + 0.5
    md = (rep / "report.md").read_text()
    assert "adhesion_lag" in md
    for png in ("signals.png", "residuals.png", "where.png", "which.png", "curves.png"):
        assert (rep / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads((rep / "gap.json").read_text())["which"]["named"] == "adhesion_lag"
    assert "hil gap:" in r.stderr   # progress on stderr


def test_cli_gap_bad_inputs(tmp_path):
    bad = tmp_path / "x.mcap"
    bad.write_text("not mcap")
    asc = tmp_path / "rig.asc"
    asc.write_text("date Mon Jan 1\n")
    junk = tmp_path / "rig.blf"
    junk.write_bytes(os.urandom(4096))
    for args, word in (([str(tmp_path / "missing.mcap")], "cannot read"), ([str(bad)], "not an MCAP file"),
                       ([str(asc)], "no valid PlantSensor frames"), ([str(junk)], "not a CAN log"),
                       ([str(tmp_path / "missing.log")], "cannot read")):
        r = hil("gap", *args, "--model", FFCC_A, timeout=120)
        assert r.returncode == 2 and word in r.stderr and r.stderr.strip().count("\n") == 0, r.stderr


def test_torque_lag_found_when_the_command_varies(tmp_path, scenario):
    """The TCU commands a constant torque, so hil run cannot show a torque lag; a log whose command
    carries a PRBS dither (written here from the real reality plant and the TCU's observer) can."""
    import numpy as np

    from hil.gap.model import ObserverReplica
    from hil.log.record import Recorder
    from plant import SensorModel
    from plant.reality import RealityPlant

    seed = fresh_seed()
    g = np.random.default_rng(seed)
    tau = float(np.exp(g.uniform(np.log(0.003), np.log(0.03))))
    plant = RealityPlant(scenario.plant_config(), {"torque_lag": {"tau_s": tau}})
    sens = SensorModel(scenario.sensors, int(g.integers(1 << 30)))
    n, t0 = scenario.steps, plant.equilibrium_torque_nm
    cmd = np.empty(n)
    k, level = 0, 1.0
    while k < n:
        span = int(g.integers(10, 40))
        cmd[k:k + span] = t0 * (1 + 0.03 * level)
        level, k = -level, k + span
    path = tmp_path / "dither.mcap"
    rec = Recorder(path)
    rec.metadata("run", {"strategy": "nlls", "exchange_period_s": repr(scenario.run.exchange_period_s)})
    motor, train = [], []
    for k in range(n):
        s = plant.state
        w, v = sens.measure(s.motor_speed_rad_s, s.train_speed_ms)
        motor.append(w)
        train.append(v)
        rec.write("/plant/sensor", s.t_s, step=k, t_s=s.t_s, motor_speed_rad_s=w, train_speed_ms=v)
        rec.write("/tcu/command", s.t_s, step=k, t_s=s.t_s, torque_nm=float(cmd[k]))
        plant.step(float(cmd[k]))
    obs = ObserverReplica(scenario.identifier_settings())
    mu = obs.mu_hat(np.array(motor), cmd)
    creep = obs.creep_kmh(np.array(motor), np.array(train))
    for k in range(n):
        t = k * scenario.run.exchange_period_s
        rec.write("/tcu/observer", t, step=k, t_s=t, creep_speed_kmh=float(creep[k]), mu_hat=float(mu[k]),
                  load_torque_nm=0.0)
    rec.close({"sim_s": n * scenario.run.exchange_period_s})
    out, _ = diagnose(read_real_log(path), scenario, identify=False)
    print(f"tau {tau:.4f} s ->", out["which"]["verdict"])
    assert out["which"]["named"] == "torque_lag"
    assert out["which"]["ranking"][0]["params"]["tau_s"] == pytest.approx(tau, rel=0.2)
    assert out["where"]["input_constant"] is False
    assert out["which"]["unobservable"] == []
    # the lag shows in the observer's mu^ (it reads the lagged torque as load): its residual follows the
    # command, ~6x the 95 % bound on every seed tried (0.42-0.58 against 0.072).  The motor speed's
    # correlation depends on the dither's pattern (0.04-0.60 over those seeds), so it is not asserted.
    mu_test = out["where"]["tests"]["mu_hat"]
    assert mu_test["xcorr_input"] > 3 * mu_test["xcorr_bound_95"]


# -- rig CAN logs ---------------------------------------------------------------------------------------
def _frames_of(mcap_path) -> list:
    """The frames that crossed the bus in a hil run, as python-can messages (what a rig logger sees)."""
    from hil.replay import _msg_from_record
    return [_msg_from_record(m) for t, _, m in read_log(mcap_path).messages if t == "/can/frames"]


def _write_can_log(path, msgs) -> None:
    import can
    writer = {".log": can.CanutilsLogWriter, ".asc": can.ASCWriter, ".blf": can.BLFWriter}[path.suffix]
    w = writer(str(path))
    for m in msgs:
        w.on_message_received(m)
    w.stop()


@pytest.fixture(scope="module")
def rig_run(tmp_path_factory, scenario):
    """A load-transfer run whose truth sits in the scenario file itself (so its text, recorded in the
    log's metadata, holds it), diagnosed from its MCAP log: made once per test session, its frames read
    back as a rig logger sees them."""
    def make(out):
        seed = fresh_seed()
        g = np.random.default_rng(seed)
        z = float(g.uniform(1.0, 2.5))
        path = out / "real.toml"
        path.write_text(FFCC_A.read_text() + f"\n[reality.load_transfer]\nbogie_height_m = {z!r}\n")
        s = run(load_scenario(path), "nlls", int(g.integers(1, 1 << 30)), bus="inprocess", out_dir=out,
                progress=False, log=print)
        mcap_out, _ = diagnose(read_real_log(s["mcap"]), scenario, identify=False)
        print(f"z {z!r} m: MCAP ->", mcap_out["which"]["verdict"])
        return {"mcap": str(s["mcap"]), "out": mcap_out, "seed": seed, "z": z}

    made = once_per_session(tmp_path_factory, "rig", make)
    return dict(made, mcap=Path(made["mcap"]), frames=_frames_of(made["mcap"]), dir=tmp_path_factory.mktemp("rig"))


def test_reader_drops_the_truth_even_from_the_scenario_text(rig_run):
    # the truth sits in the scenario file itself: its text is recorded in the log's metadata
    z = rig_run["z"]
    raw = read_log(rig_run["mcap"])
    assert TRUTH_KEY in raw.metadata and repr(z) in json.dumps(raw.metadata)   # it is in the file ...
    data = read_real_log(rig_run["mcap"])
    seen = describe(data)
    for word in (repr(z), "load_transfer", "bogie_height", TRUTH_KEY):
        assert word not in seen, word                                   # ... not in what gap sees
    assert set(data.metadata) <= {"run"}
    # and the diagnosis still finds it, from the measurements alone
    out = rig_run["out"]
    assert out["which"]["named"] == "load_transfer"
    assert out["which"]["ranking"][0]["params"]["bogie_height_m"] == pytest.approx(z, rel=0.05)


_READINGS = ("step", "t_s", "motor_speed_rad_s", "train_speed_ms", "torque_cmd_nm", "tcu_creep_kmh", "tcu_mu_hat")


def _same_readings(a, b) -> None:
    """Two reads of one run's frames hold the same readings, commands, TCU outputs and events."""
    for name in _READINGS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.identification == b.identification


def test_can_log_diagnoses_like_its_mcap_twin(rig_run, scenario):
    """The run's frames as an ASC and a BLF log read the same, and the BLF diagnoses as its MCAP twin
    did (one diagnosis: the other format's readings are equal, so would be its diagnosis)."""
    data = {}
    for suffix in (".asc", ".blf"):
        path = rig_run["dir"] / f"rig{suffix}"
        _write_can_log(path, rig_run["frames"])
        data[suffix] = read_real_log(path, scenario.run.exchange_period_s)
        assert data[suffix].source["format"] == "can-log" and data[suffix].source["damage"] == ""
        assert not np.isnan(data[suffix].tcu_mu_hat).any() and len(data[suffix].identification) >= 1
    _same_readings(data[".asc"], data[".blf"])
    twin_data = read_real_log(rig_run["mcap"])
    assert data[".blf"].n == twin_data.n
    np.testing.assert_allclose(data[".blf"].motor_speed_rad_s, twin_data.motor_speed_rad_s, rtol=1e-6)
    out, _ = diagnose(data[".blf"], scenario, identify=False)
    twin = rig_run["out"]
    assert out["which"]["named"] == twin["which"]["named"] == "load_transfer"
    assert out["which"]["named_set"] == twin["which"]["named_set"]
    assert out["shrink"]["held_out_gap_shrink_percent"] == pytest.approx(twin["shrink"]["held_out_gap_shrink_percent"],
                                                                         abs=3)


def test_can_log_with_garbage_frames_skips_and_counts_them(rig_run, scenario):
    """candump log of the same run with garbage on the bus: every bad frame is skipped and counted by
    reason, and what is read is exactly the clean log's readings (hence its diagnosis); through the
    CLI, a log of garbage only is one line."""
    import can
    g = np.random.default_rng(rig_run["seed"] + 1)
    msgs = list(rig_run["frames"])
    bad = []
    for i in range(60):
        kind = i % 5
        fid = int(g.choice([0x100, 0x110, 0x120, 0x130]))
        if kind == 0:     # wrong length
            bad.append(can.Message(arbitration_id=fid, data=bytes(g.integers(0, 256, 5).tolist()), is_fd=True,
                                   is_extended_id=False))
        elif kind == 1:   # right length, random bytes (NaN, out of range, or a wild step)
            n = {0x100: 24, 0x110: 12, 0x120: 32, 0x130: 64}[fid]
            bad.append(can.Message(arbitration_id=fid, data=bytes(g.integers(0, 256, n).tolist()), is_fd=True,
                                   is_extended_id=False))
        elif kind == 2:   # extended id
            bad.append(can.Message(arbitration_id=0x100, is_extended_id=True, data=bytes(8)))
        elif kind == 3:   # an id of another ECU
            bad.append(can.Message(arbitration_id=int(g.integers(0x200, 0x700)), data=bytes(8), is_extended_id=False))
        else:             # error frame
            bad.append(can.Message(is_error_frame=True, data=bytes(0)))
    for m in bad:
        msgs.insert(int(g.integers(0, len(msgs))), m)
    path = rig_run["dir"] / "garbage.log"
    _write_can_log(path, msgs)
    data = read_real_log(path, scenario.run.exchange_period_s)
    print(data.source)
    others = sum(m.arbitration_id not in (0x100, 0x110, 0x120, 0x130) for m in rig_run["frames"])
    assert data.source["skipped_total"] == 60 + others and data.n == 1000
    assert any(k.endswith("bad_length") for k in data.source["skipped"]), data.source
    clean = rig_run["dir"] / "clean.log"
    _write_can_log(clean, rig_run["frames"])
    _same_readings(data, read_real_log(clean, scenario.run.exchange_period_s))   # so the same diagnosis
    only = rig_run["dir"] / "only_garbage.log"
    _write_can_log(only, bad)
    r = hil("gap", only, "--model", FFCC_A, "--no-identify", timeout=120)
    # (a random frame may decode as a valid reading: then it is "N valid PlantSensor frames ... at least 50")
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0, r.stderr
    assert "no valid PlantSensor frames" in r.stderr or "needs at least 50" in r.stderr, r.stderr


def test_can_log_with_many_steps_out_of_sequence_names_the_frame(rig_run, scenario):
    from hil.bus.frames import FrameCodec
    from identifier.messages import SensorReading
    codec = FrameCodec(scenario.run.exchange_period_s)
    msgs = [m for m in rig_run["frames"] if not (m.arbitration_id == 0x100 and m.data[0] % 3 == 0)]
    msgs += [codec.sensor(SensorReading(10 ** 6 + i, 60.0, 10.0)) for i in range(30)]
    path = rig_run["dir"] / "holes.log"
    _write_can_log(path, msgs)
    with pytest.raises(Exception) as e:
        read_real_log(path, scenario.run.exchange_period_s)
    assert type(e.value).__name__ == "LogError" and "PlantSensor frame #" in str(e.value), e.value
    # a candump line that is not a frame part-way: what came before is kept and the damage said
    cut = rig_run["dir"] / "cut.log"
    _write_can_log(cut, rig_run["frames"])
    lines = cut.read_text().splitlines()
    cut.write_text("\n".join(lines[:2500] + ["(1.0) can0 this-is-not-a-frame"] + lines[2500:]) + "\n")
    try:
        data = read_real_log(cut, scenario.run.exchange_period_s)
        print(data.source)
    except Exception as e2:   # the reader stopped before 50 readings: a one-line project error
        assert type(e2).__name__ == "LogError", e2


def test_polach_fault_curve_diagnosed_and_reported(tmp_path):
    """A scenario whose fault curve follows Polach's law (no exponential params): the identification
    section and the report's curve plot work from the curve's peak() and mu()."""
    from plant import families
    text = families.draw_scenario_text(FFCC_A.read_text(), "polach", fresh_seed() % 100000, 0)
    path = tmp_path / "polach.toml"
    path.write_text(text)
    sc = load_scenario(path)
    assert not hasattr(sc.fault_curve, "params")
    s = run(sc, "nlls", 3, bus="inprocess", out_dir=tmp_path, progress=False, log=print)
    rep = tmp_path / "report"
    r = hil("gap", s["mcap"], "--model", path, "--json", "--report", rep, timeout=600)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["which"]["gap_present"] is False
    assert out["identification"]["real"]["peak_mu_err_percent"] is not None or \
        not out["identification"]["real"]["identified"]
    assert (rep / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_two_effects_at_once_found_by_forward_selection(tmp_path, scenario):
    """An adhesion lag and a sensor delay together (neither removes 80 % alone): forward selection
    names both, or names the lag and says that the rail's curve and the delay cannot be told apart in
    this log (the rail curve with the lag explains it within the margin of the pair: CI seed 3815588383,
    tau 8.3 ms, delay 3.71 ms, the pair left 13 % of the gap and the rail with the lag 26 %, MARGIN_GAP_RATIO
    0.5); the where headline starts from the earliest significant stage, not the serious one."""
    from hil.effects import with_reality
    g = np.random.default_rng(fresh_seed())
    tau, delay = float(g.uniform(0.008, 0.015)), float(g.uniform(3.0, 5.0))
    real = with_reality(scenario, {"adhesion_lag": {"tau_s": tau}, "sensor_delay": {"delay_ms": delay}})
    s = run(real, "nlls", int(g.integers(1, 1 << 30)), bus="inprocess", out_dir=tmp_path, progress=False, log=print)
    out, _ = diagnose(read_real_log(s["mcap"]), scenario, identify=False)
    which = out["which"]
    print(f"tau {tau:.4f} s, delay {delay:.2f} ms ->", which["verdict"], "|", out["where"]["summary"])
    assert set(which["named_set"]) <= {"adhesion_lag", "sensor_delay"}        # never a false name
    fw = which["forward"]
    if fw.get("pair_vs_rail") == "not_separable":       # the honest "I don't know" between rail and delay
        assert which["named_set"] == ["adhesion_lag"], fw
        assert fw["first"] == "sensor_delay" and fw["second"] == "adhesion_lag", fw
        assert "rail or sensor_delay: not separable" in which["verdict"]
    else:
        assert which["named_set"] == ["adhesion_lag", "sensor_delay"], fw
    assert out["where"]["earliest"]["stage"] in ("normal", "early")
    assert out["where"]["summary"].startswith("first significant in the")


def _bench_case(tmp_path, scenario, seed: int, i: int, mix: str, identify: bool = False, drawn=None):
    """Case ``i`` of ``hil bench gap --seed SEED --mix MIX``, recorded and diagnosed as the bench does
    (the truth's own forms held out of the candidates; ``identify``: with the model replays too).
    ``drawn``: (effects, run seed) the bench drew for that case when it was found, where its draw tables
    have grown since (issue 51's family members and library form move some cases' draws)."""
    from hil.benchmarks.gap import held_out
    from hil.effects import with_reality
    effects, run_seed = drawn if drawn is not None else draw_case(seed, i, parse_mix(mix))[1:]
    s = run(with_reality(scenario, effects), "nlls", run_seed, bus="inprocess", out_dir=tmp_path, progress=False,
            log=print)
    out, result = diagnose(read_real_log(s["mcap"]), scenario, identify=identify,
                           exclude=sorted(n for n in effects if n in held_out()))
    print(f"bench seed {seed}, case {i}: {effects} ->", out["which"]["named_set"], out["which"]["confidence"])
    return effects, out, result


def test_the_veto_in_time_keeps_a_true_delay_under_a_load_transfer(tmp_path, scenario):
    """Issue 35: a load transfer under a CAN delay (case 23 of the 300-case two-effect bench, seed
    1782120538).  Fitted without the serious stage, the load transfer forecasts it with an error of its
    own that the delay cannot remove, so the true pair leaves more than half of the first's gap there:
    the veto's old test (half the gap) rejected it and the answer was "not_separable: load_transfer or
    the rail curve", the delay unlisted.  Judged by the score with the noise level estimated from the
    residuals, the pair wins and both are named."""
    from hil.gap.select import MARGIN_GAP_RATIO, MIN_MARGIN
    effects, out, _ = _bench_case(tmp_path, scenario, 1782120538, 23, "two_effect=1")
    assert set(effects) == {"load_transfer", "can"}
    which = out["which"]
    veto = which["forward"]["held_out_in_time"]
    pair, first = veto["rows"][0], veto["rows"][1]
    print(veto["held_out"], veto["periods"], [(r["explanation"], round(r["held_out_gap"], 2),
                                              round(r.get("pair_profile_gain", 0))) for r in veto["rows"]])
    assert first["explanation"] == "load_transfer"
    assert pair["held_out_gap"] > MARGIN_GAP_RATIO * first["held_out_gap"]      # the halving refused it
    assert first["pair_profile_gain"] >= MIN_MARGIN and veto["pair_wins"], veto
    assert which["confidence"] == "confident" and which["named_set"] == ["can", "load_transfer"], which["verdict"]


def test_a_first_effect_only_most_likely_alone_is_named_when_the_pair_settles_it(tmp_path, scenario):
    """Issue 35: a resistance under a sensor delay (case 62 of the 300-case two-effect bench, seed
    1782120538, the delay's own form held out).  Alone the delay removes most of the gap but does not beat
    compliance by the margin ("most likely sensor_delay"); the resistance on top is accepted.  Before,
    only the resistance was named.  Now compliance's best with the same resistance on top is fitted too,
    the pair beats it by the margin, and both are named."""
    effects, out, _ = _bench_case(tmp_path, scenario, 1782120538, 62, "two_effect=1")
    assert set(effects) == {"resistance", "sensor_delay"}
    which, fw = out["which"], out["which"]["forward"]
    print(fw["first"], fw["second"], fw.get("runner_pair"), fw.get("pair_vs_runner"), which["verdict"][:300])
    assert fw["accepted"] and fw["first"] == "sensor_delay" and fw["second"] == "resistance"
    assert EFFECTS[fw["runner_pair"]["first"]].effect_class == "compliance", fw["runner_pair"]
    assert fw["pair_vs_runner"] == "pair"
    assert which["confidence"] == "confident" and which["named_set"] == ["resistance", "sensor_delay"]


def test_a_pair_is_fitted_in_a_form_within_its_range(tmp_path, scenario):
    """Issue 35: a static load transfer under a sensor low-pass (case 5 of the 300-case two-effect bench,
    seed 1667270391, the low-pass's own form held out).  Fitted together with the delay, the pitching form
    of the load transfer scored best with its pitch frequency run to a bound of its range, and the pair
    was rejected as implausible ("not_separable: load_transfer or the rail curve").  A pair within its
    range is now preferred to a better score off it: both are named."""
    effects, out, _ = _bench_case(tmp_path, scenario, 1667270391, 5, "two_effect=1")
    assert set(effects) == {"load_transfer", "sensor_lowpass"}
    which, fw = out["which"], out["which"]["forward"]
    print(fw["first_candidate"], fw["second_candidate"], fw["first_params"], fw["rejected_because"])
    assert fw["accepted"] and not fw["rejected_because"]
    assert which["confidence"] == "confident" and which["named_set"] == ["load_transfer", "sensor_delay"]


def test_a_small_delay_under_a_first_that_leaves_little_is_named(tmp_path, scenario):
    """Issue 35: a static load transfer under a sensor low-pass (case 70 of a 120-case two-effect probe,
    seed 1736299325, the low-pass's own form held out).  The load transfer alone removes over 99 % of the
    held-out gap and leaves 1.29 noise units: forward selection was not tried below 2.5 after a first
    removing 90 % (a gate kept for a held-out form's misfit) and only the load transfer was named.  The
    gate is now at twice the noise (``FORWARD_MIN_LEFT``), and the delay is named with it."""
    from hil.gap.select import FORWARD_MIN_LEFT
    effects, out, _ = _bench_case(tmp_path, scenario, 1736299325, 70, "two_effect=1")
    assert set(effects) == {"load_transfer", "sensor_lowpass"}
    which, best = out["which"], out["which"]["ranking"][0]
    print(best["effect"], round(best["held_out_shrink"], 4), round(best["held_out_gap"], 2), which["verdict"][:300])
    assert best["effect"] == "load_transfer" and best["held_out_shrink"] > 0.9
    assert FORWARD_MIN_LEFT <= best["held_out_gap"] < 2.5
    assert which["forward"]["accepted"], which["forward"]["rejected_because"]
    assert which["confidence"] == "confident" and which["named_set"] == ["load_transfer", "sensor_delay"]


def test_a_second_effect_is_not_fitted_into_a_held_out_forms_misfit(tmp_path, scenario):
    """Issue 35: a load transfer through a pitch mode, its form held out (case 60 of a 120-case probe of
    single held-out forms, out-of-library and rail cases, seed 194847016).  The static form removes over
    99 % of the gap and its misfit leaves 1.05 noise units; forward selection, now tried there, fits a
    second effect into that remainder and turns it away by its own tests: nothing but the load transfer
    is named."""
    from hil.gap.select import FORWARD_MIN_LEFT
    effects, out, _ = _bench_case(tmp_path, scenario, 194847016, 60,
                                  "held_out_form=1,out_of_library=0.6,outside=0.3,rail=0.3,library_form=0.3")
    assert set(effects) == {"load_transfer_pitch"}
    which, best = out["which"], out["which"]["ranking"][0]
    fw = which["forward"]
    print(best["effect"], round(best["held_out_shrink"], 4), round(best["held_out_gap"], 2), fw["second"],
          fw["rejected_because"])
    assert best["effect"] == "load_transfer" and best["held_out_shrink"] > 0.9
    assert best["held_out_gap"] >= FORWARD_MIN_LEFT
    assert fw is not None and not fw["accepted"] and fw["rejected_because"]
    assert which["named_set"] == ["load_transfer"], which["verdict"]


def test_no_second_effect_within_twice_the_noise_after_a_first_that_removes_most(tmp_path, scenario):
    """Issue 35: a creep relaxation, its form held out (case 84 of the 240-case bench, seed 829663343).
    The adhesion lag removes 98 % of the gap and leaves 0.53 noise units, its misfit of the form; with
    forward selection tried there, a resistance of factor 1.06 took 59 % of that and the pair passed
    every test: "adhesion_lag and resistance", confident and wrong (twice in that bench).  Below
    ``FORWARD_MIN_LEFT`` (twice the noise) after a first removing ``FORWARD_MAX_SHARE`` no second
    effect is tried: the adhesion lag alone is named."""
    from hil.gap.select import FORWARD_MAX_SHARE, FORWARD_MIN_LEFT
    effects, out, _ = _bench_case(tmp_path, scenario, 829663343, 84, ",".join(
        f"{k}={v}" for k, v in DEFAULT_MIX.items()))
    assert set(effects) == {"creep_relaxation"}
    which, best = out["which"], out["which"]["ranking"][0]
    print(best["effect"], round(best["held_out_shrink"], 4), round(best["held_out_gap"], 3), which["verdict"][:300])
    assert best["effect"] == "adhesion_lag" and best["held_out_shrink"] >= FORWARD_MAX_SHARE
    # below twice the noise (with issue 51's second-order form of the class, whose best may now leave less than
    # the noise: 0.21 noise units under HIL_TEST_SEED=606248406, 0.53 with the first-order form alone)
    assert best["held_out_gap"] < FORWARD_MIN_LEFT
    assert which["forward"] is None
    assert which["confidence"] == "confident" and which["named_set"] == ["adhesion_lag"], which["verdict"]


def test_a_pair_turned_away_only_against_the_rail_is_listed_not_named(tmp_path, scenario):
    """Issue 35 item 2: a constant-power limit (outside the library; case 100 of a 120-case probe, seed
    194847016).  The rail curve and the drivetrain losses come within the margin of each other
    ("not_separable"), and forward selection's pair (an adhesion lag on the drivetrain losses) passes its
    own tests but does not beat the rail curve alone by the margin: it is one more explanation within
    the margin, so the answer lists it with what turned it away, and names nothing."""
    from hil.benchmarks.gap import grade_right
    effects, out, _ = _bench_case(tmp_path, scenario, 194847016, 100,
                                  "held_out_form=1,out_of_library=0.6,outside=0.3,rail=0.3,library_form=0.3",
                                  drawn=({"power_limit": {"power_ratio": 1.0449360371043848}}, 1832957439))
    assert set(effects) == {"power_limit"}
    which, fw = out["which"], out["which"]["forward"]
    listed = which["not_separable"]
    print([(a["explanation"], round(a["held_out_gap"], 2)) for a in listed], fw["rejected_because"])
    assert which["confidence"] == "not_separable" and which["named_set"] == []
    assert not fw["accepted"] and fw["own_tests_passed"] and fw["rejected_because"] == [
        "neither the pair nor the rail curve with the same second effect beats the rail curve alone by the margin"]
    singles, pairs = [a for a in listed if len(a["effects"]) == 1], [a for a in listed if len(a["effects"]) == 2]
    assert {"rail_curve", "compliance"} <= {a["effect"] for a in singles}
    assert len(pairs) == 1 and pairs[0]["effects"] == sorted({fw["first"], fw["second"]})
    assert pairs[0]["turned_away_because"] == fw["rejected_because"]
    assert pairs[0]["explanation"] in which["verdict"] and "within the margin of them too" in which["verdict"]
    # graded as the bench grades it: an outside truth, any list is right; a truth of both classes would be listed
    assert grade_right({"truth_classes": [], "effects": effects, "oracle": None}, which)
    assert grade_right({"truth_classes": pairs[0]["effects"], "effects": {}, "oracle": None}, which)


def test_a_pair_whose_first_is_not_the_best_alone_is_found_from_another_first(tmp_path, scenario):
    """Issue 35: a lighter running resistance under a held-out speed-sensor low-pass (case 109 of the
    300-case two-effect bench, seed 179275234).  Alone, the drivetrain losses explain as much as the
    sensor delay that stands for the low-pass, and the pair built on them finds no second effect; the
    pair built on the delay, the other class the best single does not beat by the margin
    (``other_firsts``), finds the resistance and is named with its factor."""
    effects, out, _ = _bench_case(tmp_path, scenario, 179275234, 109, "two_effect=1", identify=True)
    assert set(effects) == {"resistance", "sensor_lowpass"}
    which = out["which"]
    tried = which["forward_firsts"]
    print(which["verdict"], [(f["first"], f["second"], f["accepted"]) for f in tried])
    assert which["ranking"][0]["effect"] != "sensor_delay"          # the delay was not the best alone
    assert not tried[0]["accepted"] and tried[0]["first"] == which["ranking"][0]["effect"]
    assert which["confidence"] == "confident" and which["named_set"] == ["resistance", "sensor_delay"]
    fw = which["forward"]
    assert fw["first"] == "sensor_delay" and fw["second"] == "resistance" and fw["held_out_in_time"]["pair_wins"]
    factor = fw["second_params"]["factor"]
    assert abs(factor - effects["resistance"]["factor"]) < 0.1 * effects["resistance"]["factor"], factor
    # HOW FAR is the named pair's, not the best single's, which removes less
    best = which["ranking"][0]
    sh = out["shrink"]
    print(sh["effect"], sh["held_out_gap_shrink_percent"], best["effect"], best["held_out_shrink"] * 100)
    assert sh["effect"] == "sensor_delay + resistance"
    assert sh["held_out_gap_shrink_percent"] > best["held_out_shrink"] * 100 + 5
    # and the model replay is of an effect named (the delay, named first), not of the best single
    source = out["identification"]["augmented_replay"]["source"]
    delay = next(r for r in which["ranking"] if r["effect"] == "sensor_delay")
    assert source == f"nominal + {delay['candidate']} replay" and best["candidate"] not in source, source


def test_the_veto_in_time_rejects_a_pair_that_removes_next_to_none_of_a_large_gap(tmp_path, scenario):
    """Issue 35: on a constant-power limit (outside the library; power_ratio 1.0441, run seed 1228207239,
    a case the veto was measured on) forward selection's best pair (an adhesion lag on the drivetrain
    losses) is sent to the veto in time directly, past the rules that stopped it first.  On the serious
    stage every model leaves hundreds of noise units, so the pair's tiny improvement on the first
    alone is worth millions in the score with the noise floor; with the noise level estimated from the
    residuals it is worth less than the margin, and the pair does not win."""
    from hil.effects import with_reality
    from hil.gap.select import MIN_MARGIN, time_veto
    real = with_reality(scenario, {"power_limit": {"power_ratio": 1.044128548774745}})
    s = run(real, "nlls", 1228207239, bus="inprocess", out_dir=tmp_path, progress=False, log=print)
    out, result = diagnose(read_real_log(s["mcap"]), scenario, identify=False)
    fw = out["which"]["forward"]
    assert not fw["accepted"] and out["which"]["named_set"] == [], out["which"]["verdict"]
    veto = time_veto(result.ctx, fw["first_candidate"], (fw["first_candidate"], fw["second_candidate"]), True, [])
    pair, first = veto["rows"][0], veto["rows"][1]
    print(fw["first_candidate"], fw["second_candidate"], veto["held_out"],
          [(r["explanation"], round(r["held_out_gap"], 2), round(r.get("pair_profile_gain", 0), 1))
           for r in veto["rows"]])
    assert first["held_out_gap"] > 100 and pair["score_gain"] - first["score_gain"] > 1000 * MIN_MARGIN
    assert first["pair_profile_gain"] < MIN_MARGIN
    assert not veto["pair_wins"] and fw["first_candidate"] in veto["why"], veto["why"]


def test_a_quantiser_is_named_beside_the_effect_that_explains_the_mean(tmp_path, scenario):
    """A load transfer and a quantised motor encoder: the quantiser changes the noise, not the mean, so it
    is named beside the load transfer (judged on the lattice the readings sit on), with its quantum."""
    from hil.effects import with_reality
    g = np.random.default_rng(fresh_seed())
    z, q = float(g.uniform(1.2, 2.5)), float(g.uniform(0.05, 0.15))
    real = with_reality(scenario, {"load_transfer": {"bogie_height_m": z},
                                   "sensor_quantisation": {"motor_quantum_rad_s": q}})
    s = run(real, "nlls", int(g.integers(1, 1 << 30)), bus="inprocess", out_dir=tmp_path, progress=False, log=print)
    out, _ = diagnose(read_real_log(s["mcap"]), scenario, identify=False)
    which = out["which"]
    print(f"z {z:.3f} m, quantum {q:.4f} rad/s ->", which["verdict"])
    assert which["named_set"] == ["load_transfer", "sensor_quantisation"], which["verdict"]
    assert which["named"] == "load_transfer"
    assert which["quantiser"]["params"]["motor_quantum_rad_s"] == pytest.approx(q, rel=0.02)
    assert "sensor_quantisation" not in {r["effect"] for r in which["ranking"]}    # judged apart, not ranked


def test_a_fits_short_simulation_is_the_whole_runs_first_periods(scenario):
    """A fit simulates only the periods its residuals read (``Context.n_read``): the model rolled over
    those periods gives exactly the whole run's first values, with an effect's extra states too; a mask
    reads up to its last period."""
    from hil.gap.candidates import periods_read
    from hil.gap.model import Simulator
    from plant.reality import fill_defaults
    g = np.random.default_rng(fresh_seed())
    cfg = scenario.plant_config()
    n = 400
    torque = 2000.0 + 200.0 * g.standard_normal(n)
    x0 = np.array([260.0, 13.0]) * (1 + 0.01 * g.standard_normal(2))
    for effect, names, theta in ((None, (), []), ("compliance", ("stiffness_nm_rad", "damping_ratio"),
                                                  [float(g.uniform(1e5, 1e6)), float(g.uniform(0.05, 0.5))])):
        fixed = fill_defaults({effect: dict(EFFECTS[effect].params)}, cfg)[effect] if effect else {}
        sim = Simulator(cfg, effect, names, fixed, n)
        whole = sim.run(theta, x0, torque)
        k = int(g.integers(50, n))
        for a, b in zip(sim.run(theta, x0, torque, n=k), whole):
            assert len(a) == k and np.array_equal(a, b[:k]), (effect, k)
    mask = np.zeros(n, bool)
    mask[[3, 17, 250]] = True
    assert periods_read(mask, n) == 251 and periods_read(np.zeros(n, bool), n) == n


def test_each_candidates_compiled_step_computes_the_virtual_machines_bits(scenario):
    """``hil.gap.compiled``: every plant candidate's period step (its parameters drawn inside their
    bounds), the nominal one, and one on top of another effect, rolled over a run with a varying torque,
    gives exactly (bit for bit) what CasADi's virtual machine gives; and each was compiled (a C compiler
    is on every machine the tests run on)."""
    import shutil
    from hil.gap.candidates import PlantCandidate, candidates
    from hil.gap.model import Simulator
    from plant.reality import fill_defaults
    assert shutil.which("cc") or shutil.which("gcc")
    seed = fresh_seed()
    g = np.random.default_rng(seed)
    print(f"seed {seed}")
    cfg = scenario.plant_config()
    n = 300
    torque = 2000.0 + 300.0 * g.standard_normal(n)
    x0 = np.array([260.0, 13.0]) * (1 + 0.01 * g.standard_normal(2))
    cases = [(None, (), [], None)]
    for c in candidates(scenario):
        if isinstance(c, PlantCandidate):
            cases.append((c.name, c.fit_params, [float(g.uniform(a, b)) for a, b in zip(c.lo, c.hi)], None))
    cases.append(("adhesion_lag", ("tau_s",), [0.01], {"load_transfer": {"bogie_height_m": 1.2}}))
    assert len(cases) >= 11
    for effect, names, theta, base in cases:
        base = fill_defaults(base, cfg) if base else None
        fixed = fill_defaults({effect: dict(EFFECTS[effect].params)}, cfg)[effect] if effect else {}
        sim = Simulator(cfg, effect, names, fixed, n, base)
        assert sim._step is not sim.step_vm and sim._step.name() == "gap_step", effect
        th = np.array(theta) if names else np.zeros(1)
        xi = sim.initial(th, x0, float(torque[0]))
        args = (xi, torque[None, :n - 1], np.arange(n - 1)[None, :] * 1e-3, th)
        c_out = [np.asarray(o) for o in sim._step.mapaccum("c", n - 1)(*args)]
        vm_out = [np.asarray(o) for o in sim.step_vm.mapaccum("vm", n - 1)(*args)]
        assert len(c_out) == len(vm_out) >= 1, effect
        for c, vm in zip(c_out, vm_out):
            assert np.isfinite(vm).all() and np.array_equal(c, vm), (effect, theta, np.max(np.abs(c - vm)))

def test_without_a_c_compiler_the_step_runs_on_the_virtual_machine(tmp_path):
    """A process whose PATH holds no C compiler (and no ``$CC``) builds its simulators on CasADi's virtual
    machine, with no error: the slower path, the same numbers."""
    import subprocess
    import sys
    from hil.testing import subprocess_env
    code = ("from hil.config import load_scenario; from hil.gap.model import Simulator; "
            f"cfg = load_scenario({str(FFCC_A)!r}).plant_config(); s = Simulator(cfg, None, (), {{}}, 50); "
            "print(s._step is s.step_vm)")
    env = {**subprocess_env(), "PATH": str(tmp_path)}
    env.pop("CC", None)
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "True", r.stderr[-2000:]

def test_other_firsts_are_the_classes_the_best_does_not_beat_and_accepted_pairs_within_the_margin_are_rivals():
    """Forward selection's other starts and the choice among their pairs, on rows written by hand: the
    margin is 25 in score and half the remaining gap (``beats``)."""
    from hil.gap.select import FORWARD_FIRSTS, Row, choose_pair, other_firsts

    def row(effect, candidate, score, gap, shrink):
        return Row(effect, "", candidate, {}, 1, score, shrink, gap)
    ranking = [row("compliance", "drivetrain_damping", 1000, 2.9, 0.80),
               row("compliance", "gear_efficiency", 999, 2.9, 0.80),      # the best's own class: never a start
               row("sensor_delay", "sensor_delay", 990, 3.0, 0.79),       # within the margin
               row("sensor_delay", "motor_delay", 980, 3.0, 0.79),        # its class's second form
               row("adhesion_lag", "adhesion_lag", 900, 4.2, 0.71),       # gap 2.9 > half of 4.2: not beaten
               row("resistance", "resistance", 500, 6.4, 0.56),           # beaten: 2.9 <= 3.2, 1000 >= 525
               row("torque_lag", "torque_lag", -7, 14.7, 0.0)]
    assert FORWARD_FIRSTS == 2
    assert [r.candidate for r in other_firsts(ranking, ranking[0])] == ["sensor_delay", "adhesion_lag"]
    # a class within the margin but removing less than forward selection starts from is no start
    low = [ranking[0], row("can", "can", 990, 3.0, 0.10)]
    assert other_firsts(low, low[0]) == []

    def fw(score, gap, accepted=True):
        return {"pair_score_gain": score, "pair_held_out_gap": gap, "accepted": accepted}
    a, b, c = fw(2000, 1.0), fw(1990, 1.1), fw(3000, 0.3, accepted=False)
    first_row, won, rivals = choose_pair([(ranking[0], c), (ranking[2], b), (ranking[4], a)])
    assert first_row is ranking[4] and won is a and rivals == [b]        # b within the margin of a
    first_row, won, rivals = choose_pair([(ranking[2], fw(2000, 0.4)), (ranking[4], fw(1500, 1.0))])
    assert first_row is ranking[2] and rivals == []                       # beaten by the margin
    assert choose_pair([(ranking[0], c)]) == (None, None, [])


def test_sparse_description_of_known_residuals():
    """hil/gap/sparse.py on residuals made here: a gain on the motor speed is described by the motor
    speed with its coefficient; a creep-proportional term by the creep; noise is not described; a sine
    at a frequency drawn here is described as periodic at that frequency, with its amplitude."""
    from hil.gap.sparse import describe_residual
    seed = fresh_seed()
    g = np.random.default_rng(seed)
    n, dt = 3000, 1e-3
    t = np.arange(n) * dt
    creep = np.where(t > 1.5, (t - 1.5) * g.uniform(2, 6), 0.0) + 0.05 * g.standard_normal(n)
    motor = 250.0 + 5.0 * np.sin(2 * np.pi * t / 3.0) + creep * 6.0      # varies apart from the constant
    train = 13.0 + 0.1 * t
    torque = 2000.0 + 300.0 * (t > 1.0)
    blocks = (np.arange(n) // 20) % 2
    tr, ho = blocks == 0, blocks == 1
    noise = 0.01 * g.standard_normal(n)
    k = float(g.choice([-1, 1]) * g.uniform(0.002, 0.02))
    d = describe_residual(motor * (1 + k) + noise, motor, train, creep, torque, dt, tr, ho)
    assert d["described"] and d["variables"] == ["motor_speed"], d["sentence"]
    assert d["terms"][0]["coef"] == pytest.approx(k, rel=0.1)
    c = float(g.uniform(0.05, 0.2))
    d = describe_residual(motor + c * creep + noise, motor, train, creep, torque, dt, tr, ho)
    assert d["described"] and d["variables"] == ["creep_speed"], d["sentence"]
    d = describe_residual(motor + noise, motor, train, creep, torque, dt, tr, ho)
    assert not d["described"] and "no sparse description" in d["sentence"], d["sentence"]
    assert d["line_hz"] is None                   # white noise: no spectral line
    f_hz, a = float(g.uniform(20.0, 150.0)), float(g.uniform(0.01, 0.05))
    d = describe_residual(motor + a * np.sin(2 * np.pi * f_hz * t + g.uniform(0, 6)) + noise, motor, train, creep,
                          torque, dt, tr, ho)
    print(f"sine {a:.3f} rad/s at {f_hz:.2f} Hz -> {d['sentence']}")
    assert d["described"] and d["variables"] == ["periodic"], d["sentence"]    # a plain sine: not the torque
    assert d["line_hz"] == pytest.approx(f_hz, rel=0.005)
    assert d["terms"][0]["frequency_hz"] == d["line_hz"]
    assert d["terms"][0]["coef"] == pytest.approx(a, rel=0.25)
    ramp = 1000.0 + 2000.0 * t / t[-1]               # a ripple that scales with a command ramping 1:3
    frac = a / ramp.mean()
    d = describe_residual(motor + frac * ramp * np.sin(2 * np.pi * f_hz * t) + noise, motor, train, creep, ramp, dt,
                          tr, ho)
    print(f"ripple {frac:.3g} x torque at {f_hz:.2f} Hz -> {d['sentence']}")
    assert d["described"] and d["variables"] == ["periodic", "torque"], d["sentence"]
    assert d["terms"][0]["term"] == "torque*periodic"
    assert d["terms"][0]["coef"] == pytest.approx(frac, rel=0.25)      # the term is coef x torque x sin


def test_a_red_spectrum_has_no_line_and_a_line_above_its_floor_is_found():
    """``spectral_line``: a residual that only drifts (an exponential runaway, as a replay that slips
    where the wheel was held leaves) has its largest periodogram bin at the search's 2 Hz edge on a
    falling slope: no line (it was refined to 1.0 Hz, below the floor, and described as a 1 Hz sine).
    A sine drawn here at 20-150 Hz in white noise is found within 2 %."""
    from hil.gap.sparse import LINE_MIN_HZ, spectral_line
    seed = fresh_seed()
    g = np.random.default_rng(seed)
    dt, n = 0.001, 1000
    t = dt * np.arange(n)
    mask = np.ones(n, bool)
    tau_s = g.uniform(0.05, 0.2)
    drift = -g.uniform(5, 60) * np.expm1(np.clip(t - g.uniform(0.5, 0.7), 0, None) / tau_s) \
        / np.expm1(0.3 / tau_s) + 0.01 * g.standard_normal(n)
    print(f"seed {seed}: tau {tau_s:.3f} s")
    assert spectral_line(drift, mask, dt) is None
    f_hz = g.uniform(20, 150)
    line = spectral_line(0.05 * np.sin(2 * np.pi * f_hz * t) + 0.01 * g.standard_normal(n), mask, dt)
    assert line is not None and line >= LINE_MIN_HZ and abs(line / f_hz - 1) <= 0.02, (line, f_hz)


@pytest.mark.parametrize("case, member", [(5, "power_limit"), (3, "torque_map")])
def test_a_drive_torque_that_falls_with_motor_speed_is_described_by_the_motor_speed(tmp_path, scenario, case,
                                                                                     member):
    """Issue 35's out-of-library family (cases of a 44-case probe, seed 5150, mix out_of_library=1,
    outside=0.6): a constant-power cap and a torque map that falls with motor speed.  The nominal
    replay slips where the capped wheel was held, and its residual is its own runaway: the description
    read "-85 x train_speed + 17.9 x sin(2 pi 1.00 Hz t)" in every such case.  Described by the
    acceleration the nominal model lacks at the measured state, the missing term depends on the motor
    speed, with a negative coefficient (less torque as the motor speeds up), and no line is claimed.
    The report plots what the rate view regresses against the description rebuilt from its printed
    terms, which scores on the held-out blocks the R² it claims."""
    from hil.gap.report import write_report
    from hil.gap.sparse import fitted, view_targets
    effects, out, result = _bench_case(tmp_path, scenario, 5150, case, "out_of_library=1,outside=0.6")
    assert list(effects) == [member]
    d = out["which"]["description"]
    print(d["sentence"])
    assert out["which"]["named"] == "none"
    assert d["described"] and d["view"] == "rate" and d["line_hz"] is None
    assert d["variables"] == ["motor_speed"]
    assert next(t["coef"] for t in d["terms"] if t["term"] == "motor_speed") < 0
    data = result.data
    target = view_targets(data.motor_speed_rad_s, result.nominal["motor"], data.period_s, result.ahead_motor)["rate"]
    rebuilt = fitted(d, data.motor_speed_rad_s, data.train_speed_ms, result.creep_meas, data.torque_cmd_nm,
                     data.period_s)
    held = result.ctx.held & np.isfinite(target)
    y = target[held]
    r2 = 1 - np.sum((y - rebuilt[held]) ** 2) / np.sum((y - y.mean()) ** 2)
    assert r2 == pytest.approx(d["held_out_r2"], abs=1e-6)
    md = write_report(out, result, tmp_path / "report").read_text()
    assert "![described](described.png)" in md
    assert (tmp_path / "report" / "described.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_tachometer_gain_is_none_of_the_candidates_but_described_by_the_motor_speed(tmp_path, scenario):
    """Issue 18 item 5: an effect outside every class (the motor encoder reads 0.3-2 % high or low)
    is named by no candidate, and the sparse description says the missing term is the motor speed,
    with about the gain as its coefficient."""
    from hil.effects import with_reality
    g = np.random.default_rng(fresh_seed())
    err = float(g.choice([-1, 1]) * g.uniform(0.3, 2.0))
    real = with_reality(scenario, {"tachometer_gain": {"error_percent": err}})
    s = run(real, "nlls", int(g.integers(1, 1 << 30)), bus="inprocess", out_dir=tmp_path, progress=False, log=print)
    r = hil("gap", s["mcap"], "--model", FFCC_A, "--json", "--no-identify", timeout=600)
    assert r.returncode == 0, r.stderr
    which = json.loads(r.stdout)["which"]
    d = which["description"]
    print(f"tachometer error {err:+.3f} % -> {which['named']}; {d['sentence']}")
    assert which["named"] == "none"
    assert d["described"] and d["variables"] == ["motor_speed"]
    assert d["terms"][0]["coef"] == pytest.approx(err / 100, rel=0.4)


def test_a_held_out_bristle_is_not_named_as_another_class(tmp_path, scenario):
    """A LuGre-type bristle drawn as the bench draws it, its own form held out of the candidates: the
    class's other forms (time-constant lags) cannot express its slip-dependent relaxation, so the right
    answers are its class or "none", never another class; and the truth itself, scored as the bench's
    oracle, explains more of the gap than any remaining form of its class (what is missing is a form,
    not information in the log)."""
    from hil.benchmarks.gap import held_out, oracle
    from hil.effects import with_reality
    g = np.random.default_rng(fresh_seed())
    effects = {"bristle": held_out()["bristle"](g)}
    real = with_reality(scenario, effects)
    s = run(real, "nlls", int(g.integers(1, 1 << 30)), bus="inprocess", out_dir=tmp_path, progress=False, log=print)
    out, dg = diagnose(read_real_log(s["mcap"]), scenario, identify=False, exclude=["bristle"])
    which = out["which"]
    rows = {r["candidate"]: r for r in which["ranking"]}
    print(effects, "->", which["named_set"], which["confidence"], which["verdict"][:200])
    print({n: round(r["held_out_shrink"] * 100, 1) for n, r in rows.items()
           if EFFECTS[n].effect_class == "adhesion_lag"})
    assert "bristle" not in rows
    assert set(which["named_set"]) <= {"adhesion_lag"}, which["verdict"]
    assert which["gap_present"]
    truth = oracle(dg, effects, ["adhesion_lag"])
    print("truth as a candidate:", truth)
    assert all(truth["shrink_percent"] > r["held_out_shrink"] * 100 for n, r in rows.items()
               if EFFECTS[n].effect_class == "adhesion_lag")


def test_a_candidate_whose_fit_fails_is_counted_and_named(tmp_path, scenario):
    """A model whose wheelbase is zero (a scenario built past the loader, which refuses one): the axle
    load transfer divides by it, so both load-transfer forms fail to fit on a real run.  They are
    counted and named (JSON, the text summary, report.md), ranked as removing nothing, and every other
    candidate is still fitted and judged."""
    import dataclasses

    from hil.gap.report import text_summary, write_report

    seed = fresh_seed() % 100000
    summary = run(scenario, "nlls", seed, bus="inprocess", out_dir=tmp_path, progress=False, log=print)
    bad = dataclasses.replace(scenario, vehicle=dataclasses.replace(scenario.vehicle, half_wheelbase_m=0.0))
    out, result = diagnose(read_real_log(summary["mcap"]), bad, identify=False)
    failed = out["which"]["failed_candidates"]
    print(failed)
    assert sorted((f["name"], f["step"]) for f in failed) == [("load_transfer", "alone"),
                                                              ("load_transfer_pitch", "alone")]
    for f in failed:
        assert f["effect"] == "load_transfer" and f["form"] == EFFECTS[f["name"]].form
        assert f["error"].split(":")[0] in ("FloatingPointError", "ZeroDivisionError"), f
    assert result.failed == failed
    rows = {r["candidate"]: r for r in out["which"]["ranking"]}
    for name in ("load_transfer", "load_transfer_pitch"):
        assert rows[name]["note"].startswith("fit failed") and rows[name]["share"] == 0.0
    fitted = {n for n, r in rows.items() if not r["note"].startswith("fit failed")}
    assert fitted == {n for n, s in EFFECTS.items() if s.candidate} - {"load_transfer", "load_transfer_pitch"}
    text = text_summary(out)
    assert "FAILED FITS (2;" in text and "load_transfer (static, alone)" in text, text
    md = write_report(out, result, tmp_path / "report").read_text()
    assert "| load_transfer_pitch | pitch_mode | alone |" in md, md
    assert json.loads(json.dumps(out))["which"]["failed_candidates"] == failed


def test_bench_gap_summary_fits_a_terminal():
    """``hil bench gap``'s default summary, rendered from the stored report, keeps every line within 100
    characters and every figure of it (the full report is ``--markdown``)."""
    from hil.benchmarks.gap import summary_text
    from hil.terminal import WIDTH, wrap_lines

    result = json.loads((ROOT / "docs" / "benchmarks" / "gap.json").read_text())
    text = wrap_lines(summary_text(result))
    assert max(len(line) for line in text.splitlines()) <= WIDTH == 100
    flat = " ".join(text.split())
    assert f"{result['cases']} cases (seed {result['seed']})" in flat
    assert f"false-confident rate {result['false_confident_rate']:.3f}" in flat


def test_a_creep_stretched_rail_is_the_nuisance_and_nothing_more_is_named(tmp_path, scenario):
    """Issue 35 item 3: a rail whose curve is stretched (or shrunk) in creep inside the nuisance's range,
    drawn as the bench's out-of-library family draws it.  The rail curve leaves the held-out gap within
    the noise, so the answer is the nuisance with nothing named, and no second effect is fitted on top of
    anything (before, compliance plus an adhesion lag on top was named "confident")."""
    from hil.benchmarks.gap import family
    from hil.effects import with_reality
    from hil.gap.select import NOISE_GAP
    seed = fresh_seed()
    g = np.random.default_rng(seed)
    cls, effect, sampler = family()["rail_stretch"]
    assert cls == "nuisance" and not EFFECTS[effect].candidate
    effects = {effect: sampler(g)}
    real = with_reality(scenario, effects)
    s = run(real, "nlls", int(g.integers(1, 1 << 30)), bus="inprocess", out_dir=tmp_path, progress=False, log=print)
    out, _ = diagnose(read_real_log(s["mcap"]), scenario, identify=False)
    which = out["which"]
    rail = which["nuisances"][0]
    print(f"seed {seed}: {effects} ->", which["confidence"], which["verdict"][:300])
    assert which["gap_present"]
    assert rail["held_out_gap"] <= NOISE_GAP                    # the nuisance alone is within the noise ...
    assert which["named"] == "none" and which["named_set"] == []   # ... so nothing is named
    assert which["confidence"] == "nuisance", which["verdict"]
    assert which["forward"] is None                            # and no second effect was tried
    assert rail["peak_creep_percent"] == pytest.approx((effects[effect]["creep_scale"] - 1) * 100, abs=1.5)
    assert which["not_separable"] == [] and which["separate_by"] is None
    # HOW FAR is the nuisance's shrink, not the best effect's (issue 51: that read as if it were the answer)
    assert out["shrink"]["effect"] == "rail_curve" and "nuisance" in out["shrink"]["said"]
    assert out["shrink"]["held_out_gap_shrink_percent"] == pytest.approx(rail["held_out_shrink"] * 100)


def test_a_constant_power_limit_is_never_the_rail_nor_a_name(tmp_path, scenario):
    """Issue 35: the drive's constant-power region (the torque capped at P_max / omega_m, no candidate),
    drawn as the bench's family draws it (binding from 0.5-5 % above the equilibrium speed).  The rail
    curve and the drivetrain losses (compliance's viscous + Coulomb form) each remove nearly all of its
    gap.  When neither beats the other by the margin the answer is "not_separable", listing both, with
    where their fits differ most; when the rail curve beats every effect by the margin yet leaves more
    than the noise, "none": the rail is not the whole story (at 3.8 %, test seed 2080877675, it left
    1.66 noise units and the answer was "nuisance", wrong for an effect outside the library).  Never a
    name and never "nuisance" (before, a second effect on top of one of them was named "confident"),
    and no second effect accepted."""
    from hil.benchmarks.gap import family
    from hil.effects import with_reality
    from hil.gap.report import text_summary
    from hil.gap.select import NOISE_GAP
    seed = fresh_seed()
    g = np.random.default_rng(seed)
    cls, effect, sampler = family()["power_limit"]
    assert cls == "outside" and not EFFECTS[effect].candidate
    effects = {effect: sampler(g)}
    assert 1.005 <= effects[effect]["power_ratio"] <= 1.05
    real = with_reality(scenario, effects)
    s = run(real, "nlls", int(g.integers(1, 1 << 30)), bus="inprocess", out_dir=tmp_path, progress=False, log=print)
    out, _ = diagnose(read_real_log(s["mcap"]), scenario, identify=False)
    which = out["which"]
    listed = [a["effect"] for a in which["not_separable"]]
    print(f"seed {seed}: {effects} ->", which["confidence"], listed, which["separate_by"], which["verdict"][:300])
    assert which["gap_present"]
    assert which["named"] == "none" and which["named_set"] == []
    assert which["confidence"] in ("not_separable", "none"), which["verdict"]
    assert which["forward"] is None or not which["forward"]["accepted"], which["forward"]
    if which["confidence"] == "not_separable":
        assert {"rail_curve", "compliance"} <= set(listed), listed
        sb = which["separate_by"]
        assert sb["signal"] in ("motor", "train", "mu_hat") and sb["stage"] in ("normal", "early", "serious")
        assert sb["difference_noise_units"] > 0 and \
            set(sb["between"]) <= {a["explanation"] for a in which["not_separable"]}
        text = text_summary(out)
        assert "NOT SEPARABLE:" in text and "separate by:" in text, text
    else:
        assert listed == [] and which["separate_by"] is None
        rail = which["nuisances"][0]
        if "rail's curve beats every effect" in which["verdict"]:       # best by the margin, not the whole story
            assert rail["held_out_gap"] > NOISE_GAP, rail


def test_grades_are_scored_and_the_calibration_is_read_back(tmp_path):
    """Issue 35 item 1, the table's plumbing (no diagnosis): the bench grades answers as the issue defines
    "right" per grade, writes per grade the right answers and their count, and ``hil gap``'s reader gives
    the line printed beside an answer of that grade; no file, no line."""
    from hil.benchmarks.gap import calibration, grade_right
    from hil.gap.calibration import grade_line, read_calibration

    def case(effects, truth, named_set, grade, listed=(), best="compliance", oracle=None, member_class=None):
        which = {"named_set": named_set, "confidence": grade, "ranking": [{"effect": best}],
                 "not_separable": [{"effect": e} if isinstance(e, str) else {"effect": e[0], "effects": e}
                                   for e in listed]}
        rec = {"effects": effects, "truth_classes": truth, "oracle": oracle, "confidence": grade,
               "member_class": member_class}
        return dict(rec, grade_right=grade_right(rec, which))

    cases = [case({"compliance": {}}, ["compliance"], ["compliance"], "confident"),          # right
             case({"rail_curve": {}}, [], ["adhesion_lag"], "confident"),                      # wrong: a rail
             case({"power_limit": {}}, [], [], "not_separable", ["rail_curve", "compliance"]),  # right: outside
             case({"load_transfer": {}}, ["load_transfer"], [], "not_separable", ["rail_curve", "compliance"]),
             # a pair listed (forward selection's, within the margin) holds both of its classes
             case({"load_transfer": {}, "can": {}}, ["can", "load_transfer"], [], "not_separable",
                  ["load_transfer", "rail_curve", ["load_transfer", "can"]]),                  # right
             case({"load_transfer": {}, "can": {}}, ["can", "load_transfer"], [], "not_separable",
                  ["load_transfer", "rail_curve"]),                                             # wrong
             case({"rail_curve": {}}, [], [], "nuisance"),                                     # right
             case({"tachometer_gain": {}}, [], [], "nuisance"),                                # wrong: no rail
             case({"bristle": {}}, ["adhesion_lag"], [], "tentative", best="adhesion_lag"),   # right
             case({}, [], [], "none"),                                                          # right: nominal
             case({"bristle": {}}, ["adhesion_lag"], [], "none", oracle={"separable": False}),  # right: beyond
             case({"bristle": {}}, ["adhesion_lag"], [], "none", oracle={"separable": True}),   # wrong
             # issue 51: the rail's curve changed in shape (a family member classed nuisance) is the rail too
             case({"rail_shape": {}}, [], [], "nuisance", member_class="nuisance"),             # right
             case({"rail_shape": {}}, [], ["load_transfer"], "confident", member_class="nuisance")]   # wrong
    assert [c["grade_right"] for c in cases] == [True, False, True, False, True, False, True, False, True, True,
                                                 True, False, True, False]
    table = calibration(cases)
    assert {g: (v["right"], v["cases"]) for g, v in table.items()} == {
        "confident": (1, 3), "tentative": (1, 1), "not_separable": (2, 4), "nuisance": (2, 3), "none": (2, 3)}
    lo, hi = table["none"]["interval95"]
    assert lo < 2 / 3 < hi
    path = tmp_path / "gap-calibration.json"
    assert read_calibration(path) is None and grade_line("confident", read_calibration(path)) is None
    path.write_text(json.dumps({"seed": 7, "cases": 10, "grades": table}))
    line = grade_line("none", read_calibration(path))
    assert line["sentence"] == "none: right in 2 of 3 bench cases" and line["seed"] == 7


@pytest.mark.slow
def test_an_effect_added_as_one_record_and_its_equations_is_simulated_fitted_ranked_and_drawn(tmp_path, scenario):
    """A newcomer's effect (issue 51): an inverter whose torque runs ``offset_nm`` above the command, added
    as one ``EffectSpec`` (parameters, units, fit settings, bench draw) with its ``Equations``; nothing
    else changes.  The plant integrates it (the motor's initial acceleration is offset / J_eq), the
    candidate list offers it, a diagnosis of a run with it recovers its offset and ranks it first, and
    the bench draws it among the candidates' own forms."""
    from hil.benchmarks.gap import draw_case, library, parse_mix
    from hil.effects import Draw, EffectSpec, PlantFit, add_effect, remove_effect, with_reality
    from hil.gap.candidates import candidates
    from plant import WheelsetPlant
    from plant.reality import Equations, RealityModel, RealityPlant

    class TorqueOffset(Equations):
        """T = T + offset_nm."""

        def torque(self, e, v):
            v.torque = v.torque + e["offset_nm"]

    cfg = scenario.plant_config()
    t0 = WheelsetPlant(cfg).equilibrium_torque_nm
    add_effect(EffectSpec("torque_offset", "plant", {"offset_nm": 10.0}, "the inverter's torque offset",
                          {"offset_nm": "N·m"}, form="offset", equations=TorqueOffset(),
                          fit=PlantFit(("offset_nm",), (-0.2 * t0,), (0.2 * t0,), (False,), (21,)),
                          draws=(Draw("library_form", lambda g: {"offset_nm": float(g.uniform(0.02, 0.05) * t0)},
                                      recover="offset_nm"),),
                          plausible={"offset_nm": (-0.2 * t0, 0.2 * t0)}))
    try:
        seed = 5151          # a fixed case: the test shows the record is enough, not a rate
        g = np.random.default_rng(seed)
        offset = float(g.uniform(0.02, 0.05) * t0)
        # simulated: at the equilibrium the motor accelerates by offset / J_eq (rad/s^2) more than nominal
        # (plant.model's Appendix A), the train not at all; and a run with it drifts off the nominal one
        model = RealityPlant(cfg, {"torque_offset": {"offset_nm": offset}}).model
        x0 = WheelsetPlant(cfg).x0
        dx = [np.asarray(RealityModel(cfg, e).rhs(x0, t0, 0.0)[0], float).ravel() for e in (model.effects, {})]
        assert dx[0][0] - dx[1][0] == pytest.approx(offset / cfg.params.equivalent_inertia_kgm2, rel=1e-9)
        assert dx[0][1] == pytest.approx(dx[1][1], rel=1e-12)
        # offered as a candidate, with the record's fit settings
        cand = next(c for c in candidates(scenario) if c.name == "torque_offset")
        assert (cand.fit_params, cand.scan) == (("offset_nm",), (21,))
        # fitted and ranked first on a run with it
        real = with_reality(scenario, {"torque_offset": {"offset_nm": offset}})
        s = run(real, "nlls", int(g.integers(1, 1 << 30)), bus="inprocess", out_dir=tmp_path, progress=False,
                log=print)
        out, _ = diagnose(read_real_log(s["mcap"]), scenario, identify=False)
        which = out["which"]
        print(f"seed {seed}: offset {offset:.2f} N·m ->", which["verdict"])
        top = which["ranking"][0]
        assert top["candidate"] == "torque_offset", which["verdict"]
        assert top["params"]["offset_nm"] == pytest.approx(offset, rel=0.1)
        # drawn by the bench among the library forms
        mix = parse_mix("library_form=1")
        assert "torque_offset" in library()
        assert any("torque_offset" in draw_case(seed, i, mix)[1] for i in range(200))
    finally:
        remove_effect("torque_offset")
    assert "torque_offset" not in {c.name for c in candidates(scenario)}


def test_a_quantiser_under_noise_after_it_is_found_by_the_lattices_coherence():
    """Issue 51: speeds on a lattice with noise added after the quantiser step by far less than the
    quantum wherever a reading stays on one lattice point, so the smallest steps miss the lattice; the
    values' coherence with it finds it.  Readings without a quantiser (a ramp plus the sensor noise) give
    no lattice of coherence above 0.9 (the quantiser's naming threshold)."""
    from hil.gap.model import lattice_quantum

    # a fixed seed: the draws sit close to the test's margins (7,178 draws at the merge: coherence down to
    # 0.90001 against the 0.9 threshold, the quantum's error up to 1.6 % against 2 %), so drawn afresh the
    # test would fail more often than once in 10,000 runs; the statistics belong to the design note
    seed = 5151
    g = np.random.default_rng(seed)
    sigma = 0.0045                                   # ffcc_a's motor encoder noise (rad/s)
    t = np.arange(700) * 1e-3
    for _ in range(6):
        q = float(g.uniform(0.05, 0.2))
        motor = 64.0 + float(g.uniform(2, 30)) * t + float(g.uniform(0, 20)) * np.maximum(t - 0.4, 0) ** 2
        noise_after = q / float(g.uniform(40, 60))
        y = np.round((motor + sigma * g.standard_normal(t.size)) / q) * q + noise_after * g.standard_normal(t.size)
        found, coherence = lattice_quantum(y, 2 * sigma, 400 * sigma)
        print(f"seed {seed}: q {q:.4f}, noise after {noise_after:.4f} -> {found:.4f} (coherence {coherence:.3f})")
        assert found == pytest.approx(q, rel=0.02) and coherence > 0.9
        plain = motor + sigma * g.standard_normal(t.size)
        assert lattice_quantum(plain, 2 * sigma, 400 * sigma)[1] < 0.9


def test_a_fit_outside_what_a_vehicle_allows_is_not_named_with_confidence():
    """Issue 51: a static load transfer stood for another change of the curve's shape at low creep with a
    fitted bogie height of 0.06-0.32 m against the vehicle's 2.6 m.  The same row, confident when its
    height is one a vehicle allows (``EffectSpec.plausible``), is only "most likely" when it is not;
    rows written by hand (the margin is 25 in score and half the remaining gap)."""
    from hil.gap.select import Row, judge, off_vehicle

    lo, hi = EFFECTS["load_transfer"].plausible["bogie_height_m"]
    base = {"gap": 10.0, "score": 0.0, "per_signal": {}}

    def ranking(z):
        return [Row("load_transfer", "static", "load_transfer", {"bogie_height_m": z}, 1, 5000.0, 0.97, 0.3,
                    at_bound={"bogie_height_m": False}),
                Row("compliance", "stiffness_backlash", "compliance", {"stiffness_nm_rad": 3e5}, 2, 1000.0, 0.5, 5.0)]
    for z, grade in ((2.0, "confident"), (lo * 0.5, "tentative"), (0.1, "tentative"), (hi * 1.5, "tentative"),
                     (lo, "confident")):
        rows = ranking(z)
        assert bool(off_vehicle(rows[0])) == (grade == "tentative")
        v = judge(base, rows, None, True)
        assert v.grade == grade, (z, v.sentence)
        if grade == "tentative":
            assert "outside what a vehicle allows" in v.sentence and v.named == "none"


def test_adhesion_dynamics_as_a_second_order_contact_lag_is_named_adhesion_lag(tmp_path, scenario):
    """Issue 51: adhesion dynamics written as a second-order contact lag was answered "none" (the
    first-order forms and the bristle cannot lag like it; a static load transfer with a bogie pivot a
    dozen centimetres high explained most of it).  The class's second-order form names its class."""
    from hil.effects import with_reality
    # a fixed case: 4 of 4 drawn cases were named before the merge, too few to set a drawn assertion's failure
    # rate below 1 in 10,000; the bench measures the form's rate
    seed = 5151
    g = np.random.default_rng(seed)
    effects = {"adhesion_lag2": {"natural_hz": float(np.exp(g.uniform(np.log(8), np.log(40)))),
                                 "damping_ratio": float(g.uniform(0.4, 0.9))}}
    s = run(with_reality(scenario, effects), "nlls", int(g.integers(1, 1 << 30)), bus="inprocess", out_dir=tmp_path,
            progress=False, log=print)
    out, _ = diagnose(read_real_log(s["mcap"]), scenario, identify=False)
    which = out["which"]
    print(f"seed {seed}: {effects} ->", which["confidence"], which["verdict"][:300])
    assert which["named_set"] == ["adhesion_lag"] and which["confidence"] == "confident", which["verdict"]
    assert out["shrink"]["held_out_gap_shrink_percent"] >= 80


@pytest.mark.slow
def test_a_second_effect_in_the_remainder_of_a_first_fitted_in_a_poor_basin_is_turned_away(tmp_path, scenario):
    """Issue 51: a second-order contact lag (9.25 Hz, damping 0.681, run seed 1485128210), recorded by
    6d676e1 where the case was drawn (the plant's curve and the TCU have changed since, so a run today is
    another log; this one is kept, xz-compressed, in tests/data).  Alone, the second-order form's fit
    stops at 13.5 Hz and leaves 11.6 noise units; a running resistance (factor 0.906) took 62 % of that
    and, the veto in time passed, the answer was "adhesion_lag and resistance", confident (the tree before
    the fix, 82bfd87's parent, on this file).  Fitted again on the whole window from where its fit before
    the serious stage landed, the lag alone leaves the gap within the noise, and the pair does not beat it."""
    import lzma
    log = tmp_path / "ffcc_a-nlls-1485128210-real.mcap"
    log.write_bytes(lzma.decompress((ROOT / "tests" / "data"
                                     / "ffcc_a-nlls-1485128210-adhesion_lag2-6d676e1.mcap.xz").read_bytes()))
    out, _ = diagnose(read_real_log(log), scenario, identify=False)
    which, fw = out["which"], out["which"]["forward"]
    print(which["confidence"], which["verdict"][:300], fw.get("rejected_because"))
    assert which["named_set"] in ([], ["adhesion_lag"]), which["verdict"]
    assert "resistance" not in which["named_set"]
    assert not fw["accepted"] and fw["second"] == "resistance" and fw["held_out_in_time"]["pair_wins"]
    again = fw["first_again"]["params"]
    assert abs(again["natural_hz"] / 9.254621873200328 - 1) < 0.05, again     # the drawn truth, not a fitted value
    assert abs(again["damping_ratio"] / 0.68100455271771 - 1) < 0.05, again
    assert fw["first_again"]["held_out_gap"] < 0.5 * fw["pair_held_out_gap"]
    assert fw["rejected_because"][0].startswith("adhesion_lag alone, fitted again from where its fit before")
