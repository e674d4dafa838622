"""The period's account: where each microsecond of an exchange period goes, measured where it is spent.

``hil bench period`` asks for it; a run never does, and then nothing of this module is on the loop's path.
When asked, ``install_plant(node)`` (in the plant's process) and ``install_tcu(node, bus)`` (in the TCU's,
when the environment names a file in ``ACCOUNT_ENV``) replace the bound methods of the parts on those
objects by timing wrappers: ``time.perf_counter_ns`` before and after, the difference added to the part's
slot of the current period in a preallocated ``array('q')``.  The code of the loop is unchanged: the parts
are timed where and as they really run, on the run's own frames.

Times are *exclusive*: a wrapped call inside another (a log row written inside ``sense``, the MAC inside
an encoding, a collection of the garbage collector anywhere) is counted in its own part only, and
subtracted from its caller's.  The wrappers' own cost (``calibrate``: a wrapped call that does nothing
against the bare call, times the wrapped calls of the period) is the part *the account itself*; what no
wrapper covers (the loop's own lines) is ``other``: the period's wall time minus the sum of the rest.

A period is, on the plant, from one ``send_sensor`` to the next; on the TCU, from the return of the
``recv`` that brought one PlantSensor frame to the next one's.  ``recv`` is split by what it did: a call
that returned nothing, or waited (a timeout above zero) before a frame came, is ``wait``; a call with no
timeout that returned a frame is ``receive``.  The frames' *transit* (a send returning in one process to
the ``recv`` that returns the frame in the other: the bus, the kernel, the peer's wake-up or the end of its
current poll) is taken from stamps on ``CLOCK_MONOTONIC`` (``perf_counter_ns`` on Linux), which both
processes share, of the PlantSensor and TorqueCommand frames, matched by their first 8 bytes (the step
counter and more), the first of each.  ``poll``: the plant node's ``poll`` itself, i.e. its pacing (the
sleeps before a real-time period's start) and its glue.
"""
from __future__ import annotations

import gc
import time
from array import array

#: the environment variable that asks a TCU process (``hil.tcu_node``) to keep an account, and names the
#: file (``.npz``) it writes at its end
ACCOUNT_ENV = "HIL_PERIOD_ACCOUNT"

PLANT_PARTS = ("plant step", "sense", "encode", "authenticate", "send", "wait", "receive", "verify", "decode",
               "frame handling", "log append", "log write", "poll", "collector")
TCU_PARTS = ("wait", "receive", "verify", "decode", "observer", "control law", "command", "strategy", "encode",
             "authenticate", "send", "collector")
#: the frames whose sends and receipts are stamped (the transit of the period's two frames)
from .bus.frames import COMMAND_ID, SENSOR_ID  # noqa: E402


