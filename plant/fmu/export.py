"""Export the CasADi wheelset plant as an FMI 2.0 (or 3.0) Co-Simulation FMU.

The model is *not* re-written for the FMU: :func:`plant.model.dynamics` and :func:`plant.model.rk4_step`
(the very functions the loop's ``WheelsetPlant`` integrates) are called on a configuration whose
numbers are CasADi symbols.  CasADi's ``CodeGenerator`` turns the resulting expressions into C; a
small FMI 2 wrapper (``fmi2_cs.c``) holds the variables and, in ``fmi2DoStep``, runs as many fixed
RK4 steps of ``integration_step_s`` as the communication step holds.  gcc compiles it for this
platform; the sources travel inside the FMU too.

Everything that differs between scenarios is an FMU parameter -- Table 1 (``WheelsetParams``), both
friction curves, the fault time, the demanded adhesion, the integration step and the initial state --
so one FMU serves every scenario whose curves have at most ``n_terms`` exponential terms (fewer
terms are padded with lambda = 0).  Only exponential curves: a scenario whose fault curve follows
Polach's law (``[curves.fault] model = "polach"``) is refused with one line (``FmuExportError``).
"""
from __future__ import annotations

import dataclasses
import datetime
import hashlib
import os
import shutil
import subprocess
import tempfile
import uuid
import zipfile
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import casadi as ca

from ..friction import FrictionCurve
from ..model import PlantConfig, dynamics, equilibrium, rk4_step
from ..params import WheelsetParams

MODEL_IDENTIFIER = "wheelset"
GENERATION_TOOL = "railway-hil"
WRAPPERS = {"2": Path(__file__).with_name("fmi2_cs.c"), "3": Path(__file__).with_name("fmi3_cs.c")}

#: units of the WheelsetParams fields (for modelDescription.xml); the names carry them too
_PARAM_UNITS = {"kg": "kg", "kgm2": "kg.m2", "m": "m", "ms2": "m/s2", "n": "N", "n_per_ms": "N.s/m",
                "n_per_ms2": "N.s2/m2"}

OUTPUTS = (  # name, unit, description
    ("motor_speed_rad_s", "rad/s", "motor angular speed omega_m (true, noise-free)"),
    ("train_speed_ms", "m/s", "train speed v_t (true, noise-free)"),
    ("creep_speed_kmh", "km/h", "creep speed v_s = omega_m/R_g*r - v_t"),
    ("mu", "1", "adhesion (friction) coefficient at the creep speed"),
    ("load_torque_nm", "N.m", "adhesion load torque at the motor shaft T_L = mu*T_W*g*r/(eta*R_g)"),
)
INPUT = ("torque_nm", "N.m", "motor torque T_e, held over the communication step")
EXTRA_PARAMS = (  # handled by the C wrapper, not by the CasADi expressions
    ("integration_step_s", "s", "fixed RK4 step; the communication step must be a whole multiple of it"),
    ("initial_motor_speed_rad_s", "rad/s", "motor speed at the start (default: the exporting scenario's "
                                           "equilibrium before the fault)"),
    ("initial_train_speed_ms", "m/s", "train speed at the start"),
)


class FmuExportError(RuntimeError):
    """The FMU could not be built (no C compiler, compiler error, bad configuration)."""


def _unit(field_name: str) -> str:
    if field_name == "driven_axles":
        return "1"
    if field_name in ("efficiency", "gear_ratio"):
        return "1"
    for suffix in sorted(_PARAM_UNITS, key=len, reverse=True):
        if field_name.endswith("_" + suffix):
            return _PARAM_UNITS[suffix]
    return "1"


def curve_param_names(prefix: str, n_terms: int) -> list[str]:
    return ([f"{prefix}_lambda0"] + [f"{prefix}_lambda{i + 1}" for i in range(n_terms)]
            + [f"{prefix}_tau{i + 1}" for i in range(n_terms)])


def model_param_names(n_terms: int) -> list[str]:
    """The parameters the CasADi expressions read, in the order of the generated functions' ``p``."""
    return ([f.name for f in dataclasses.fields(WheelsetParams)] + ["mu_required", "fault_time_s"]
            + curve_param_names("normal_curve", n_terms) + curve_param_names("fault_curve", n_terms))


def _exponential_only(cfg: PlantConfig) -> None:
    """The FMU's parameters are the exponential form's: refuse any other friction law in one line."""
    for which, curve in (("normal", cfg.normal_curve), ("fault", cfg.fault_curve)):
        if not isinstance(curve, FrictionCurve):
            model = getattr(curve, "model", type(curve).__name__)
            raise FmuExportError(f"{which} curve: model = {model!r} cannot be exported; the FMU holds exponential "
                                 "curves only (model = 'exp': mu = lambda0 + sum lambda_i exp(tau_i v_s))")


