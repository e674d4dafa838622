"""Part ``fmus``: broken FMUs made from our exported one (``broken_fmu``) through
``hil.plants.make_plant``: each refused in one line, nothing loaded or unpacked outside.
"""
from __future__ import annotations

import collections
import os
import random
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

from ...testing import SCENARIOS, files_under, rezip
from .probe import Part

FMU_KINDS = ("ident_abs", "ident_rel", "member_escape", "zip_bomb", "not_zip", "folder", "fmi1", "no_binary",
             "me_only", "garbage_binary", "other_guid", "liar")


def broken_fmu(kind: str, good: Path, dest: Path, rng: random.Random, marker_lib: Path | None) -> tuple[Path, str]:
    """A broken copy of ``good`` of the given kind at ``dest``: (its path, what it is)."""
    import fmpy

    ident = fmpy.read_model_description(str(good)).coSimulation.modelIdentifier
    if kind in ("ident_abs", "ident_rel"):
        evil = str(marker_lib.with_suffix("")) if kind == "ident_abs" else "../" * rng.randint(1, 6) + "evil"
        return rezip(good, dest, edit_md=lambda md: md.replace(f'modelIdentifier="{ident}"',
                                                                f'modelIdentifier="{evil}"')), f"modelIdentifier {evil}"
    if kind == "member_escape":
        member = rng.choice(["../", "../../escaped/", "/abs/", "resources/../../", "binaries/../../../",
                             "a/b/../../../"]) + f"x{rng.randrange(1000)}"
        shutil.copy(good, dest)
        with zipfile.ZipFile(dest, "a") as z:
            z.writestr(member, b"written outside")
        return dest, f"archive member {member}"
    if kind == "zip_bomb":
        shutil.copy(good, dest)
        zeros = bytes(1 << 20)
        n = rng.randint(3, 4)
        with zipfile.ZipFile(dest, "a", zipfile.ZIP_DEFLATED) as z:
            for i in range(n):
                with z.open(f"resources/zeros{i}", "w", force_zip64=True) as f:
                    for _ in range(200):
                        f.write(zeros)
        return dest, f"{n} x 200 MiB of zeros ({dest.stat().st_size // 1024} KiB archive)"
    if kind == "not_zip":
        dest.write_bytes(rng.choice([b"not a zip", b"PK\x03\x04 broken", rng.randbytes(rng.randint(1, 4096))]))
        return dest, "not a zip"
    if kind == "folder":
        dest.mkdir()
        return dest, "a folder"
    if kind == "fmi1":
        return rezip(good, dest, edit_md=lambda md: md.replace('fmiVersion="2.0"', 'fmiVersion="1.0"')), "FMI 1.0"
    if kind == "no_binary":
        return rezip(good, dest, drop_prefix=f"binaries/{fmpy.platform}/"), "no binary for this platform"
    if kind == "me_only":
        return rezip(good, dest, edit_md=lambda md: md.replace("<CoSimulation ", "<ModelExchange ").replace(
            "</CoSimulation>", "</ModelExchange>")), "Model Exchange only"
    if kind == "garbage_binary":
        return rezip(good, dest, edit_binary=lambda b: b"\x7fELF" + rng.randbytes(rng.randint(0, 4096))), \
            "a binary that is not a shared library"
    if kind == "other_guid":
        return rezip(good, dest, edit_md=lambda md: md.replace('guid="{', 'guid="{0')), "another export's GUID"
    if kind == "liar":
        shutil.copy(good, dest)
        with zipfile.ZipFile(dest, "a", zipfile.ZIP_DEFLATED) as z:
            z.writestr("resources/lie", bytes(rng.randint(2048, 65536)))
        data = bytearray(dest.read_bytes())
        cd = data.rfind(b"PK\x01\x02")
        data[cd + 24:cd + 28] = (16).to_bytes(4, "little")          # declared size 16 B
        dest.write_bytes(bytes(data))
        return dest, "a member that inflates to more than it declares"
    raise ValueError(kind)


