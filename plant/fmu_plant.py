"""Any Co-Simulation FMU as the loop's plant, behind ``WheelsetPlant``'s interface (fmpy underneath).

    plant = FmuPlant("plant.fmu", scenario.plant_config())                # our export: nothing to map
    plant = FmuPlant("Mass_Damper.fmu", cfg, mapping={"torque_nm": "f", "motor_speed_rad_s": "mass.v",
                                                      "train_speed_ms": "y"})

The *mapping* says which FMU variable plays which role (keys: ``ROLES``); unmapped roles default to
the names our own export uses.  ``torque_nm`` must be a Real input; the speeds (and the optional
``mu`` and ``creep_speed_kmh``) Real outputs or locals.  Without a ``creep_speed_kmh`` variable the
creep speed is computed from the two speeds with the scenario's wheel radius and gear ratio; without
``mu`` the true adhesion is unknown (NaN in the log).

FMI 2.0 Co-Simulation goes through fmpy's ``FMU2Slave`` (its raw ctypes calls on preallocated arrays:
one step is a few microseconds); FMI 3.0 Co-Simulation through ``FMU3Slave``.  Model Exchange only
FMUs are refused: the loop needs the FMU to integrate itself.

Loading an FMU runs its native code inside this process: only load FMUs you trust.  Before that, an
FMU is treated as data (``archive_problems``): its ``modelIdentifier`` must be a plain name (the
binary loaded is ``binaries/<platform>/<modelIdentifier>.so`` inside the unpacked FMU, never a path
elsewhere), every archive member must stay inside the folder it is unpacked to, and the unpacked size
is capped (``max_extracted_bytes``); ``extract_fmu`` unpacks only such an archive and counts the bytes
it writes.
"""
from __future__ import annotations

import ctypes
import math
import os
import posixpath
import re
import shutil
import tempfile
import weakref
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .model import PlantConfig, PlantState, creep_speed_kmh, equilibrium

if TYPE_CHECKING:                      # fmpy is imported where an FMU is read, not with this module
    from fmpy.model_description import ModelDescription

#: role -> default FMU variable name (what plant/fmu/export.py writes)
ROLES = {"torque_nm": "torque_nm", "motor_speed_rad_s": "motor_speed_rad_s", "train_speed_ms": "train_speed_ms",
         "mu": "mu", "creep_speed_kmh": "creep_speed_kmh"}
REQUIRED_ROLES = ("torque_nm", "motor_speed_rad_s", "train_speed_ms")
_READABLE = ("output", "local")
_LIST_LIMIT = 40


class FmuError(ValueError):
    """An FMU that cannot serve as the plant; the message is one line naming the file and the problem."""


#: the most an FMU may unpack to, in bytes, unless the environment variable ``MAX_BYTES_ENV`` says otherwise
MAX_EXTRACTED_BYTES = 512 * 1024 ** 2
MAX_BYTES_ENV = "HIL_FMU_MAX_BYTES"
#: the most members an FMU archive may hold
MAX_MEMBERS = 100_000
#: the largest modelDescription.xml read
MAX_MODEL_DESCRIPTION_BYTES = 64 * 1024 ** 2
#: what a modelIdentifier may be: a file-name stem without separators (FMI: a C identifier)
_IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def max_extracted_bytes() -> int:
    """``MAX_EXTRACTED_BYTES``, or the environment's ``HIL_FMU_MAX_BYTES`` (bytes) when set; FmuError
    (one line) when that is not a positive whole number."""
    raw = os.environ.get(MAX_BYTES_ENV)
    if raw is None or raw.strip() == "":
        return MAX_EXTRACTED_BYTES
    try:
        value = int(raw)
    except ValueError:  # not a number: refused below like 0
        value = 0
    if value <= 0:
        raise FmuError(f"{MAX_BYTES_ENV}={raw!r}: must be a positive number of bytes")
    return value


def _member_problem(name: str) -> str | None:
    if "\\" in name or "\0" in name:
        return "holds a backslash or NUL"
    if name.startswith("/") or re.match(r"[A-Za-z]:", name):
        return "is an absolute path"
    norm = posixpath.normpath(name)
    if norm == ".." or norm.startswith("../"):
        return "leaves the FMU's folder"
    return None


