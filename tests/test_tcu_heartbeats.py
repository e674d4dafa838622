"""The TCU's heartbeats (``hil.tcu_node.serve``): sent by its loop between frames, and by a backstop
thread while the loop is held by long work, so a busy TCU never looks silent to the plant."""
import random
import subprocess
import sys
import time

import can
import pytest

from hil.bus.frames import TCU_HEARTBEAT_ID, FrameCodec
from hil.bus.localbus import create_channel, remove_channel
from identifier.messages import SensorReading

from .conftest import ROOT, case_seed, subprocess_env

SILENCE_S, HEARTBEAT_S = 0.05, 0.002


@pytest.fixture
def channel():
    path = create_channel()
    yield path
    remove_channel(path)


def _heartbeats(bus, until, stop_after: int | None = None, timeout_s: float = 60.0) -> list[float]:
    """Arrival times of the TCU's heartbeats on ``bus`` until ``until()`` (then what is still queued),
    ``stop_after`` of them or ``timeout_s``."""
    times, end = [], time.monotonic() + timeout_s
    while len(times) < (stop_after or float("inf")):
        done = until() or time.monotonic() > end
        msg = bus.recv(0.0 if done else 0.005)
        if msg is None and done:
            return times
        if msg is not None and msg.arbitration_id == TCU_HEARTBEAT_ID:
            times.append(time.monotonic())
    return times


TCU = """
import sys, time
from hil.config import load_scenario, parse_set
from hil.bus.link import open_bus
from hil.tcu_node import TcuNode, serve
import can
busy_s = float(sys.argv[2])
scenario = load_scenario("scenarios/ffcc_a.toml", parse_set(["bus.auth=off"]))
node = TcuNode(scenario, "nlls", 1)
answer = node.handle
def held(msg, classified=None, send=None):
    out = answer(msg, classified, send)
    print("busy", time.monotonic(), flush=True)
    end = time.perf_counter() + busy_s
    while time.perf_counter() < end:        # pure Python: holds the interpreter, as a fit does
        pass
    print("done", time.monotonic(), flush=True)
    node.finished = True
    return out
node.handle = held
bus = can.Bus(interface="localbus", channel=sys.argv[1])
serve(bus, node, silence_s=%r, heartbeat_period_s=%r, startup_timeout_s=10.0, realtime=True)
bus.shutdown()
""" % (SILENCE_S, HEARTBEAT_S)


def test_heartbeats_keep_coming_while_the_tcu_is_held_by_long_work_and_come_from_its_loop_otherwise(channel):
    """A TCU process answers one sensor frame with work that holds its interpreter for ``busy_s``
    (longer than the silence limit), as a strategy's fit does: its heartbeats still come, never further
    apart than the silence limit.  Idle, its loop sends them every heartbeat period."""
    busy_s = random.Random(case_seed("busy")).uniform(0.15, 0.35)
    print(f"busy {busy_s * 1e3:.0f} ms")
    plant_bus = can.Bus(interface="localbus", channel=channel)
    tcu = subprocess.Popen([sys.executable, "-c", TCU, channel, repr(busy_s)], cwd=ROOT, env=subprocess_env(),
                           stdout=subprocess.PIPE, text=True)
    try:
        first = _heartbeats(plant_bus, lambda: False, stop_after=1, timeout_s=60.0)
        assert first, "no heartbeat from the TCU process"
        start = time.monotonic()
        idle = _heartbeats(plant_bus, lambda: time.monotonic() > start + 0.3)
        plant_bus.send(FrameCodec(1e-3).sensor(SensorReading(0, 100.0, 10.0)))
        rest = _heartbeats(plant_bus, lambda: tcu.poll() is not None)
        out = tcu.communicate(timeout=30)[0]
    finally:
        if tcu.poll() is None:
            tcu.kill()
            tcu.wait()
        plant_bus.shutdown()
    assert tcu.returncode == 0
    marks = dict(line.split() for line in out.split("\n") if line.strip())
    t_busy, t_done = float(marks["busy"]), float(marks["done"])
    # idle: the loop's heartbeats, one per period (give or take the bus's 1 ms timeout granularity)
    gaps = sorted(b - a for a, b in zip(idle, idle[1:]))
    print(f"idle: {len(idle)} heartbeats in 0.3 s, gaps p50 {gaps[len(gaps) // 2] * 1e3:.2f} ms")
    assert len(idle) >= 0.3 / (3 * HEARTBEAT_S)
    # busy: the backstop's, never a silence limit apart
    edges = [t_busy, *(t for t in rest if t_busy <= t <= t_done), t_done]
    longest = max(b - a for a, b in zip(edges, edges[1:]))
    print(f"busy: {len(edges) - 2} heartbeats, longest gap {longest * 1e3:.1f} ms")
    assert longest < SILENCE_S
    assert len(edges) - 2 >= busy_s / SILENCE_S
