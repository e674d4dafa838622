"""The plant as an FMU: our FMI 2.0 CS export against the CasADi plant, FMUs in the loop, bad FMUs.

Every FMU here is real: ours is built once per session with gcc (about 1 s); the third-party ones
are OpenModelica- and PythonFMU3-built FMUs shipped in the ``gemseo-fmu`` wheel (installed with
``pip install --no-deps gemseo-fmu``: its own requirements pin an older fmpy).
"""
from __future__ import annotations

import json
import math
import shutil
import subprocess
import zipfile
from importlib import metadata
from pathlib import Path

import fmpy
import numpy as np
import pytest
from fmpy.fmi2 import FMU2Slave
from fmpy.validation import validate_fmu

from hil.exchange import run
from hil.log.read import read_log
from hil.plants import make_plant
from hil.testing import rezip
from hil.config import load_scenario
from plant import WheelsetPlant
from plant.fmu import export_fmu, model_param_names, parameter_values
from plant.fmu_plant import FmuError, FmuPlant

from .conftest import SCENARIOS, hil_command, subprocess_env

STATE_FIELDS = ("motor_speed_rad_s", "train_speed_ms", "creep_speed_kmh", "mu", "load_torque_nm")


@pytest.fixture(scope="session")
def wheelset_fmu(tmp_path_factory) -> Path:
    """Our FMU, exported from FFCC-a (start values) once per test session."""
    sc = load_scenario(SCENARIOS / "ffcc_a.toml")
    return export_fmu(sc.plant_config(), tmp_path_factory.mktemp("fmu") / "wheelset.fmu",
                      stop_time_s=sc.run.duration_s)


@pytest.fixture(scope="session")
def wheelset_fmu3(tmp_path_factory) -> Path:
    """The same plant as an FMI 3.0 Co-Simulation FMU."""
    sc = load_scenario(SCENARIOS / "ffcc_a.toml")
    return export_fmu(sc.plant_config(), tmp_path_factory.mktemp("fmu3") / "wheelset3.fmu",
                      stop_time_s=sc.run.duration_s, fmi_version=3)


def gemseo_fmu(name: str) -> Path:
    try:
        dist = metadata.distribution("gemseo-fmu")
    except metadata.PackageNotFoundError:
        pytest.skip("gemseo-fmu not installed (pip install --no-deps gemseo-fmu): no third-party FMUs")
    for f in dist.files or []:
        if str(f).endswith(f"fmu_files/linux/{name}"):
            return Path(dist.locate_file(f))
    pytest.fail(f"gemseo-fmu has no linux/{name}")