def archive_problems(path, md=None) -> list[str]:
    """What makes the zip archive ``path`` unsafe to unpack or load, one short sentence each: member
    paths that are absolute or climb out (``..``), more than ``MAX_MEMBERS`` members, a total unpacked
    size (as the archive declares it) above ``max_extracted_bytes()``, and, given its model description
    ``md``, a ``modelIdentifier`` that is not a plain name.  Reads only the archive's directory."""
    problems = []
    with zipfile.ZipFile(path) as z:
        infos = z.infolist()
    if len(infos) > MAX_MEMBERS:
        problems.append(f"{len(infos)} archive members (at most {MAX_MEMBERS})")
    bad = [(i.filename, why) for i in infos if (why := _member_problem(i.filename))]
    for name, why in bad[:5]:
        problems.append(f"archive member {name[:120]!r} {why}")
    if len(bad) > 5:
        problems.append(f"... and {len(bad) - 5} more such members")
    total, cap = sum(i.file_size for i in infos), max_extracted_bytes()
    if total > cap:
        problems.append(f"unpacks to {total / 1024 ** 2:.0f} MiB, more than the {cap / 1024 ** 2:.0f} MiB allowed "
                        f"({MAX_BYTES_ENV} sets it)")
    if md is not None:
        for kind in ("coSimulation", "modelExchange"):
            ident = getattr(getattr(md, kind, None), "modelIdentifier", None)
            if ident is not None and not _IDENTIFIER.fullmatch(ident):
                problems.append(f"{kind} modelIdentifier {ident[:120]!r} is not a plain name (it names the "
                                "binary to load; a path there would load code from outside the FMU)")
    return problems


def extract_fmu(path, dest=None) -> str:
    """Unpack the FMU ``path`` into ``dest`` (default: a new temporary folder) after
    ``archive_problems`` found nothing, writing at most the declared size of each member and at most
    ``max_extracted_bytes()`` in all; FmuError (one line, the partial folder removed) otherwise."""
    problems = archive_problems(path)
    if problems:
        raise FmuError(f"{path}: refused: {'; '.join(problems)}")
    made = dest is None
    root = Path(tempfile.mkdtemp(prefix="hil-fmu-") if made else dest).resolve()
    budget = max_extracted_bytes()
    try:
        with zipfile.ZipFile(path) as z:
            for info in z.infolist():
                target = (root / posixpath.normpath(info.filename)).resolve()
                if target != root and root not in target.parents:
                    raise FmuError(f"{path}: refused: archive member {info.filename!r} leaves the FMU's folder")
                if info.is_dir():
                    target.mkdir(parents=True, exist_ok=True)
                    continue
                target.parent.mkdir(parents=True, exist_ok=True)
                with z.open(info) as src, open(target, "wb") as dst:
                    left = info.file_size
                    while chunk := src.read(1 << 20):
                        left -= len(chunk)
                        budget -= len(chunk)
                        if left < 0 or budget < 0:
                            raise FmuError(f"{path}: refused: archive member {info.filename!r} unpacks to more "
                                           "than it declares or than the size allowed")
                        dst.write(chunk)
    except FmuError:
        if made:
            shutil.rmtree(root, ignore_errors=True)
        raise
    except (OSError, zipfile.BadZipFile, EOFError, RuntimeError) as e:
        if made:
            shutil.rmtree(root, ignore_errors=True)
        raise FmuError(f"{path}: cannot unpack the FMU: {e}") from None
    return str(root)


def _fmi_version(path, z: zipfile.ZipFile) -> str:
    """The ``fmiVersion`` attribute of the archive's modelDescription.xml root, read before fmpy does
    (fmpy fails on FMI 1.0 with a message about int())."""
    info = z.getinfo("modelDescription.xml")
    if info.file_size > MAX_MODEL_DESCRIPTION_BYTES:
        raise FmuError(f"{path}: modelDescription.xml unpacks to {info.file_size / 1024 ** 2:.0f} MiB "
                       f"(at most {MAX_MODEL_DESCRIPTION_BYTES / 1024 ** 2:.0f} MiB)")
    try:
        with z.open(info) as f:
            for _, element in ET.iterparse(f, events=("start",)):
                return str(element.get("fmiVersion") or "")
    except (ET.ParseError, zipfile.BadZipFile, OSError, EOFError, RuntimeError) as e:
        raise FmuError(f"{path}: unreadable modelDescription.xml: {e}") from None
    return ""


