"""hil sweep on a real local Dask cluster of 2 workers: the same rows as a serial run, a SIGKILLed worker
costs nothing but a rerun, --resume after Ctrl-C runs only the missing points, a bad axis is one line
before anything runs.  Seeds are drawn at test time and printed."""
import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pandas as pd
import psutil
import pytest

from hil.cli import main
from hil.sweep.driver import run_sweep
from hil.sweep.spec import load_sweep
from hil.sweep.table import TOL_PEAK_CREEP_PERCENT, TOL_PEAK_MU_PERCENT, comparable

from .conftest import ROOT, case_seed

BASE = ROOT / "scenarios" / "ffcc_a.toml"


def sweep_file(tmp_path, axes: str, name="t", extra="") -> Path:
    p = tmp_path / f"{name}.toml"
    p.write_text(f'name = "{name}"\nbase = "{BASE}"\n{extra}\n[set]\n"run.duration_s" = 0.8\n\n{axes}\n')
    return p


def drawn_seeds(n: int, where: str) -> list[int]:
    seed = case_seed(f"{where}: master seed of the run seeds")
    rng = random.Random(seed)
    return [rng.randrange(1, 2 ** 31) for _ in range(n)]


def eight_points(tmp_path, name="eight"):
    seeds = drawn_seeds(4, name)
    axes = (f'[axes."run.mu_required"]\nvalues = [0.158, 0.162]\n\n[axes.seed]\nvalues = {json.dumps(seeds)}\n')
    return sweep_file(tmp_path, axes, name)


def test_the_tolerances_are_the_judges():
    from hil.benchmarks import judge

    assert (TOL_PEAK_MU_PERCENT, TOL_PEAK_CREEP_PERCENT) == (judge.TOL_PEAK_MU_PERCENT, judge.TOL_PEAK_CREEP_PERCENT)


@pytest.mark.parametrize("axis,expect", [
    ('[axes."run.no_such_field"]\nvalues = [1.0]', "run.no_such_field"),
    ('[axes."run.mu_required"]\nvalues = [0.16, "high"]', "must be a number"),
    ('[axes."vehicle.gear_ratio"]\nuniform = [1, 3]\ndraws = 2', "seed"),
    ('[axes.strategy]\nvalues = ["nlls", "psychic"]', "psychic"),
    ('[axes.reality]\nvalues = ["no_such_effect:x=1"]', "no_such_effect"),
])
def test_a_bad_axis_is_one_line_before_anything_runs(tmp_path, capsys, axis, expect):
    path = sweep_file(tmp_path, axis, "bad")
    out = tmp_path / "out"
    code = main(["sweep", str(path), "--out", str(out), "--workers", "0"])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("hil sweep: error:"), err
    assert expect in lines[0] and str(path) in lines[0], lines[0]
    assert not out.exists()        # nothing ran, nothing was written


def test_eight_points_on_two_workers_equal_the_serial_run(tmp_path):
    sweep = load_sweep(eight_points(tmp_path))
    assert len(sweep.points) == 8
    serial = run_sweep(sweep, tmp_path / "serial", workers=0, progress=False)
    dask = run_sweep(sweep, tmp_path / "dask", workers=2, progress=False)
    assert serial["rows"] == dask["rows"] == 8 and dask["failed"] == 0
    a = pd.read_parquet(tmp_path / "serial" / "table")
    b = pd.read_parquet(tmp_path / "dask" / "table")
    assert b["worker"].nunique() == 2                       # both workers ran points
    pd.testing.assert_frame_equal(comparable(a), comparable(b))
    assert (tmp_path / "dask" / "summary.md").read_text().count("| 0.158 |") == 1
    assert (tmp_path / "dask" / "sweep-run.mu_required.png").stat().st_size > 1000


def _worker_pids(parent: psutil.Process) -> list[psutil.Process]:
    return [p for p in parent.children(recursive=True)
            if any("spawn_main" in part for part in p.cmdline()) and "resource_tracker" not in " ".join(p.cmdline())]


