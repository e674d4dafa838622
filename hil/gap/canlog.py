"""A rig's CAN log as the measured side of a real run (``hil gap RIG.log --model SCENARIO``).

Any file ``can.LogReader`` reads (candump ``.log``, ``.asc``, ``.blf``, ``.csv``, ``.trc``, ``.mf4``)
is decoded through hil/hil.dbc by ``FrameCodec.classify``, the same validation the nodes apply:

* ``PlantSensor``  -> motor and train speed at its step (the plant side's measurement),
* ``TorqueCommand`` -> the torque applied over that step,
* ``TcuStatus``    -> the TCU's creep and mu^ (when ``ObserverValid``),
* ``TcuResult``    -> identification events.

The bus is a trust boundary: a frame that does not decode, has the wrong length, an unknown id or a
non-finite or out-of-range signal is skipped and counted by reason (``RealData.source["skipped"]``);
a second frame for a step already read (a log recorded on two interfaces) is skipped when it repeats
the first and counted as ``conflicting_duplicate`` when it does not.  Sensor steps must form one
consecutive run (and commands, observer readings and results must fall inside it): frames outside the longest consecutive run of steps are skipped and counted
(``out_of_sequence``) as long as they are at most ``MAX_OUT_OF_SEQUENCE`` of the sensor frames; more
than that, or a gap inside the run, is an error naming the first offending frame (its index in the
file and its step).  A file that stops being readable part-way keeps what was read before
(``source["damage"]``).  The exchange period comes from the model scenario (a CAN log carries none).
"""
from __future__ import annotations

from collections import Counter
from pathlib import Path

import can

from ..errors import LogError
from ..bus.frames import COMMAND_ID, RESULT_ID, SENSOR_ID, STATUS_ID, FrameCodec

#: file suffixes read with ``can.LogReader``
CAN_LOG_SUFFIXES = (".log", ".asc", ".blf", ".csv", ".trc", ".mf4")
#: the largest fraction of sensor frames that may lie outside the main consecutive run of steps
MAX_OUT_OF_SEQUENCE = 0.01
WANTED = (SENSOR_ID, COMMAND_ID, STATUS_ID, RESULT_ID)


def _longest_run(steps) -> tuple[int, int]:
    """(first, last) step of the longest run of consecutive integers among ``steps``."""
    s = sorted(set(steps))
    best, start = (s[0], s[0]), s[0]
    for a, b in zip(s, s[1:] + [None]):
        if b != a + 1:
            if a - start > best[1] - best[0]:
                best = (start, a)
            start = b
    return best


def read_can_log(path, period_s: float) -> tuple[dict, dict, dict, list, dict]:
    """(sensor, command, observer, events, source) as ``hil.gap.data.assemble`` takes them."""
    p = Path(path)
    if not p.is_file():
        raise LogError(f"{path}: cannot read: no such file")
    codec = FrameCodec(period_s)
    sensor, command, observer, events = {}, {}, {}, []
    where = {}                # sensor step -> index of its frame in the file
    skipped = Counter()
    n, damage = 0, ""

    def keep(table, k, value, i):
        if k in table:
            skipped["duplicate" if table[k] == value else "conflicting_duplicate"] += 1
            return
        table[k] = value
        if table is sensor:
            where[k] = i

    try:
        with can.LogReader(str(p)) as reader:
            for msg in reader:
                n += 1
                if msg.arbitration_id not in WANTED or msg.is_extended_id:
                    skipped["other_id"] += 1
                    continue
                frame, status = codec.classify(codec.upgrade(msg))
                if frame is None:
                    skipped[f"{hex(msg.arbitration_id)}:{status}"] += 1
                    continue
                v = frame.value
                if msg.arbitration_id == SENSOR_ID:
                    keep(sensor, v.step, (v.motor_speed_rad_s, v.train_speed_ms), n - 1)
                elif msg.arbitration_id == COMMAND_ID:
                    keep(command, v.step, v.torque_nm, n - 1)
                elif msg.arbitration_id == STATUS_ID:
                    st, obs = v
                    if obs is not None:
                        keep(observer, st.step, (obs.creep_speed_kmh, obs.mu_hat), n - 1)
                else:
                    events.append({"step": v.step, "t_s": v.t_s, "kind": v.kind, "correction": v.correction,
                                   "params": list(v.params), "samples": v.samples})
    except Exception as e:  # noqa: BLE001 - a file from another tool: keep what was read, or say what it is
        what = f"{type(e).__name__}: {e}".splitlines()[0][:200]
        if n == 0:
            raise LogError(f"{path}: not a CAN log python-can can read ({what})") from None
        damage = f"unreadable after {n} frames ({what})"
    if not sensor:
        raise LogError(f"{path}: no valid PlantSensor frames (id 0x{SENSOR_ID:X}) among its {n} frames"
                       + (f" (skipped: {dict(skipped)})" if skipped else ""))
    if len(sensor) < 50:
        raise LogError(f"{path}: {len(sensor)} valid PlantSensor frames among its {n} frames; hil gap needs at "
                       f"least 50" + (f" (skipped: {dict(skipped)})" if skipped else ""))
    first, last = _longest_run(sensor)
    outside = sorted((where[k], k) for k in sensor if not first <= k <= last)
    if len(outside) > MAX_OUT_OF_SEQUENCE * len(sensor):
        i, k = outside[0]
        raise LogError(f"{path}: PlantSensor frame #{i} (step {k}) lies outside the consecutive run of steps "
                       f"{first}-{last}, as do {len(outside) - 1} more; hil gap needs one run of consecutive steps")
    for _, k in outside:
        del sensor[k]
        skipped["out_of_sequence"] += 1
    # commands, observer readings and results must fall in the sensor run too (a garbage frame that
    # decodes with a wild step is counted here rather than used)
    for table in (command, observer):
        for k in [k for k in table if not first <= k <= last]:
            del table[k]
            skipped["out_of_sequence"] += 1
    kept = [e for e in events if first <= e["step"] <= last]
    skipped["out_of_sequence"] += len(events) - len(kept)
    events = sorted(kept, key=lambda e: e["t_s"])
    for e in events:
        del e["step"]
    if not skipped["out_of_sequence"]:
        del skipped["out_of_sequence"]
    source = {"format": "can-log", "frames": n, "skipped": dict(skipped), "skipped_total": sum(skipped.values()),
              "damage": damage}
    return sensor, command, observer, events, source