def _real_types(fmi_version: str) -> tuple[str, ...]:
    return ("Real",) if fmi_version.startswith("2") else ("Float64",)


def read_model_description(path) -> "ModelDescription":
    """The model description of the FMI 2.0 or 3.0 FMU ``path`` (a zip archive), or FmuError naming
    what it is instead (missing, a folder, not a zip, no or a huge modelDescription.xml, FMI 1.0)."""
    import fmpy

    path = Path(path)
    if path.is_dir():
        raise FmuError(f"{path}: is a folder; an FMU is a single .fmu file (a zip archive)")
    if not path.exists():
        raise FmuError(f"{path}: no such FMU file")
    if not path.is_file():
        raise FmuError(f"{path}: not a regular file; an FMU is a .fmu file (a zip archive)")
    if not zipfile.is_zipfile(path):
        raise FmuError(f"{path}: not an FMU (not a zip archive)")
    try:
        with zipfile.ZipFile(path) as z:
            if "modelDescription.xml" not in set(z.namelist()):
                raise FmuError(f"{path}: not an FMU (no modelDescription.xml in the archive)")
            version = _fmi_version(path, z)
    except zipfile.BadZipFile as e:
        raise FmuError(f"{path}: not an FMU (broken zip archive: {e})") from None
    if not version.startswith(("2", "3")):
        raise FmuError(f"{path}: FMI {version or '(no version)'} is not supported (need FMI 2.0 or 3.0 "
                       "Co-Simulation)")
    try:
        return fmpy.read_model_description(str(path), validate=False)
    except Exception as e:  # fmpy raises plain Exceptions for XML and schema problems
        raise FmuError(f"{path}: unreadable modelDescription.xml: {str(e).splitlines()[0] if str(e) else e!r}") \
            from None


def read_fmu(path) -> "ModelDescription":
    """Model description of a Co-Simulation FMU with a binary for this platform and nothing
    ``archive_problems`` objects to, or FmuError."""
    import fmpy

    md = read_model_description(path)
    problems = archive_problems(path, md)
    if problems:
        raise FmuError(f"{path}: refused: {'; '.join(problems)}")
    if md.coSimulation is None:
        kinds = [k for k, v in (("Model Exchange", md.modelExchange),
                                ("Scheduled Execution", getattr(md, "scheduledExecution", None))) if v is not None]
        raise FmuError(f"{path}: FMI {md.fmiVersion} {' + '.join(kinds) or 'FMU'} only; the loop needs a "
                       "Co-Simulation FMU (one that integrates itself)")
    platforms = fmpy.supported_platforms(str(path))
    if fmpy.platform not in platforms:
        offered = ", ".join(p for p in platforms if p != "c-code") or "none"
        hint = " (it ships C sources: fmpy.build.build_platform_binary on its unzipped folder can build one)" if "c-code" in platforms \
            else ""
        raise FmuError(f"{path}: no binary for this platform {fmpy.platform} (binaries for: {offered}){hint}")
    return md


def describe_variables(md) -> str:
    """'Real inputs: a, b; Real outputs: c; ...' (the variables a mapping can name)."""
    real = _real_types(md.fmiVersion)
    parts = []
    for causality, label in (("input", "inputs"), ("output", "outputs"), ("local", "locals"),
                             ("parameter", "parameters")):
        names = [v.name for v in md.modelVariables if v.causality == causality and v.type in real]
        if names:
            shown = ", ".join(names[:_LIST_LIMIT]) + (f", ... ({len(names)} in all)" if len(names) > _LIST_LIMIT
                                                      else "")
            parts.append(f"{real[0]} {label}: {shown}")
    return "; ".join(parts) or "no Real variables"