def test_a_worker_sigkilled_mid_sweep_costs_only_a_rerun(tmp_path):
    seeds = drawn_seeds(10, "killed worker")
    path = sweep_file(tmp_path, f"[axes.seed]\nvalues = {json.dumps(seeds)}\n", "killed")
    sweep = load_sweep(path)
    table = tmp_path / "out" / "table"
    killed = []

    def killer():
        """SIGKILL a worker process of this test's cluster that has written a row (found by the port in its
        address), once two rows are written: the rows then come from at least two addresses, whichever
        worker started first."""
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            time.sleep(0.05)
            if len(list(table.glob("part-*.parquet"))) < 2:
                continue
            try:
                ports = {int(a.rsplit(":", 1)[1]) for a in pd.read_parquet(table)["worker"].dropna()}
            except Exception:  # noqa: BLE001 - a part being written: read again
                continue
            for w in _worker_pids(psutil.Process()):
                if ports & {c.laddr.port for c in w.net_connections("tcp") if c.status == "LISTEN"}:
                    os.kill(w.pid, signal.SIGKILL)
                    killed.append(w.pid)
                    return

    t = threading.Thread(target=killer, daemon=True)
    t.start()
    doc = run_sweep(sweep, tmp_path / "out", workers=2, progress=False)
    t.join(5)
    assert killed, "no worker found to kill"
    df = pd.read_parquet(table)
    assert doc["rows"] == 10 and sorted(df["point"]) == list(range(10)) and df["error"].isna().all()
    assert df["worker"].nunique() >= 2
    assert set(df["seed"]) == set(seeds)


def test_resume_after_ctrl_c_runs_only_the_missing_points(tmp_path):
    seeds = drawn_seeds(8, "resume")
    path = sweep_file(tmp_path, f"[axes.seed]\nvalues = {json.dumps(seeds)}\n", "resume")
    out = tmp_path / "out"
    table = out / "table"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "hil.cli", "sweep", str(path), "--workers", "2", "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT)
    try:
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline and len(list(table.glob("part-*.parquet"))) < 2 and proc.poll() is None:
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, err
    assert "interrupted" in err
    done_before = len(list(table.glob("part-*.parquet")))
    assert 2 <= done_before < 8, err
    doc = run_sweep(load_sweep(path), out, workers=2, resume=True, progress=False)
    assert doc["skipped"] == done_before and doc["ran_now"] == 8 - done_before
    df = pd.read_parquet(table)
    assert sorted(df["point"]) == list(range(8)) and df["error"].isna().all()
    with pytest.raises(Exception, match="--resume"):      # without --resume the finished table is not touched
        run_sweep(load_sweep(path), out, workers=0, progress=False)


def test_a_failing_point_is_a_row_and_the_sweep_goes_on(tmp_path):
    # fault_time 0.7 is fine; 0.9 is after duration_s 0.8: each value passes alone, the combination does not
    path = sweep_file(tmp_path, '[axes."run.fault_time_s"]\nvalues = [0.5, 0.9]\n', "fails")
    with pytest.raises(Exception, match="duration_s"):
        load_sweep(path)      # a value the base (with [set]) refuses is refused before anything runs
    path = sweep_file(tmp_path, '[axes."run.fault_time_s"]\nvalues = [0.5, 0.9]\n\n[axes."run.duration_s"]\n'
                      'values = [0.8, 1.0]\n', "fails2").read_text().replace('"run.duration_s" = 0.8\n', "")
    p = tmp_path / "fails2.toml"
    p.write_text(path)
    doc = run_sweep(load_sweep(p), tmp_path / "out", workers=0, progress=False)
    df = pd.read_parquet(tmp_path / "out" / "table")
    assert doc["rows"] == 4 and doc["failed"] == 1
    bad = df[df["error"].notna()]
    assert list(bad["in.run.fault_time_s"]) == [0.9] and "duration_s" in bad["error"].iloc[0]


def test_bench_identify_on_two_workers_gives_the_serial_verdicts(capsys):
    seed = case_seed("bench identify draws") % (1 << 30) + 1
    args = ["bench", "identify", "--family", "default", "--draws", "3", "--seed", str(seed), "--strategies", "nlls",
            "--oracle-draws", "50", "--json"]
    assert main(args) == 0
    serial = json.loads(capsys.readouterr().out)
    assert main(args + ["--workers", "2"]) == 0
    dask = json.loads(capsys.readouterr().out)

    def strip(x):       # the cost per sample is a timing
        if isinstance(x, dict):
            return {k: strip(v) for k, v in x.items() if "cost" not in k}
        return [strip(v) for v in x] if isinstance(x, list) else x

    assert strip(serial) == strip(dask)
    # the --cases mode (Table 3: the paper's curves, fixed seeds): the same summaries on 2 workers
    args = ["bench", "identify", "--cases", "ffcc_a", "--seeds", "2", "--first-seed", str(seed % 1000 + 1),
            "--strategies", "proposed", "--oracle-draws", "50", "--json"]
    assert main(args) == 0
    serial = json.loads(capsys.readouterr().out)
    assert main(args + ["--workers", "2"]) == 0
    assert strip(serial) == strip(json.loads(capsys.readouterr().out))
