"""The session of a run (``hil.session``): what it takes before the loop is given back when the run
cannot start, on the real resources (a python-can bus, the hub process, idle spinners, SCHED_FIFO,
the CPU latency request, the CPU affinity, the temporary directories, the signal handlers)."""
import os
import signal
import tempfile
from pathlib import Path

import can.interfaces.virtual
import pytest

from hil.testing import children_of, cmdline
from hil.config import load_scenario, parse_set
from hil.errors import BusError
from hil.exchange import run

from .conftest import SCENARIOS


def _state() -> dict:
    """What a run may change in this process and must put back."""
    fds = []
    for fd in Path("/proc/self/fd").iterdir():
        try:
            fds.append(os.readlink(fd))
        except OSError:
            pass
    return {"affinity": os.sched_getaffinity(0), "policy": os.sched_getscheduler(0),
            "priority": os.sched_getparam(0).sched_priority,
            "handlers": (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)),
            "latency_fds": [f for f in fds if f == "/dev/cpu_dma_latency"],
            "children": sorted((pid, cmdline(pid)) for pid in children_of(os.getpid()))}


@pytest.fixture
def private_tmp(tmp_path, monkeypatch):
    """The temporary directories a run makes (TCU report, frame key) go here, where no other run's are."""
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))
    return tmp


def test_a_bus_failing_after_the_hub_started_releases_everything_taken_before_it(tmp_path, private_tmp):
    """Real time with every host setting on, then the hub started and refused (an external TCU cannot be
    on a hub started here): the hub, the spinners, SCHED_FIFO, the latency request, the pinning, the
    directories and the signal handlers are all given back, and no log is left."""
    cpu = sorted(os.sched_getaffinity(0))[0]
    scenario = load_scenario(SCENARIOS / "ffcc_a.toml", parse_set(['bus.idle_spin="on"', "bus.rt_priority=10",
                                                         "bus.cpu_latency_us=0", f"bus.cpu_affinity_plant=[{cpu}]"]))
    before = _state()
    said = []
    with pytest.raises(BusError, match="a hub started here has no external TCU on it"):
        run(scenario, bus="hub", mode="realtime", external_tcu=True, out_dir=tmp_path / "logs", log=said.append,
            progress=False)
    text = "\n".join(said)
    print(text)
    # it did take them (else this test shows nothing) ...
    assert "SCHED_FIFO priority 10" in text and "SCHED_IDLE spinner" in text
    assert "CPU latency request" in text and "cannot pin" not in text
    # ... and gave every one back
    assert _state() == before
    assert list(private_tmp.iterdir()) == []
    assert not list(tmp_path.glob("logs/*.mcap"))


def test_a_bus_only_this_process_reaches_is_closed_when_a_tcu_process_cannot_join_it(tmp_path, private_tmp):
    """Lockstep with a TCU process: pinned to a CPU, the report and key directories made, a python-can
    virtual bus opened, then refused (no second process can join it): all of it given back."""
    scenario = load_scenario(SCENARIOS / "ffcc_a.toml", parse_set(['bus.auth="on"']))   # a key written, then removed
    channel = f"hil-session-test-{os.getpid()}"
    before = _state()
    with pytest.raises(BusError, match=f"bus virtual:{channel}: reachable only inside this process"):
        run(scenario, bus=f"virtual:{channel}", out_dir=tmp_path / "logs", log=print, progress=False)
    assert channel not in can.interfaces.virtual.channels          # the bus was shut down
    assert _state() == before
    assert list(private_tmp.iterdir()) == []
    assert not list(tmp_path.glob("logs/*.mcap"))


def test_an_interrupt_swallowed_before_the_run_takes_nothing(tmp_path, private_tmp):
    """A Ctrl-C that something swallowed before the run (``hil.cli._Interrupts`` remembers it) stops the
    run before it takes anything: no spinner started, no SCHED_FIFO, nothing left to give back."""
    from hil.cli import _Interrupts

    scenario = load_scenario(SCENARIOS / "ffcc_a.toml", parse_set(['bus.idle_spin="on"', "bus.rt_priority=10"]))
    handler = _Interrupts()
    handler.interrupted = True
    old = signal.signal(signal.SIGINT, handler)
    try:
        before = _state()
        said = []
        with pytest.raises(KeyboardInterrupt):
            run(scenario, bus="inprocess", mode="realtime", out_dir=tmp_path / "logs", log=said.append,
                progress=False)
        assert said == []
        assert _state() == before
    finally:
        signal.signal(signal.SIGINT, old)
    assert list(private_tmp.iterdir()) == []
    assert not list(tmp_path.glob("logs/*.mcap"))