def _padded(curve: FrictionCurve, n_terms: int, which: str) -> list[float]:
    if curve.n_terms > n_terms:
        raise FmuExportError(f"{which} curve {curve.name!r} has {curve.n_terms} exponential terms; this FMU "
                             f"holds at most {n_terms} (export with more terms)")
    pad = n_terms - curve.n_terms
    return [curve.lambda0, *curve.lambdas, *([0.0] * pad), *curve.taus, *([-1.0] * pad)]


def parameter_values(cfg: PlantConfig, n_terms: int) -> dict[str, float]:
    """Every FMU parameter for a numeric plant configuration, by name (what FmuPlant sets)."""
    _exponential_only(cfg)
    x0, _ = equilibrium(cfg)
    values = [float(getattr(cfg.params, f.name)) for f in dataclasses.fields(WheelsetParams)]
    values += [cfg.mu_required, cfg.fault_time_s]
    values += _padded(cfg.normal_curve, n_terms, "normal") + _padded(cfg.fault_curve, n_terms, "fault")
    out = dict(zip(model_param_names(n_terms), (float(v) for v in values)))
    out.update(integration_step_s=float(cfg.integration_step_s), initial_motor_speed_rad_s=float(x0[0]),
               initial_train_speed_ms=float(x0[1]))
    return out


def _symbolic_config(n_terms: int) -> tuple[PlantConfig, ca.SX]:
    """A PlantConfig whose numbers are CasADi symbols, and the vector of those symbols."""
    syms: dict[str, ca.SX] = {name: ca.SX.sym(name) for name in model_param_names(n_terms)}
    params = WheelsetParams(**{f.name: syms[f.name] for f in dataclasses.fields(WheelsetParams)})

    def curve(prefix):
        n = curve_param_names(prefix, n_terms)
        return FrictionCurve(syms[n[0]], tuple(syms[k] for k in n[1:1 + n_terms]),
                             tuple(syms[k] for k in n[1 + n_terms:]), prefix)

    cfg = PlantConfig(params, curve("normal_curve"), curve("fault_curve"), syms["mu_required"],
                      syms["fault_time_s"], initial_train_speed_ms=float("nan"), integration_step_s=1.0,
                      exchange_period_s=1.0)
    return cfg, ca.vertcat(*syms.values())


def build_functions(n_terms: int) -> tuple[ca.Function, ca.Function]:
    """(step, out): one RK4 step and the outputs, with every model parameter an input ``p``."""
    cfg, p = _symbolic_config(n_terms)
    x = ca.SX.sym("x", 2)
    torque = ca.SX.sym("torque_nm")
    t = ca.SX.sym("t_s")
    h = ca.SX.sym("h_s")
    x_next = rk4_step(lambda x_, u_, t_: dynamics(cfg, x_, u_, t_)[0], x, torque, t, h)
    step = ca.Function("wheelset_rk4", [x, torque, t, h, p], [x_next], ["x", "torque_nm", "t_s", "h_s", "p"],
                       ["x_next"])
    _, mu, v_s = dynamics(cfg, x, 0.0, t)
    out = ca.Function("wheelset_out", [x, t, p], [mu, v_s, mu * cfg.params.torque_per_mu_nm],
                      ["x", "t_s", "p"], ["mu", "creep_speed_kmh", "load_torque_nm"])
    return step, out


@dataclass(frozen=True)
class _Var:
    name: str
    vr: int
    causality: str
    unit: str
    description: str
    start: float | None = None
    type: str = "Real"


def _variables(values: dict[str, float], torque_start: float, n_terms: int) -> list[_Var]:
    out = []
    names = model_param_names(n_terms)
    descr = {"mu_required": "adhesion demanded before the fault (the other axles hold it)",
             "fault_time_s": "time the rail switches from the normal to the fault curve",
             "driven_axles": "number of driven axles pulling the train (count)"}
    for name in names:
        if name.startswith(("normal_curve_", "fault_curve_")):
            unit = "h/km" if "_tau" in name else "1"
            d = ("NFCC-0 " if name.startswith("normal") else "FFCC ") + \
                "term of mu(v_s) = lambda0 + sum lambda_i*exp(tau_i*v_s), v_s in km/h"
        else:
            unit = "s" if name == "fault_time_s" else _unit(name)
            d = descr.get(name, "paper Table 1" if name in _TABLE1 else "train-level data")
        out.append(_Var(name, len(out), "parameter", unit, d, values[name]))
    for name, unit, d in EXTRA_PARAMS:
        out.append(_Var(name, len(out), "parameter", unit, d, values[name]))
    out.append(_Var(INPUT[0], len(out), "input", INPUT[1], INPUT[2], torque_start))
    for name, unit, d in OUTPUTS:
        out.append(_Var(name, len(out), "output", unit, d))
    out.append(_Var("fault_active", 0, "output", "", "true once time >= fault_time_s", type="Boolean"))
    return out