class PeriodAccount:
    """Per-period exclusive times of named parts (module docstring), for up to ``capacity`` periods."""

    def __init__(self, parts: tuple[str, ...], capacity: int):
        self.parts = parts
        self.capacity = capacity
        self._p = len(parts)
        self.ns = array("q", bytes(8 * self._p * capacity))
        self.starts = array("q", bytes(8 * capacity))
        self.calls = array("q", bytes(8 * capacity))      # wrapped calls per period (the account's own cost)
        self.k = -1                      # the current period (-1: before the first)
        self._stack = [0]                # per open wrapped call: the time of the calls nested in it
        self.stamps: dict[int, dict[str, array]] = {}     # frame id -> {"sent"|"received": ns of the n-th}
        self._gc_t0 = []
        self.overhead_ns = calibrate(self)

    def index(self, part: str) -> int:
        return self.parts.index(part)

    def begin_period(self, t_ns: int) -> None:
        self.k += 1
        if self.k < self.capacity:
            self.starts[self.k] = t_ns

    def _add(self, i: int, dt: int) -> None:
        k = self.k
        if 0 <= k < self.capacity:
            self.ns[k * self._p + i] += dt
            self.calls[k] += 1

    def stamp(self, msg, what: str, t_ns: int) -> None:
        """The time a frame of a stamped id was sent or received, keyed by its first 8 bytes (the step
        counter and more: the same key in both processes for the same frame)."""
        d = self.stamps.setdefault(msg.arbitration_id, {"sent": array("q"), "sent_key": array("q"),
                                                        "received": array("q"), "received_key": array("q")})
        d[what].append(t_ns)
        d[what + "_key"].append(int.from_bytes(bytes(msg.data[:8]), "little", signed=True))

    def timed(self, fn, part: str):
        """``fn`` with its exclusive time added to ``part`` of the current period."""
        i, stack, clock, add = self.index(part), self._stack, time.perf_counter_ns, self._add

        def wrapper(*args, **kwargs):
            stack.append(0)
            t0 = clock()
            try:
                return fn(*args, **kwargs)
            finally:
                dt = clock() - t0
                nested = stack.pop()
                stack[-1] += dt
                add(i, dt - nested)
        return wrapper

    def wrap(self, obj, attr: str, part: str) -> None:
        setattr(obj, attr, self.timed(getattr(obj, attr), part))

    def wrap_bus(self, bus, period_id: int | None = None, begin_after: bool = False) -> None:
        """``bus.send`` (``send``; the stamped frames' sent times) and ``bus.recv`` (``wait`` or
        ``receive``, see the module docstring; the stamped frames' received times).  ``period_id``: a
        received frame of that id begins a period (``begin_after``: right after its ``recv``)."""
        send, recv = bus.send, bus.recv
        i_send, i_wait, i_recv = self.index("send"), self.index("wait"), self.index("receive")
        stack, clock, add = self._stack, time.perf_counter_ns, self._add

        def timed_send(msg, timeout=None):
            stack.append(0)
            t0 = clock()
            try:
                return send(msg, timeout=timeout)
            finally:
                t1 = clock()
                nested = stack.pop()
                stack[-1] += t1 - t0
                add(i_send, t1 - t0 - nested)
                if msg.arbitration_id in (SENSOR_ID, COMMAND_ID):
                    self.stamp(msg, "sent", t1)

        def timed_recv(timeout=None):
            stack.append(0)
            t0 = clock()
            msg = None
            try:
                msg = recv(timeout=timeout)
                return msg
            finally:
                t1 = clock()
                nested = stack.pop()
                stack[-1] += t1 - t0
                fid = msg.arbitration_id if msg is not None else None
                if fid == period_id and begin_after:
                    self.begin_period(t1)
                add(i_recv if msg is not None and not timeout else i_wait, t1 - t0 - nested)
                if fid in (SENSOR_ID, COMMAND_ID):
                    self.stamp(msg, "received", t1)

        bus.send, bus.recv = timed_send, timed_recv

    def watch_collector(self) -> None:
        """The garbage collector's passes as the part ``collector`` (``gc.callbacks``)."""
        i, stack, clock = self.index("collector"), self._stack, time.perf_counter_ns

        def callback(phase, info):
            if phase == "start":
                self._gc_t0.append(clock())
            elif self._gc_t0:
                dt = clock() - self._gc_t0.pop()
                stack[-1] += dt
                self._add(i, dt)
        self._gc_callback = callback
        gc.callbacks.append(callback)

    def close(self) -> None:
        cb = getattr(self, "_gc_callback", None)
        if cb is not None and cb in gc.callbacks:
            gc.callbacks.remove(cb)

    # -- the figures -----------------------------------------------------------------------------------
    def table(self, skip: int = 10):
        """(periods, parts + ["other"], total): per-period microseconds as numpy arrays, the first ``skip``
        periods (warm-up) and the last (unfinished) left out."""
        import numpy as np

        n = min(self.k, self.capacity - 1)          # periods with an end
        per = np.frombuffer(self.ns, dtype=np.int64).reshape(self.capacity, self._p)[:n].astype(float) / 1e3
        starts = np.frombuffer(self.starts, dtype=np.int64)[:n + 1].astype(float) / 1e3
        total = np.diff(starts)
        own = np.frombuffer(self.calls, dtype=np.int64)[:n].astype(float) * self.overhead_ns / 1e3
        other = total - per.sum(axis=1) - own
        parts = np.column_stack([per, own, other])[skip:]
        return parts, list(self.parts) + ["the account itself", "other"], total[skip:]

    def save(self, path) -> None:
        import numpy as np

        parts, names, total = self.table(skip=0)
        stamps = {f"{kind}_{fid:x}": np.frombuffer(a, dtype=np.int64) for fid, d in self.stamps.items()
                  for kind, a in d.items()}
        np.savez(path, parts=parts, names=np.array(names), total=total, **stamps)


