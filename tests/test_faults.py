"""Faults outside the run's control end it in one line with the right exit code and a complete cleanup:
a full disk (a file size limit, RLIMIT_FSIZE, in the child: no tmpfs needed) and the hub killed."""
import os
import random
import resource
import signal
import subprocess
import time
from pathlib import Path

from hil.log.read import read_log

from .conftest import ROOT, case_seed, hil_command, subprocess_env
from .test_bus import alive, children_of, cmdline


def _tcu_processes(seed: int) -> list[int]:
    """TCU processes of a run with this seed still alive anywhere (none may outlive its run)."""
    out = []
    for p in Path("/proc").iterdir():
        if p.name.isdigit():
            c = cmdline(p.name)
            if "hil.tcu_node" in c and f"--seed {seed} " in c:
                out.append(int(p.name))
    return out


def _run_with_file_limit(limit_bytes: int, out: Path, seed: int, bus: str = "local", seconds: float = 10.0):
    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))
    return subprocess.run([*hil_command(), "run", "scenarios/ffcc_a.toml", "--bus", bus, "--seed", str(seed),
                           "--out", str(out), "--set", f"run.duration_s={seconds}",
                           "--set", f"run.fault_time_s={seconds / 2}"],
                          cwd=ROOT, env=subprocess_env(), capture_output=True, text=True, timeout=300,
                          preexec_fn=limit)


def test_a_disk_that_fills_mid_run_ends_it_in_one_line_with_the_tcu_stopped_and_the_log_readable(tmp_path):
    rng = random.Random(case_seed())
    limit = rng.randrange(300_000, 1_500_000)
    seed = rng.randrange(100_000, 1_000_000)
    print(f"file size limit {limit} bytes, seed {seed}")
    r = _run_with_file_limit(limit, tmp_path, seed)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("hil run: error: ") and "cannot write the log" in last and "File too large" in last
    time.sleep(0.5)
    assert _tcu_processes(seed) == []                          # the TCU was stopped
    (log_file,) = tmp_path.glob("*.mcap")
    assert 0 < log_file.stat().st_size <= limit
    log = read_log(log_file)                                  # what reached the disk reads back
    assert log.cut and log.message_count > 0 and log.topic("/plant/state")


def test_a_full_disk_at_the_start_leaves_no_empty_log(tmp_path):
    for bus in ("inprocess", "local"):
        r = _run_with_file_limit(0, tmp_path, 7, bus=bus, seconds=1.0)
        assert r.returncode == 2, r.stderr
        assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) <= 2, r.stderr
        assert r.stderr.strip().splitlines()[-1].startswith("hil run: error: ")
        assert list(tmp_path.iterdir()) == [], bus            # no 0-byte log (nor anything else)


def test_the_hub_killed_mid_run_ends_it_in_one_line_exit_3(tmp_path):
    rng = random.Random(case_seed())
    seed = rng.randrange(100_000, 1_000_000)
    after_s = rng.uniform(0.5, 2.0)
    print(f"seed {seed}, hub killed {after_s:.2f} s into the run")
    proc = subprocess.Popen([*hil_command(), "run", "scenarios/ffcc_a.toml", "--bus", "hub", "--seed", str(seed),
                             "--out", str(tmp_path), "--set", "run.duration_s=60", "--set", "run.fault_time_s=30"],
                            cwd=ROOT, env=subprocess_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        hub, tcu, end = None, None, time.monotonic() + 60
        while time.monotonic() < end and (hub is None or tcu is None):
            for c in children_of(proc.pid):
                hub = c if "can_remote" in cmdline(c) else hub
                tcu = c if "hil.tcu_node" in cmdline(c) else tcu
            time.sleep(0.02)
        assert hub and tcu, "no hub or TCU child appeared"
        time.sleep(after_s)
        os.kill(hub, signal.SIGKILL)
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 3, err
    assert "Traceback" not in err
    last = err.strip().splitlines()[-1]
    assert last.startswith("hil run: error: ") and "log closed" in last
    time.sleep(0.5)
    assert not alive(tcu)
    (log_file,) = tmp_path.glob("*.mcap")
    log = read_log(log_file)
    assert not log.damage and log.ended_early.startswith("fault at step")   # closed properly, after a fault