_TABLE1 = {"axle_load_kg", "motor_inertia_kgm2", "wheelset_inertia_kgm2", "wheel_radius_m", "train_mass_kg",
           "gravity_ms2", "gear_ratio", "efficiency", "half_bogie_distance_m", "half_wheelbase_m",
           "coupler_height_m", "bogie_height_m"}


def _model_description(variables, guid, description, stop_time_s, step_s, sources) -> str:
    units = sorted({v.unit for v in variables if v.unit})
    lines = ['<?xml version="1.0" encoding="UTF-8"?>',
             f'<fmiModelDescription fmiVersion="2.0" modelName="{MODEL_IDENTIFIER}" guid="{guid}"'
             f' description={quoteattr(description)}'
             f' generationTool="{GENERATION_TOOL} (CasADi {ca.__version__})"'
             f' generationDateAndTime="{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%dT%H:%M:%SZ}"'
             ' variableNamingConvention="flat" numberOfEventIndicators="0">',
             f'  <CoSimulation modelIdentifier="{MODEL_IDENTIFIER}" canHandleVariableCommunicationStepSize="true"'
             ' canBeInstantiatedOnlyOncePerProcess="false" canNotUseMemoryManagementFunctions="false"'
             ' canGetAndSetFMUstate="false" canSerializeFMUstate="false" providesDirectionalDerivative="false">',
             '    <SourceFiles>']
    lines += [f'      <File name="{s}"/>' for s in sources]
    lines += ['    </SourceFiles>', '  </CoSimulation>', '  <UnitDefinitions>']
    lines += [f'    <Unit name={quoteattr(u)}/>' for u in units]
    lines += ['  </UnitDefinitions>', '  <LogCategories>', '    <Category name="logStatusError"/>',
              '    <Category name="logAll"/>', '  </LogCategories>',
              f'  <DefaultExperiment startTime="0" stopTime="{stop_time_s!r}" stepSize="{step_s!r}"/>',
              '  <ModelVariables>']
    for v in variables:
        if v.causality == "parameter":
            attrs, inner = 'variability="fixed" initial="exact"', f'<Real unit={quoteattr(v.unit)} start="{v.start!r}"/>'
        elif v.causality == "input":
            attrs, inner = 'variability="continuous"', f'<Real unit={quoteattr(v.unit)} start="{v.start!r}"/>'
        elif v.type == "Boolean":
            attrs, inner = 'variability="discrete" initial="calculated"', '<Boolean/>'
        else:
            attrs, inner = 'variability="continuous" initial="calculated"', f'<Real unit={quoteattr(v.unit)}/>'
        lines.append(f'    <ScalarVariable name="{v.name}" valueReference="{v.vr}" causality="{v.causality}" '
                     f'{attrs} description={quoteattr(v.description)}>')
        lines.append(f'      {inner}')
        lines.append('    </ScalarVariable>')
    lines.append('  </ModelVariables>')
    outputs = [i + 1 for i, v in enumerate(variables) if v.causality == "output"]
    lines += ['  <ModelStructure>', '    <Outputs>']
    lines += [f'      <Unknown index="{i}" dependencies=""/>' for i in outputs]
    lines += ['    </Outputs>', '    <InitialUnknowns>']
    lines += [f'      <Unknown index="{i}"/>' for i in outputs]
    lines += ['    </InitialUnknowns>', '  </ModelStructure>', '</fmiModelDescription>', '']
    return "\n".join(lines)