def torque_profile(eq_torque: float, steps: int) -> np.ndarray:
    """A torque that moves: slow sine plus a step and fixed pseudo-random noise."""
    k = np.arange(steps)
    rng = np.random.default_rng(0)
    return eq_torque * (1 + 0.2 * np.sin(k / 37) + 0.05 * (k > steps // 3)) + rng.normal(0, 30, steps)


# -- our export ---------------------------------------------------------------------------------------
def test_export_passes_fmpy_validation_and_declares_the_parameters(wheelset_fmu):
    assert validate_fmu(str(wheelset_fmu)) == []
    md = fmpy.read_model_description(str(wheelset_fmu))
    assert md.fmiVersion == "2.0" and md.coSimulation is not None and md.modelExchange is None
    assert fmpy.platform in fmpy.supported_platforms(str(wheelset_fmu))
    by_name = {v.name: v for v in md.modelVariables}
    for name in (*model_param_names(2), "integration_step_s", "initial_motor_speed_rad_s", "initial_train_speed_ms"):
        v = by_name[name]
        assert (v.causality, v.variability, v.type) == ("parameter", "fixed", "Real"), name
    # Table 1, curves and fault time carry FFCC-a's values as start values
    assert float(by_name["gear_ratio"].start) == 2.788
    assert float(by_name["fault_curve_tau2"].start) == -1.1
    assert float(by_name["fault_time_s"].start) == 0.5
    assert by_name["torque_nm"].causality == "input"
    for name in STATE_FIELDS:
        assert by_name[name].causality == "output"


@pytest.mark.parametrize("scenario", ["ffcc_a", "ffcc_b"])
def test_simulate_fmu_matches_the_casadi_plant(wheelset_fmu, scenario):
    """fmpy's own simulate_fmu, other scenario's values passed as start values: one FMU, several scenarios."""
    sc = load_scenario(SCENARIOS / f"{scenario}.toml")
    cfg = sc.plant_config()
    res = fmpy.simulate_fmu(str(wheelset_fmu), stop_time=sc.run.duration_s, step_size=cfg.exchange_period_s,
                            output_interval=cfg.exchange_period_s, start_values=parameter_values(cfg, 2),
                            output=list(STATE_FIELDS))
    plant = WheelsetPlant(cfg)
    ref = [plant.state] + [plant.step(plant.equilibrium_torque_nm) for _ in range(sc.steps)]
    assert len(res) == len(ref)
    assert np.allclose(res["time"], [s.t_s for s in ref], rtol=0, atol=1e-12)
    for name in STATE_FIELDS:
        expected = np.array([getattr(s, name) for s in ref])
        assert np.max(np.abs(res[name] - expected)) <= 1e-9 * max(1.0, np.max(np.abs(expected))), name
    # the fault did happen inside the run: mu falls by more than a third
    assert res["mu"][-1] < 0.67 * res["mu"][0]


def test_fmi3_export_passes_validation(wheelset_fmu3):
    assert validate_fmu(str(wheelset_fmu3)) == []
    md = fmpy.read_model_description(str(wheelset_fmu3))
    assert md.fmiVersion == "3.0" and md.coSimulation is not None and md.modelExchange is None
    assert fmpy.platform in fmpy.supported_platforms(str(wheelset_fmu3))


@pytest.mark.parametrize("fmi", ["2", "3"])
@pytest.mark.parametrize("scenario", ["ffcc_a", "ffcc_b"])
def test_fmu_plant_tracks_the_casadi_plant_under_a_moving_torque(wheelset_fmu, wheelset_fmu3, scenario, fmi):
    sc = load_scenario(SCENARIOS / f"{scenario}.toml")
    cfg = sc.plant_config()
    ref = WheelsetPlant(cfg)
    with FmuPlant(wheelset_fmu if fmi == "2" else wheelset_fmu3, cfg) as fmu:
        assert fmu.fmi_version == fmi
        assert np.array_equal(fmu.x0, ref.x0) and fmu.equilibrium_torque_nm == ref.equilibrium_torque_nm
        worst = dict.fromkeys(STATE_FIELDS, 0.0)
        for tq in torque_profile(ref.equilibrium_torque_nm, sc.steps):
            a, b = ref.step(tq), fmu.step(tq)
            assert (a.t_s, a.fault_active, a.torque_nm) == (b.t_s, b.fault_active, b.torque_nm)
            for name in STATE_FIELDS:
                worst[name] = max(worst[name], abs(getattr(a, name) - getattr(b, name)))
        assert all(v <= 1e-9 for v in worst.values()), worst
        # reset starts again from the equilibrium
        s0 = fmu.reset()
        assert fmu.step_index == 0 and s0.t_s == 0 and s0.motor_speed_rad_s == ref.x0[0]


def test_fmu_step_must_be_a_multiple_of_the_integration_step(wheelset_fmu):
    sc = load_scenario(SCENARIOS / "ffcc_a.toml", {"run.exchange_period_s": 1e-3, "run.integration_step_s": 1e-4})
    cfg = sc.plant_config()
    with FmuPlant(wheelset_fmu, cfg, parameters={"integration_step_s": 3e-4}) as fmu:
        with pytest.raises(FloatingPointError, match="not a whole multiple of integration_step_s"):
            fmu.step(fmu.equilibrium_torque_nm)


def test_identification_identical_with_fmu_and_casadi_plant(wheelset_fmu, tmp_path):
    """`hil run` both ways, same seed: the JSON summaries agree on everything but wall-clock figures."""
    runs = {}
    for kind in ("casadi", f"fmu:{wheelset_fmu}"):
        out = tmp_path / kind.split(":")[0]
        r = subprocess.run(hil_command() + ["run", "scenarios/ffcc_b.toml", "--bus", "inprocess", "--seed", "5",
                                            "--plant", kind, "--out", str(out), "--json"],
                           capture_output=True, text=True, env=subprocess_env(), timeout=300)
        assert r.returncode == 0, r.stderr
        runs[kind] = json.loads(r.stdout)
    a, b = runs.values()
    assert a["corrections"] > 0 and a["params"]
    assert a["plant"] == "casadi" and b["plant"] == "fmu-wheelset"
    timing = {"wall_s", "mcap", "sim_s_per_wall_s", "messages", "frames_tx", "frames_rx", "plant"}
    timing |= {k for k in a if k.startswith(("round_trip", "deadline", "jitter", "late", "period_"))}
    for key in set(a) | set(b):
        if key not in timing:
            assert a.get(key) == b.get(key), key
    meta = read_log(b["mcap"]).metadata["plant"]
    assert meta["path"] == str(wheelset_fmu) and json.loads(meta["mapping"])["torque_nm"] == "torque_nm"
    assert "plant" not in read_log(a["mcap"]).metadata


# -- bad FMUs and bad mappings ---------------------------------------------------------------------------
def test_bad_fmus_give_one_clear_error(wheelset_fmu, tmp_path):
    cfg = load_scenario(SCENARIOS / "ffcc_a.toml").plant_config()
    text = tmp_path / "text.fmu"
    text.write_text("not a zip")
    with pytest.raises(FmuError, match=r"text.fmu: not an FMU \(not a zip archive\)"):
        FmuPlant(text, cfg)
    with pytest.raises(FmuError, match="no such FMU file"):
        FmuPlant(tmp_path / "missing.fmu", cfg)
    no_bin = rezip(wheelset_fmu, tmp_path / "nobin.fmu", drop_prefix=f"binaries/{fmpy.platform}/")
    with pytest.raises(FmuError, match=f"no binary for this platform {fmpy.platform} .*C sources"):
        FmuPlant(no_bin, cfg)
    me_only = rezip(wheelset_fmu, tmp_path / "me.fmu", edit_md=lambda md: md.replace(
        "<CoSimulation ", '<ModelExchange ').replace("</CoSimulation>", "</ModelExchange>"))
    with pytest.raises(FmuError, match="Model Exchange only; the loop needs a Co-Simulation FMU"):
        FmuPlant(me_only, cfg)
    # a binary that is not a shared library, and a binary from another export (GUID mismatch)
    garbage = tmp_path / "garbage.fmu"
    with zipfile.ZipFile(wheelset_fmu) as zin, zipfile.ZipFile(garbage, "w") as zout:
        for item in zin.infolist():
            zout.writestr(item, b"\x7fELF garbage" if item.filename.startswith("binaries/") else zin.read(item))
    with pytest.raises(FmuError, match="garbage.fmu: cannot load or instantiate the FMU's binary"):
        FmuPlant(garbage, cfg)
    other_guid = rezip(wheelset_fmu, tmp_path / "guid.fmu", edit_md=lambda md: md.replace('guid="{', 'guid="{0'))
    with pytest.raises(FmuError, match="GUID mismatch"):
        FmuPlant(other_guid, cfg)


def test_missing_and_mistyped_mapping_named_with_what_the_fmu_offers(wheelset_fmu):
    cfg = load_scenario(SCENARIOS / "ffcc_a.toml").plant_config()
    with pytest.raises(FmuError) as e:
        FmuPlant(wheelset_fmu, cfg, mapping={"torque_nm": "mu", "train_speed_ms": "v_train"})
    msg = str(e.value)
    assert "\n" not in msg
    assert "torque_nm -> 'mu' (is Real output, need Real input)" in msg
    assert "train_speed_ms -> 'v_train' (no such variable)" in msg
    assert "Real inputs: torque_nm; Real outputs: motor_speed_rad_s, train_speed_ms" in msg
    with pytest.raises(FmuError, match="unknown mapping key"):
        FmuPlant(wheelset_fmu, cfg, mapping={"speed": "x"})
    with pytest.raises(FmuError, match="cannot set parameter 'no_such'"):
        FmuPlant(wheelset_fmu, cfg, parameters={"no_such": 1.0})


def test_hil_run_with_a_bad_fmu_is_one_line_exit_2(tmp_path):
    bad = tmp_path / "bad.fmu"
    bad.write_bytes(b"PK\x03\x04 broken")
    r = subprocess.run(hil_command() + ["run", "scenarios/ffcc_a.toml", "--bus", "inprocess", "--plant", f"fmu:{bad}",
                                        "--out", str(tmp_path)], capture_output=True, text=True,
                       env=subprocess_env(), timeout=120)
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "bad.fmu: not an FMU" in r.stderr and "Traceback" not in r.stderr


def test_hil_fmu_export_command_writes_a_valid_fmu(tmp_path):
    out = tmp_path / "b.fmu"
    r = subprocess.run(hil_command() + ["fmu", "export", "scenarios/ffcc_b.toml", "-o", str(out)],
                       capture_output=True, text=True, env=subprocess_env(), timeout=120)
    assert r.returncode == 0, r.stderr
    assert validate_fmu(str(out)) == []
    md = fmpy.read_model_description(str(out))
    starts = {v.name: v.start for v in md.modelVariables}
    assert float(starts["fault_curve_lambda0"]) == load_scenario(SCENARIOS / "ffcc_b.toml").fault_curve.lambda0


# -- FMUs we did not build ------------------------------------------------------------------------------------
def test_third_party_openmodelica_fmu_runs_through_the_loop_with_a_mapping(tmp_path):
    """Mass_Damper (OpenModelica 1.19, FMI 2.0 ME+CS): force input f, mass speed and position as the 'speeds'.
    The identification is meaningless here; the loop must run, record, and map the variables."""
    fmu_path = gemseo_fmu("Mass_Damper.fmu")
    scenario = tmp_path / "mass_damper.toml"
    scenario.write_text((SCENARIOS / "ffcc_a.toml").read_text() + f"""
[plant]
fmu = "{fmu_path}"
[plant.mapping]
torque_nm = "f"
motor_speed_rad_s = "mass.v"
train_speed_ms = "y"
[plant.parameters]
"damper.d" = 20.0
""")
    sc = load_scenario(scenario)
    plant = make_plant(sc)
    try:
        summary = run(sc, "nlls", 1, bus="inprocess", out_dir=tmp_path, progress=False, plant=plant, log=print)
    finally:
        plant.close()
    assert summary["sim_s"] == pytest.approx(sc.run.duration_s)
    log = read_log(summary["mcap"])
    meta = log.metadata["plant"]
    assert json.loads(meta["mapping"]) == {"torque_nm": "f", "motor_speed_rad_s": "mass.v", "train_speed_ms": "y"}
    assert json.loads(meta["parameters"]) == {"damper.d": 20.0}
    states = log.topic("/plant/state")
    assert len(states) == sc.steps
    assert all(math.isnan(s.mu) for s in states)      # no true mu mapped
    # replay the recorded torques into the FMU with fmpy directly: the log must hold the FMU's own values
    md = fmpy.read_model_description(str(fmu_path))
    vr = {v.name: v.valueReference for v in md.modelVariables}
    unzipped = fmpy.extract(str(fmu_path))
    try:
        fmu = FMU2Slave(guid=md.guid, unzipDirectory=unzipped, modelIdentifier=md.coSimulation.modelIdentifier,
                        instanceName="replay")
        fmu.instantiate()
        fmu.setupExperiment(startTime=0.0)
        fmu.setReal([vr["damper.d"], vr["f"]], [20.0, states[0].torque_nm])
        fmu.enterInitializationMode()
        fmu.exitInitializationMode()
        period = sc.run.exchange_period_s
        for k, s in enumerate(states):
            v, y = fmu.getReal([vr["mass.v"], vr["y"]])
            assert (s.motor_speed_rad_s, s.train_speed_ms) == (v, y), k
            if k + 1 < len(states):     # state k+1 records the torque applied from k to k+1
                fmu.setReal([vr["f"]], [states[k + 1].torque_nm])
                fmu.doStep(k * period, period)
        fmu.terminate()
        fmu.freeInstance()
    finally:
        shutil.rmtree(unzipped, ignore_errors=True)
    moved = np.ptp([s.train_speed_ms for s in states])
    assert moved > 1e-3       # the mass did move under the commanded force


def test_third_party_fmi3_cosimulation_fmu(tmp_path):
    """FMU3Model (PythonFMU3, FMI 3.0 CS): output = 3 + increment*input at initialisation, then +increment per step."""
    fmu_path = gemseo_fmu("FMU3Model.fmu")
    cfg = load_scenario(SCENARIOS / "ffcc_a.toml").plant_config()
    with FmuPlant(fmu_path, cfg, mapping={"torque_nm": "input", "motor_speed_rad_s": "output",
                                          "train_speed_ms": "output"}, parameters={"increment": 0.5}) as p:
        assert p.fmi_version == "3"
        start = 3 + 0.5 * p.equilibrium_torque_nm
        assert p.state.motor_speed_rad_s == pytest.approx(start)
        for k in range(1, 6):
            s = p.step(10.0)
            assert s.motor_speed_rad_s == pytest.approx(start + 0.5 * k) and s.t_s == pytest.approx(k * 1e-3)


# -- choosing the plant: --plant and the [plant] table ------------------------------------------------------------
def _scenario_with(tmp_path, extra: str):
    path = tmp_path / "s.toml"
    path.write_text((SCENARIOS / "ffcc_a.toml").read_text() + extra)
    return load_scenario(path)


def test_plant_table_relative_fmu_path_and_plant_spec(wheelset_fmu, tmp_path):
    from hil.errors import ConfigError
    from hil.config import ScenarioError

    shutil.copy(wheelset_fmu, tmp_path / "wheelset.fmu")
    sc = _scenario_with(tmp_path, '\n[plant]\nfmu = "wheelset.fmu"\n')
    plant = make_plant(sc)
    try:
        assert isinstance(plant, FmuPlant) and plant.path == tmp_path / "wheelset.fmu"
    finally:
        plant.close()
    assert make_plant(sc, "casadi") is None                      # --plant casadi wins over the table
    assert make_plant(load_scenario(SCENARIOS / "ffcc_a.toml")) is None
    with pytest.raises(ConfigError, match="expected 'casadi' or 'fmu:PATH'"):
        make_plant(sc, "modelica")
    with pytest.raises(ScenarioError, match=r"s.toml: \[plant\] fmux: unknown key"):
        make_plant(_scenario_with(tmp_path, '\n[plant]\nfmux = "a.fmu"\n'))
    with pytest.raises(ScenarioError, match=r"\[plant.mapping\] torque_nm: must be an FMU variable name"):
        make_plant(_scenario_with(tmp_path, '\n[plant]\nfmu = "wheelset.fmu"\n[plant.mapping]\ntorque_nm = 3\n'))
    with pytest.raises(ConfigError, match=r"\[reality\] plant effects \(torque_lag\).*cannot be combined"):
        make_plant(_scenario_with(tmp_path, '\n[plant]\nfmu = "wheelset.fmu"\n[reality]\ntorque_lag = true\n'))


# -- FMUs are data until trusted ------------------------------------------------------------------------------
def _files_under(root: Path) -> set[Path]:
    return {p for p in root.rglob("*")}


def _hil_fmu(args, tmp_path, **env):
    """``hil ARGS`` with TMPDIR in ``tmp_path/tmp`` (where an FMU would be unpacked), output captured."""
    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir(exist_ok=True)
    return subprocess.run(hil_command() + [str(a) for a in args], capture_output=True, text=True,
                          env={**subprocess_env(), "TMPDIR": str(tmpdir), **env}, timeout=120)


@pytest.fixture(scope="module")
def marker_library(tmp_path_factory):
    """A shared library that, once loaded, creates the file ``loaded`` beside itself: what an FMU with a
    path for a modelIdentifier would make hil run."""
    if shutil.which("gcc") is None:
        pytest.skip("no gcc")
    d = tmp_path_factory.mktemp("evil")
    (d / "evil.c").write_text('#include <stdio.h>\n__attribute__((constructor)) static void hit(void) '
                              f'{{ FILE *f = fopen("{d}/loaded", "w"); if (f) fclose(f); }}\n')
    subprocess.run(["gcc", "-shared", "-fPIC", "-o", str(d / "evil.so"), str(d / "evil.c")], check=True)
    return d


def test_a_model_identifier_that_is_a_path_is_refused_and_nothing_runs(wheelset_fmu, marker_library, tmp_path):
    cfg = load_scenario(SCENARIOS / "ffcc_a.toml").plant_config()
    ident = fmpy.read_model_description(str(wheelset_fmu)).coSimulation.modelIdentifier
    for i, evil in enumerate([str(marker_library / "evil"), "../../evil"]):
        fmu = rezip(wheelset_fmu, tmp_path / f"evil{i}.fmu",
                     edit_md=lambda md: md.replace(f'modelIdentifier="{ident}"', f'modelIdentifier="{evil}"'))
        with pytest.raises(FmuError) as e:
            FmuPlant(fmu, cfg)
        msg = str(e.value)
        assert "\n" not in msg and f"coSimulation modelIdentifier '{evil}' is not a plain name" in msg, msg
        r = _hil_fmu(["run", SCENARIOS / "ffcc_a.toml", "--bus", "inprocess", "--plant", f"fmu:{fmu}", "--out",
                      tmp_path / "out"], tmp_path)
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "is not a plain name" in r.stderr
        info = _hil_fmu(["fmu", "info", fmu], tmp_path)
        assert info.returncode == 0 and "safety: 1 problem(s); hil refuses to unpack or load this FMU" in info.stdout
        assert f"modelIdentifier '{evil}' is not a plain name" in info.stdout, info.stdout
    assert not (marker_library / "loaded").exists()
    assert list((tmp_path / "tmp").iterdir()) == [] and not (tmp_path / "out").exists()


@pytest.mark.parametrize("member", ["../x", "../../escaped/x", "/abs/x", "resources/../../x"])
def test_an_archive_member_outside_the_fmu_is_refused_before_unpacking(wheelset_fmu, tmp_path, member):
    cfg = load_scenario(SCENARIOS / "ffcc_a.toml").plant_config()
    work = tmp_path / "a" / "b"
    work.mkdir(parents=True)
    fmu = work / "slip.fmu"
    shutil.copy(wheelset_fmu, fmu)
    with zipfile.ZipFile(fmu, "a") as z:
        z.writestr(member, b"written outside")
    before = _files_under(tmp_path)
    with pytest.raises(FmuError, match=r"refused: archive member .* (leaves the FMU's folder|is an absolute path)"):
        FmuPlant(fmu, cfg)
    r = _hil_fmu(["run", SCENARIOS / "ffcc_a.toml", "--bus", "inprocess", "--plant", f"fmu:{fmu}", "--out",
                  work / "out"], tmp_path)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "refused: archive member" in r.stderr
    info = _hil_fmu(["fmu", "info", fmu], tmp_path)
    assert info.returncode == 0 and "safety: 1 problem(s)" in info.stdout, info.stdout
    assert _files_under(tmp_path) - before == {tmp_path / "tmp"}        # nothing unpacked anywhere


def test_a_zip_bomb_is_refused_before_unpacking(wheelset_fmu, tmp_path):
    """Three members of 200 MiB of zeros (0.6 MB in the archive) declare more than the 512 MiB cap."""
    fmu = tmp_path / "bomb.fmu"
    shutil.copy(wheelset_fmu, fmu)
    zeros = bytes(1 << 20)
    with zipfile.ZipFile(fmu, "a", zipfile.ZIP_DEFLATED) as z:
        for i in range(3):
            with z.open(f"resources/zeros{i}", "w", force_zip64=True) as f:
                for _ in range(200):
                    f.write(zeros)
    assert fmu.stat().st_size < 2_000_000
    r = _hil_fmu(["run", SCENARIOS / "ffcc_a.toml", "--bus", "inprocess", "--plant", f"fmu:{fmu}", "--out",
                  tmp_path / "out"], tmp_path)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert "refused: unpacks to 600 MiB, more than the 512 MiB allowed (HIL_FMU_MAX_BYTES sets it)" in lines[0]
    assert list((tmp_path / "tmp").iterdir()) == [] and not (tmp_path / "out").exists()
    info = _hil_fmu(["fmu", "info", fmu, "--json"], tmp_path)
    assert info.returncode == 0 and json.loads(info.stdout)["safety_problems"] == [
        "unpacks to 600 MiB, more than the 512 MiB allowed (HIL_FMU_MAX_BYTES sets it)"]


def test_the_unpacked_size_cap_is_settable_and_counted_while_unpacking(wheelset_fmu, tmp_path, monkeypatch):
    from plant.fmu_plant import extract_fmu

    cfg = load_scenario(SCENARIOS / "ffcc_a.toml").plant_config()
    size = sum(i.file_size for i in zipfile.ZipFile(wheelset_fmu).infolist())
    monkeypatch.setenv("HIL_FMU_MAX_BYTES", str(size - 1))
    with pytest.raises(FmuError, match="refused: unpacks to .* MiB allowed"):
        FmuPlant(wheelset_fmu, cfg)
    monkeypatch.setenv("HIL_FMU_MAX_BYTES", "lots")
    with pytest.raises(FmuError, match="HIL_FMU_MAX_BYTES='lots': must be a positive number of bytes"):
        FmuPlant(wheelset_fmu, cfg)
    monkeypatch.setenv("HIL_FMU_MAX_BYTES", str(size))
    dest = tmp_path / "unpacked"
    assert extract_fmu(wheelset_fmu, dest) == str(dest.resolve())
    assert sum(p.stat().st_size for p in dest.rglob("*") if p.is_file()) == size
    # a member that inflates to more than it declares: zipfile stops at the declared size, the CRC fails
    liar = tmp_path / "liar.fmu"
    shutil.copy(wheelset_fmu, liar)
    with zipfile.ZipFile(liar, "a", zipfile.ZIP_DEFLATED) as z:
        z.writestr("resources/lie", bytes(4096))
    data = bytearray(liar.read_bytes())
    cd = data.rfind(b"PK\x01\x02")                                                   # last central entry
    name_at = data.rfind(b"resources/lie")
    assert cd < name_at
    data[cd + 24:cd + 28] = (16).to_bytes(4, "little")                                # declared size 16 B
    liar.write_bytes(bytes(data))
    monkeypatch.delenv("HIL_FMU_MAX_BYTES")
    with pytest.raises(FmuError, match="liar.fmu: cannot unpack the FMU: Bad CRC-32|unpacks to more than it declares"):
        extract_fmu(liar, tmp_path / "liar")


def test_a_folder_and_an_fmi1_fmu_get_the_right_line(wheelset_fmu, tmp_path):
    folder = tmp_path / "unzipped.fmu"
    folder.mkdir()
    fmi1 = rezip(wheelset_fmu, tmp_path / "fmi1.fmu", edit_md=lambda md: md.replace('fmiVersion="2.0"',
                                                                                         'fmiVersion="1.0"'))
    for fmu, says in ((folder, "unzipped.fmu: is a folder; an FMU is a single .fmu file (a zip archive)"),
                      (fmi1, "fmi1.fmu: FMI 1.0 is not supported (need FMI 2.0 or 3.0 Co-Simulation)")):
        for args in (["run", SCENARIOS / "ffcc_a.toml", "--bus", "inprocess", "--plant", f"fmu:{fmu}", "--out",
                      tmp_path / "out"], ["fmu", "info", fmu]):
            r = _hil_fmu(args, tmp_path)
            assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and says in r.stderr, r.stderr