def resolve_mapping(path, md, mapping: dict | None) -> dict[str, object]:
    """role -> ModelVariable (or None for an unmapped optional role); one FmuError naming every problem."""
    mapping = dict(mapping or {})
    unknown_roles = sorted(set(mapping) - set(ROLES))
    if unknown_roles:
        raise FmuError(f"{path}: unknown mapping key(s) {', '.join(unknown_roles)} (known: {', '.join(ROLES)})")
    by_name = {v.name: v for v in md.modelVariables}
    real = _real_types(md.fmiVersion)
    problems, out = [], {}
    for role, default in ROLES.items():
        name = mapping.get(role, default)
        if not isinstance(name, str):
            problems.append(f"{role} -> {name!r} (must be a variable name)")
            continue
        v = by_name.get(name)
        explicit = role in mapping
        if v is None:
            if explicit or role in REQUIRED_ROLES:
                problems.append(f"{role} -> {name!r} (no such variable)")
            out[role] = None
            continue
        want = ("input",) if role == "torque_nm" else _READABLE
        if v.type not in real or v.causality not in want:
            if explicit or role in REQUIRED_ROLES:
                problems.append(f"{role} -> {name!r} (is {v.type} {v.causality}, need {real[0]} "
                                f"{' or '.join(want)})")
            out[role] = None
            continue
        out[role] = v
    if problems:
        raise FmuError(f"{path}: mapping does not fit the FMU: {'; '.join(problems)}. "
                       f"The FMU offers {describe_variables(md)}")
    return out


def _is_ours(md) -> bool:
    from .fmu import GENERATION_TOOL

    return (md.generationTool or "").startswith(GENERATION_TOOL)


def _our_parameters(path, md, cfg: PlantConfig) -> dict[str, float]:
    from .fmu import parameter_values

    n_terms = sum(1 for v in md.modelVariables if v.name.startswith("fault_curve_tau"))
    try:
        return parameter_values(cfg, n_terms)
    except Exception as e:
        raise FmuError(f"{path}: {e}") from None