def _model_description3(variables, guid, description, stop_time_s, step_s) -> str:
    """FMI 3.0: one value-reference space (fault_active and time follow the reals)."""
    n_real = sum(1 for v in variables if v.type == "Real")
    units = sorted({v.unit for v in variables if v.unit})
    lines = ['<?xml version="1.0" encoding="UTF-8"?>',
             f'<fmiModelDescription fmiVersion="3.0" modelName="{MODEL_IDENTIFIER}" instantiationToken="{guid}"'
             f' description={quoteattr(description)}'
             f' generationTool="{GENERATION_TOOL} (CasADi {ca.__version__})"'
             f' generationDateAndTime="{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%dT%H:%M:%SZ}"'
             ' variableNamingConvention="flat">',
             f'  <CoSimulation modelIdentifier="{MODEL_IDENTIFIER}" canHandleVariableCommunicationStepSize="true"'
             ' canGetAndSetFMUState="false" canSerializeFMUState="false" providesDirectionalDerivatives="false"'
             ' providesAdjointDerivatives="false" hasEventMode="false" providesIntermediateUpdate="false"/>',
             '  <UnitDefinitions>']
    lines += [f'    <Unit name={quoteattr(u)}/>' for u in units]
    lines += ['  </UnitDefinitions>', '  <LogCategories>', '    <Category name="logStatusError"/>',
              '    <Category name="logAll"/>', '  </LogCategories>',
              f'  <DefaultExperiment startTime="0" stopTime="{stop_time_s!r}" stepSize="{step_s!r}"/>',
              '  <ModelVariables>',
              f'    <Float64 name="time" valueReference="{n_real + 1}" causality="independent"'
              ' variability="continuous" unit="s" description="simulation time"/>']
    outputs = []
    for v in variables:
        d = f'description={quoteattr(v.description)}'
        if v.type == "Boolean":
            vr = n_real
            lines.append(f'    <Boolean name="{v.name}" valueReference="{vr}" causality="output" variability="discrete"'
                         f' initial="calculated" {d}/>')
        else:
            vr = v.vr
            attrs = {"parameter": f'variability="fixed" initial="exact" start="{v.start!r}"',
                     "input": f'variability="continuous" start="{v.start!r}"',
                     "output": 'variability="continuous" initial="calculated"'}[v.causality]
            lines.append(f'    <Float64 name="{v.name}" valueReference="{vr}" causality="{v.causality}" {attrs}'
                         f' unit={quoteattr(v.unit)} {d}/>')
        if v.causality == "output":
            outputs.append(vr)
    lines += ['  </ModelVariables>', '  <ModelStructure>']
    lines += [f'    <Output valueReference="{vr}" dependencies=""/>' for vr in outputs]
    lines += [f'    <InitialUnknown valueReference="{vr}"/>' for vr in outputs]
    lines += ['  </ModelStructure>', '</fmiModelDescription>', '']
    return "\n".join(lines)


def _build_description3(sources) -> str:
    files = "\n".join(f'      <SourceFile name="{s}"/>' for s in sources)
    return f"""<?xml version="1.0" encoding="UTF-8"?>
<fmiBuildDescription fmiVersion="3.0">
  <BuildConfiguration modelIdentifier="{MODEL_IDENTIFIER}">
    <SourceFileSet language="C99">
{files}
    </SourceFileSet>
  </BuildConfiguration>
</fmiBuildDescription>
"""


def _spec_header(variables, guid, n_model_params) -> str:
    reals = [v for v in variables if v.type == "Real"]
    vr = {v.name: v.vr for v in variables}
    start = ", ".join(repr(float(v.start)) if v.start is not None else "0.0" for v in reals)
    return f"""/* generated by plant/fmu/export.py: value references and start values of the wheelset FMU */
#ifndef MODEL_SPEC_H
#define MODEL_SPEC_H
#define MODEL_GUID "{guid}"
#define N_MODEL_PARAMS {n_model_params}
#define N_REAL {len(reals)}
#define N_BOOL 1
#define VR_FAULT_TIME {vr['fault_time_s']}
#define VR_H {vr['integration_step_s']}
#define VR_OMEGA0 {vr['initial_motor_speed_rad_s']}
#define VR_V0 {vr['initial_train_speed_ms']}
#define VR_TORQUE {vr['torque_nm']}
#define VR_OMEGA {vr['motor_speed_rad_s']}
#define VR_V {vr['train_speed_ms']}
#define VR_CREEP {vr['creep_speed_kmh']}
#define VR_MU {vr['mu']}
#define VR_LOAD {vr['load_torque_nm']}
#define VR_FAULT_ACTIVE {vr['fault_active']}
#define STEP_FN wheelset_rk4
#define STEP_FN_WORK wheelset_rk4_work
#define OUT_FN wheelset_out
#define OUT_FN_WORK wheelset_out_work
static const double START_VALUES[N_REAL] = {{{start}}};
#endif
"""


def _compiler() -> str:
    cc = os.environ.get("CC") or shutil.which("gcc") or shutil.which("cc")
    if not cc:
        raise FmuExportError("no C compiler found (install gcc or set CC) -- needed to build the FMU binary")
    return cc