def part_fmus(seed: int, count: int, log) -> dict:
    from ...config import load_scenario
    from ...errors import PlantError
    from ...plants import make_plant

    part = Part("fmus", seed, f"{count} broken FMUs through make_plant: each refused in one line, 0 loads from "
                "outside the FMU, nothing unpacked outside a temporary folder that is removed")
    rng = random.Random(f"{seed}:fmus")
    if shutil.which("gcc") is None:
        part.figures["skipped"] = "no gcc: cannot export an FMU"
        return part.done(passed=False)
    from plant.fmu import export_fmu

    by_kind = collections.Counter()
    loads_outside = 0
    left_behind = 0
    with tempfile.TemporaryDirectory(prefix="hil-robust-fmus-") as tmp:
        tmp = Path(tmp)
        sc = load_scenario(SCENARIOS / "ffcc_a.toml")
        log("bench robustness: fmus: exporting our FMU (gcc)")
        good = export_fmu(sc.plant_config(), tmp / "good" / "wheelset.fmu", stop_time_s=sc.run.duration_s)
        evil = tmp / "evil"
        evil.mkdir()
        marker = evil / "loaded"
        (evil / "evil.c").write_text('#include <stdio.h>\n__attribute__((constructor)) static void hit(void) '
                                     f'{{ FILE *f = fopen("{marker}", "w"); if (f) fclose(f); }}\n')
        subprocess.run(["gcc", "-shared", "-fPIC", "-o", str(evil / "evil.so"), str(evil / "evil.c")], check=True)
        # the probe has teeth: loading the library does leave the marker (checked in another process)
        subprocess.run([sys.executable, "-c", f"import ctypes; ctypes.CDLL({str(evil / 'evil.so')!r})"], check=True)
        marker_works = marker.exists()
        if marker_works:
            marker.unlink()
        else:
            part.fail("-", "marker library", "loading the marker library left no marker: the probe cannot see a load")
        unpack = tmp / "tmp"
        unpack.mkdir()
        cases = tmp / "cases"
        cases.mkdir()
        old_tempdir, old_env = tempfile.tempdir, os.environ.get("TMPDIR")
        tempfile.tempdir = str(unpack)
        os.environ["TMPDIR"] = str(unpack)
        bomb = None
        said: dict = {}
        try:
            for i in range(count):
                kind = FMU_KINDS[i % len(FMU_KINDS)] if i < len(FMU_KINDS) else rng.choice(FMU_KINDS)
                d = cases / str(i)
                d.mkdir()
                if kind == "zip_bomb" and bomb is not None:        # made once: it takes seconds
                    path, what = bomb
                else:
                    path, what = broken_fmu(kind, good, d / f"{kind}.fmu", rng, evil / "evil.so")
                    if kind == "zip_bomb":
                        bomb = (path, what)
                by_kind[kind] += 1
                part.cases += 1
                before = files_under(tmp)
                what = f"{kind}: {what}"
                try:
                    plant = make_plant(sc, f"fmu:{path}")
                except PlantError as e:
                    msg = str(e)
                    said.setdefault(kind, msg.replace(str(tmp), "$TMP")[:240])
                    if "\n" in msg or not msg:
                        part.fail(i, what, f"refused, but not in one line: {msg!r}")
                except Exception as e:  # noqa: BLE001 - the point of the probe
                    part.fail(i, what, f"{type(e).__name__} instead of a PlantError: {e}")
                else:
                    plant.close()
                    part.fail(i, what, "loaded")
                import gc
                gc.collect()             # an FmuPlant that failed after unpacking removes its folder when collected
                if marker.exists():
                    loads_outside += 1
                    part.fail(i, what, "the library outside the FMU was loaded")
                    marker.unlink()
                new = sorted(files_under(tmp) - before)
                if new:
                    left_behind += 1
                    part.fail(i, what, f"files left after the refusal: {new[:5]}")
        finally:
            tempfile.tempdir = old_tempdir
            if old_env is None:
                os.environ.pop("TMPDIR", None)
            else:
                os.environ["TMPDIR"] = old_env
    part.figures = {"broken_fmus": count, "by_kind": dict(by_kind), "refused": count - sum(
        1 for f in part.failures if f["detail"] == "loaded"), "loads_from_outside": loads_outside,
        "cases_leaving_files": left_behind, "marker_library_loads_when_loaded": marker_works, "refusals": said}
    return part.done()