class FmuPlant:
    """A Co-Simulation FMU stepped once per exchange period; same interface as ``WheelsetPlant``.

    ``cfg``: the scenario's plant configuration (exchange period, fault time, equilibrium torque; and,
    for an FMU exported by this project, every parameter it sets).  ``parameters``: FMU parameter
    name -> value, set after those (for any FMU).
    """

    def __init__(self, path, cfg: PlantConfig, mapping: dict | None = None, parameters: dict | None = None,
                 instance_name: str = "plant"):
        self.path = Path(path)
        self.cfg = cfg
        self.md = md = read_fmu(self.path)
        self.fmi_version = md.fmiVersion[0]
        self.vars = resolve_mapping(self.path, md, mapping)
        self.x0, self.equilibrium_torque_nm = equilibrium(cfg)
        by_name = {v.name: v for v in md.modelVariables}
        params = _our_parameters(self.path, md, cfg) if _is_ours(md) else {}
        for name, value in (parameters or {}).items():
            v = by_name.get(name)
            if v is None or v.type not in _real_types(md.fmiVersion) or v.variability == "constant" \
                    or v.causality not in ("parameter", "input"):
                raise FmuError(f"{self.path}: cannot set parameter {name!r} (no such Real parameter). "
                               f"The FMU offers {describe_variables(md)}")
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise FmuError(f"{self.path}: parameter {name!r} must be a number, got {value!r}")
            params[name] = float(value)
        missing = [n for n in params if n not in by_name]
        if missing:
            raise FmuError(f"{self.path}: exported by {md.generationTool!r} but lacks parameters "
                           f"{', '.join(missing)} (re-export it with `hil fmu export`)")
        self._param_names = list(params)
        self._param_vrs = [by_name[n].valueReference for n in params]
        self._param_values = list(params.values())
        self._unzipdir = extract_fmu(self.path)
        self._finalizer = weakref.finalize(self, shutil.rmtree, self._unzipdir, True)
        self._log: list[str] = []
        self._fmu = None
        self._initialised = False
        out_roles = [r for r in ("motor_speed_rad_s", "train_speed_ms", "mu", "creep_speed_kmh") if self.vars[r]]
        self._out_roles = out_roles
        n = len(out_roles)
        self._vr_in = (ctypes.c_uint * 1)(self.vars["torque_nm"].valueReference)
        self._val_in = (ctypes.c_double * 1)()
        self._vr_out = (ctypes.c_uint * n)(*(self.vars[r].valueReference for r in out_roles))
        self._val_out = (ctypes.c_double * n)()
        # fmi3DoStep's results (eventHandlingNeeded, terminateSimulation, earlyReturn, lastSuccessfulTime)
        self._step3_flags = (ctypes.c_bool(), ctypes.c_bool(), ctypes.c_bool(), ctypes.c_double())
        self._step3_out = tuple(ctypes.byref(x) for x in self._step3_flags)
        self._instantiate(instance_name)
        self.reset()

    # -- FMI plumbing -------------------------------------------------------------------------------
    def _on_log(self, *args):
        message = args[-1]
        self._log.append(message.decode("utf-8", "replace") if isinstance(message, bytes) else str(message))
        del self._log[:-20]

    def _instantiate(self, instance_name: str) -> None:
        from fmpy.fmi2 import (FMU2Slave, calloc, fmi2CallbackAllocateMemoryTYPE, fmi2CallbackFreeMemoryTYPE,
                               fmi2CallbackFunctions, fmi2CallbackLoggerTYPE, free)

        md = self.md
        ident = md.coSimulation.modelIdentifier
        cwd = os.getcwd()   # fmpy chdirs into binaries/ to load and does not come back if loading fails
        try:
            if self.fmi_version == "2":
                self._fmu = FMU2Slave(guid=md.guid, unzipDirectory=self._unzipdir, modelIdentifier=ident,
                                      instanceName=instance_name)
                cb = fmi2CallbackFunctions()
                cb.logger = fmi2CallbackLoggerTYPE(lambda env, inst, status, cat, msg: self._on_log(msg))
                cb.allocateMemory = fmi2CallbackAllocateMemoryTYPE(calloc)
                cb.freeMemory = fmi2CallbackFreeMemoryTYPE(free)
                try:
                    from fmpy.logging import addLoggerProxy
                    addLoggerProxy(ctypes.byref(cb))
                except Exception:  # without the proxy the unformatted message still arrives
                    pass
                self._callbacks = cb
                self._fmu.instantiate(callbacks=cb)
            else:
                from fmpy.fmi3 import FMU3Slave

                self._fmu = FMU3Slave(guid=md.instantiationToken, unzipDirectory=self._unzipdir,
                                      modelIdentifier=ident, instanceName=instance_name)
                self._fmu.instantiate(logMessage=lambda env, status, cat, msg: self._on_log(msg))
        except FmuError:
            raise
        except Exception as e:
            raise FmuError(f"{self.path}: cannot load or instantiate the FMU's binary: {e}"
                           + self._last_log()) from None
        finally:
            os.chdir(cwd)

    def _last_log(self) -> str:
        return f" (FMU says: {self._log[-1]})" if self._log else ""

    def _call(self, what: str, fn, *args):
        try:
            return fn(*args)
        except Exception as e:
            raise FmuError(f"{self.path}: {what} failed at t={self.t_s:.4f} s: {e}{self._last_log()}") from None

    def _initialise(self) -> None:
        f = self._fmu
        if self.fmi_version == "2":
            if self._initialised:
                self._call("fmi2Reset", f.reset)
            self._call("fmi2SetupExperiment", f.setupExperiment, None, 0.0)
            if self._param_vrs:
                self._call("setting parameters", f.setReal, self._param_vrs, self._param_values)
            self._call("setting the torque input", f.setReal, [self._vr_in[0]], [self.equilibrium_torque_nm])
            self._call("fmi2EnterInitializationMode", f.enterInitializationMode)
            self._call("fmi2ExitInitializationMode", f.exitInitializationMode)
        else:
            if self._initialised:
                self._call("fmi3Reset", f.reset)
            if self._param_vrs:
                self._call("setting parameters", f.setFloat64, self._param_vrs, self._param_values)
            self._call("setting the torque input", f.setFloat64, [self._vr_in[0]], [self.equilibrium_torque_nm])
            self._call("fmi3EnterInitializationMode", f.enterInitializationMode, None, 0.0)
            self._call("fmi3ExitInitializationMode", f.exitInitializationMode)
        self._initialised = True

    # -- WheelsetPlant interface ---------------------------------------------------------------------
    @property
    def t_s(self) -> float:
        return self.step_index * self.cfg.exchange_period_s

    def reset(self) -> PlantState:
        self.step_index = 0
        self._initialise()
        self._read_outputs()
        self.x0 = np.array([self._values["motor_speed_rad_s"], self._values["train_speed_ms"]])
        self.state = self._observe(self.equilibrium_torque_nm)
        return self.state

    def step(self, torque_nm: float) -> PlantState:
        t0 = self.t_s
        f = self._fmu
        self._val_in[0] = torque_nm
        try:
            if self.fmi_version == "2":
                f.fmi2SetReal(f.component, self._vr_in, 1, self._val_in)
                f.fmi2DoStep(f.component, t0, self.cfg.exchange_period_s, 1)
            else:
                f.fmi3SetFloat64(f.component, self._vr_in, 1, self._val_in, 1)
                f.fmi3DoStep(f.component, t0, self.cfg.exchange_period_s, True, *self._step3_out)
                if self._step3_flags[1].value or self._step3_flags[2].value:
                    raise RuntimeError("the FMU asked to terminate or returned early")
        except Exception as e:
            raise FloatingPointError(f"{self.path}: FMU step failed at t={t0:.4f} s (torque {torque_nm} N·m): "
                                     f"{e}{self._last_log()}") from None
        self.step_index += 1
        self._read_outputs()
        self.state = self._observe(torque_nm)
        return self.state

    def metadata(self) -> dict[str, str]:
        """What to record about this plant in the MCAP file (metadata record ``plant``)."""
        md = self.md
        return {"kind": f"fmu (FMI {md.fmiVersion} Co-Simulation)", "path": str(self.path),
                "model_name": md.modelName or "", "generation_tool": md.generationTool or "",
                "guid": md.guid or getattr(md, "instantiationToken", "") or "",
                "mapping": {role: v.name for role, v in self.vars.items() if v is not None},
                "parameters": dict(zip((v for v in self._param_names), self._param_values))}

    def close(self) -> None:
        """Terminate and free the FMU instance and delete its unpacked files (idempotent)."""
        f, self._fmu = self._fmu, None
        if f is not None:
            try:
                f.terminate()
            except Exception:  # FMPy raises plain Exception; an FMU in error may refuse: close must go on and free
                pass
            try:
                f.freeInstance()
            except Exception:  # as above: the unpacked files are deleted whatever the FMU says
                pass
        self._finalizer()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- outputs -------------------------------------------------------------------------------------
    def _read_outputs(self) -> None:
        f = self._fmu
        n = len(self._out_roles)
        try:
            if self.fmi_version == "2":
                f.fmi2GetReal(f.component, self._vr_out, n, self._val_out)
            else:
                f.fmi3GetFloat64(f.component, self._vr_out, n, self._val_out, n)
        except Exception as e:
            raise FmuError(f"{self.path}: reading outputs failed at t={self.t_s:.4f} s: {e}{self._last_log()}") \
                from None
        self._values = dict(zip(self._out_roles, self._val_out))

    def _observe(self, torque_nm: float) -> PlantState:
        v = self._values
        omega, v_t = v["motor_speed_rad_s"], v["train_speed_ms"]
        if not (math.isfinite(omega) and math.isfinite(v_t)):
            raise FloatingPointError(f"{self.path}: plant diverged at t={self.t_s:.4f} s (torque {torque_nm} N·m)")
        creep = v["creep_speed_kmh"] if "creep_speed_kmh" in v else float(creep_speed_kmh(self.cfg.params, omega, v_t))
        mu = v.get("mu", math.nan)
        t_s = self.t_s
        return PlantState(t_s, omega, v_t, creep, mu, mu * self.cfg.params.torque_per_mu_nm, float(torque_nm),
                          t_s >= self.cfg.fault_time_s)