def _platform(fmi_version: str) -> tuple[str, str]:
    """(binaries/ folder name, shared library extension) for this machine and FMI version."""
    import fmpy

    ext = {"linux64": ".so", "linux32": ".so", "darwin64": ".dylib", "win64": ".dll", "win32": ".dll"}
    if fmpy.platform not in ext:
        raise FmuExportError(f"cannot build an FMU binary for platform {fmpy.platform!r}")
    return (fmpy.platform if fmi_version == "2" else fmpy.platform_tuple), ext[fmpy.platform]


def export_fmu(cfg: PlantConfig, path, *, n_terms: int | None = None, description: str = "",
               stop_time_s: float = 1.0, fmi_version: str = "2") -> Path:
    """Write an FMI 2.0 (or, ``fmi_version="3"``, 3.0) Co-Simulation FMU of the plant to ``path``;
    start values are ``cfg``'s.

    ``n_terms``: exponential terms per curve the FMU holds (default: as many as ``cfg``'s curves).
    Returns the path.  Raises FmuExportError with one line if it cannot be built.
    """
    import fmpy

    fmi_version = str(fmi_version)[0]
    if fmi_version not in WRAPPERS:
        raise FmuExportError(f"FMI version {fmi_version!r}: only 2 and 3 can be exported")
    path = Path(path)
    _exponential_only(cfg)
    n_terms = n_terms or max(cfg.normal_curve.n_terms, cfg.fault_curve.n_terms)
    values = parameter_values(cfg, n_terms)
    _, torque0 = equilibrium(cfg)
    variables = _variables(values, torque0, n_terms)
    step, out = build_functions(n_terms)
    cc = _compiler()
    platform, ext = _platform(fmi_version)
    c_code_dir = Path(fmpy.__file__).parent / "c-code"

    with tempfile.TemporaryDirectory(prefix="wheelset-fmu-") as tmp:
        tmp = Path(tmp)
        src = tmp / "sources"
        src.mkdir()
        gen = ca.CodeGenerator("wheelset_model.c", {"with_header": True, "casadi_real": "double"})
        gen.add(step)
        gen.add(out)
        gen.generate(str(src) + os.sep)
        wrapper = WRAPPERS[fmi_version].name
        shutil.copy(WRAPPERS[fmi_version], src / wrapper)
        headers = ("fmi2Functions.h", "fmi2FunctionTypes.h", "fmi2TypesPlatform.h") if fmi_version == "2" else \
            ("fmi3Functions.h", "fmi3FunctionTypes.h", "fmi3PlatformTypes.h")
        for header in headers:
            shutil.copy(c_code_dir / header, src / header)
        # the GUID ties modelDescription.xml to the binary: a hash of the generated code and start values
        digest = hashlib.sha256((src / "wheelset_model.c").read_bytes()
                                + repr(sorted(values.items())).encode() + repr(torque0).encode()
                                + fmi_version.encode()).hexdigest()
        guid = "{" + str(uuid.UUID(digest[:32])) + "}"
        (src / "model_spec.h").write_text(_spec_header(variables, guid, len(model_param_names(n_terms))))
        sources = [wrapper, "wheelset_model.c"]
        binary_dir = tmp / "binaries" / platform
        binary_dir.mkdir(parents=True)
        cmd = [cc, "-shared", "-fPIC", "-O2", "-ffp-contract=off", "-fvisibility=hidden", "-I", str(src),
               *(str(src / s) for s in sources), "-o", str(binary_dir / (MODEL_IDENTIFIER + ext)), "-lm"]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            first = (proc.stderr.strip().splitlines() or ["(no output)"])[0]
            raise FmuExportError(f"C compiler failed building the FMU ({' '.join(cmd[:2])} ...): {first}")
        description = description or "railway-hil wheelset-rail plant"
        if fmi_version == "2":
            md = _model_description(variables, guid, description, stop_time_s, cfg.exchange_period_s, sources)
        else:
            md = _model_description3(variables, guid, description, stop_time_s, cfg.exchange_period_s)
            (src / "buildDescription.xml").write_text(_build_description3(sources))
        (tmp / "modelDescription.xml").write_text(md)
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_name(path.name + ".partial")
        with zipfile.ZipFile(partial, "w", zipfile.ZIP_DEFLATED) as z:
            z.write(tmp / "modelDescription.xml", "modelDescription.xml")
            for f in sorted(binary_dir.iterdir()):
                z.write(f, f"binaries/{platform}/{f.name}")
            for f in sorted(src.iterdir()):
                z.write(f, f"sources/{f.name}")
        partial.replace(path)
    return path