def calibrate(account: PeriodAccount, calls: int = 2000, batches: int = 7) -> float:
    """What one wrapped call adds to its caller's time (ns; the median of ``batches``): the wrapper's own
    lines outside its two clock reads, estimated on a call that does nothing.  The account charges it, times
    the wrapped calls of each period, to the part ``the account itself`` rather than to ``other``."""
    def nothing(x):
        return x
    saved_k, account.k = account.k, 0             # the calibration's calls count in period 0, cleared after
    wrapped = account.timed(nothing, account.parts[0])
    clock, out = time.perf_counter_ns, []
    for _ in range(batches):
        t0 = clock()
        for _ in range(calls):
            nothing(None)
        t1 = clock()
        for _ in range(calls):
            wrapped(None)
        t2 = clock()
        out.append(((t2 - t1) - (t1 - t0)) / calls)
    account.k = saved_k
    for i in range(account._p):
        account.ns[i] = 0
    account.calls[0] = 0
    return max(sorted(out)[batches // 2], 0.0)


def install_plant(node, capacity: int) -> PeriodAccount:
    """An account of the plant node's periods: its rig, codec, bus, recorder and frame handling wrapped."""
    acc = PeriodAccount(PLANT_PARTS, capacity)
    rig, codec = node.rig, node.codec
    acc.wrap(rig.plant, "step", "plant step")
    acc.wrap(rig, "sense", "sense")
    acc.wrap(rig, "demand", "sense")
    for attr in ("sensor", "demand", "plant_heartbeat"):
        acc.wrap(codec, attr, "encode")
    if codec.auth is not None:
        acc.wrap(codec.auth, "protect", "authenticate")
        acc.wrap(codec.auth, "verify", "verify")
    acc.wrap(codec, "classify", "decode")
    acc.wrap(node, "_accept", "frame handling")
    rec = node.rec
    if rec is not None:
        acc.wrap(rec, "row", "log append")
        acc.wrap(rec, "write", "log append")
        acc.wrap(rec, "work", "log write")
    acc.wrap(node, "poll", "poll")
    acc.wrap_bus(node.bus)
    send_sensor = node.send_sensor

    def begin_and_send():
        acc.begin_period(time.perf_counter_ns())
        send_sensor()
    node.send_sensor = begin_and_send
    acc.watch_collector()
    return acc


def install_tcu(node, bus, capacity: int) -> PeriodAccount:
    """An account of a TCU node's periods: its codec, identifier and ``bus`` (the one ``serve`` gets) wrapped."""
    acc = PeriodAccount(TCU_PARTS, capacity)
    codec, ident = node.codec, node.identifier
    for attr in ("command", "status", "sample", "result", "interval", "tcu_heartbeat", "tcu_scenario"):
        acc.wrap(codec, attr, "encode")
    if codec.auth is not None:
        acc.wrap(codec.auth, "protect", "authenticate")
        acc.wrap(codec.auth, "verify", "verify")
    acc.wrap(codec, "classify", "decode")
    acc.wrap(ident.observer, "update", "observer")
    acc.wrap(ident, "command_nm", "control law")
    acc.wrap(ident.controller, "torque_nm", "control law")
    acc.wrap(ident, "command", "command")
    acc.wrap(ident, "work", "strategy")
    acc.wrap(node, "_new_samples", "strategy")
    acc.wrap_bus(bus, period_id=SENSOR_ID, begin_after=True)
    acc.watch_collector()
    return acc

