"""Part ``disk``: ``hil run`` on a disk that fills mid-run (a file size limit, a small tmpfs) and
with a limit of 0: exit 2 in one line, the TCU stopped, the log readable up to the limit.
"""
from __future__ import annotations

import os
import random
import resource
import subprocess
import tempfile
import time
from pathlib import Path

from ...testing import ROOT, SCENARIOS, cmdline, files_under, first_traceback, hil_cmd, last_line, subprocess_env
from .probe import RUN_TIMEOUT_S, Part


def _limited(limit_bytes: int):
    def apply():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))
    return apply


def _tcus_of(seed: int) -> list[int]:
    return [int(p.name) for p in Path("/proc").iterdir() if p.name.isdigit()
            and "hil.tcu_node" in (c := cmdline(int(p.name))) and f"--seed {seed} " in c]


def _mount_tmpfs(path: Path, size_bytes: int) -> str | None:
    """A tmpfs of ``size_bytes`` mounted at ``path`` (made here); None, or why it could not be."""
    path.mkdir(parents=True, exist_ok=True)
    try:
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_bytes},mode=0700", "tmpfs", str(path)],
                           capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as e:
        return f"mount: {e}"
    return None if r.returncode == 0 else (r.stderr.strip() or f"mount exit {r.returncode}")[:200]


def _unmount(path: Path) -> None:
    subprocess.run(["umount", str(path)], capture_output=True, timeout=30)


def part_disk(seed: int, count: int, log) -> dict:
    from ...log.read import read_log

    part = Part("disk", seed, f"a full disk mid-run: {count} file size limits (RLIMIT_FSIZE) and {count} small tmpfs "
                "(where mounting is allowed), and a limit of 0: exit 2 in one line, the TCU stopped, the log readable "
                "up to the limit, no empty log")
    rng = random.Random(f"{seed}:disk")
    runs = []
    with tempfile.TemporaryDirectory(prefix="hil-robust-disk-") as tmp:
        cases = [("fsize", "local", rng.randrange(300_000, 1_500_000), 10.0) for _ in range(count)]
        cases += [("fsize", "inprocess", 0, 1.0), ("fsize", "local", 0, 1.0)]
        cases += [("tmpfs", "local", rng.randrange(300_000, 1_500_000), 10.0) for _ in range(count)]
        tmpfs_refused = None
        for i, (kind, bus, limit, seconds) in enumerate(cases):
            run_seed = rng.randrange(100_000, 1_000_000)
            mount = Path(tmp) / f"tmpfs{i}"
            out = mount / "out" if kind == "tmpfs" else Path(tmp) / str(i)
            if kind == "tmpfs":
                if tmpfs_refused:             # refused once: not tried again
                    continue
                tmpfs_refused = _mount_tmpfs(mount, limit)
                if tmpfs_refused:
                    log(f"bench robustness: disk: no tmpfs here ({tmpfs_refused}); only file size limits")
                    continue
                st = os.statvfs(mount)
                limit = st.f_blocks * st.f_frsize         # what the kernel made of it (whole pages)
            log(f"bench robustness: disk: case {i}: {bus}, {'tmpfs of' if kind == 'tmpfs' else 'file size limit'} "
                f"{limit} bytes (seed {run_seed})")
            try:
                r = subprocess.run(hil_cmd("run", SCENARIOS / "ffcc_a.toml", "--bus", bus, "--seed", run_seed, "--out",
                                           out, "--no-rrd", "--set", f"run.duration_s={seconds}",
                                           "--set", f"run.fault_time_s={seconds / 2}"),
                                   cwd=ROOT, env=subprocess_env(), capture_output=True, text=True,
                                   timeout=RUN_TIMEOUT_S, preexec_fn=_limited(limit) if kind == "fsize" else None)
                time.sleep(0.5)
                part.cases += 1
                runs.append(_judge_disk_run(part, i, kind, bus, limit, run_seed, out, r, read_log))
            finally:
                if kind == "tmpfs":
                    _unmount(mount)
    part.figures = {"runs": runs, "tmpfs_refused": tmpfs_refused}
    return part.done()


def _judge_disk_run(part, i, kind, bus, limit, run_seed, out, r, read_log) -> dict:
    what = f"{bus}, {'tmpfs' if kind == 'tmpfs' else 'limit'} {limit} bytes, run seed {run_seed}"
    last = last_line(r.stderr)
    logs = sorted(out.glob("*.mcap")) if out.exists() else []
    rec = {"kind": kind, "bus": bus, "limit": limit, "seed": run_seed, "exit": r.returncode, "last_line": last[:200],
           "log_bytes": logs[0].stat().st_size if logs else None, "tcu_left": bool(_tcus_of(run_seed))}
    if r.returncode != 2 or not last.startswith("hil run: error: "):
        part.fail(i, what, f"exit {r.returncode}: {last}")
    if "Traceback" in r.stderr:
        part.fail(i, what, f"a traceback on stderr: {first_traceback(r.stderr)}")
    if rec["tcu_left"]:
        part.fail(i, what, "the TCU process outlived its run")
    if limit == 0:
        left = files_under(out) if out.exists() else set()
        rec["files_left"] = sorted(left)
        if left:
            part.fail(i, what, f"files left: {sorted(left)}")
        return rec
    if "cannot write the log" not in last:
        part.fail(i, what, f"the last line does not say the log could not be written: {last}")
    if len(logs) != 1 or not 0 < logs[0].stat().st_size <= limit:
        part.fail(i, what, f"logs {[(p.name, p.stat().st_size) for p in logs]}")
    else:
        got = read_log(logs[0])
        rec.update(messages=got.message_count, cut=got.cut)
        if not (got.cut and got.message_count > 0 and got.topic("/plant/state")):
            part.fail(i, what, f"the log is not readable up to the limit: {got.problem()}")
    return rec
