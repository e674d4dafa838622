"""The kernels' first compile is shown in the foreground (``identifier.kernel_cache``, ``hil run``), never
spent unseen inside the TCU process the plant waits for; later runs skip it."""
import json
import subprocess
import sys

from identifier import kernel_cache

from .conftest import ROOT, SCENARIOS


def test_the_stamp_says_fresh_only_for_this_source_and_machine(tmp_path, monkeypatch):
    monkeypatch.setattr(kernel_cache, "STAMP", tmp_path / "__pycache__" / "kernels-compiled.json")
    assert not kernel_cache.fresh()                       # no stamp
    kernel_cache.mark()
    assert kernel_cache.fresh()
    stamp = json.loads(kernel_cache.STAMP.read_text())
    assert stamp["source_sha256"] and stamp["numba"] and stamp["python"]
    for key, other in (("source_sha256", "0" * 64), ("numba", "0.0.1"), ("cpu", "another CPU")):
        kernel_cache.STAMP.write_text(json.dumps({**stamp, key: other}))
        assert not kernel_cache.fresh(), key
    kernel_cache.STAMP.write_text("not json")
    assert not kernel_cache.fresh()


def test_hil_run_compiles_in_the_foreground_once(tmp_path):
    """Without the stamp, ``hil run`` says it compiles (loading numba's cache here, so it is quick) and
    leaves the stamp; the next run says nothing of it."""
    def hil_run():
        return subprocess.run([sys.executable, "-m", "hil.cli", "run", str(SCENARIOS / "ffcc_a.toml"), "--out",
                               str(tmp_path), "--no-rrd", "--set", "run.duration_s=0.6", "--bus", "inprocess"],
                              capture_output=True, text=True, cwd=ROOT, timeout=900)

    kernel_cache.STAMP.unlink(missing_ok=True)
    first = hil_run()
    assert first.returncode == 0, first.stderr
    assert "hil run: compiling the identifier's kernels" in first.stderr and "kernels compiled in" in first.stderr
    assert kernel_cache.fresh()
    second = hil_run()
    assert second.returncode == 0, second.stderr
    assert "compiling" not in second.stderr, second.stderr
