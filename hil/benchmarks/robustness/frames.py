"""Part ``frames``: a third node on the run's localbus channel sending malformed, forged and replayed
frames; every frame accounted for at each receiver (module docstring of ``hil.benchmarks.robustness``).
"""
from __future__ import annotations

import collections
import json
import random
import struct
import subprocess
import tempfile
import time
from pathlib import Path

from ...testing import ROOT, SCENARIOS, children_of, cmdline, hil_cmd, last_line, stop, subprocess_env
from .probe import RUN_TIMEOUT_S, Part

IDENT_KEYS = ("identified", "t_identified_s", "corrections", "params", "samples", "r2", "peak_mu_err_percent")


FRAME_RUN = ("--set", "run.duration_s=3", "--set", "run.fault_time_s=2.5")


def _float_signals(db):
    """(frame id, byte offset, name) of every 64-bit float signal but JEf (allowed non-finite)."""
    out = []
    for m in db.messages:
        for s in m.signals:
            if s.is_float and s.length == 64 and s.name != "JEf":
                out.append((m.frame_id, s.start // 8, s.name))
    return out


def garbage_frame(rng: random.Random, codec, authenticated: bool):
    """One malformed frame a receiver must reject whatever the authentication: (kind, can.Message).
    With ``authenticated``, also frames of a right id and length whose bytes are random (a MAC that
    cannot verify); without, such a frame could decode, so it is never drawn."""
    import can

    from ...bus.frames import INTERVAL_ID, RESULT_ID, SAMPLE_ID, SENSOR_ID, STATUS_ID
    from identifier.messages import SensorReading, TorqueCommand

    known = {m.frame_id: m.length for m in codec.db.messages}
    kinds = ["unknown_id", "extended_id", "bad_length", "remote", "error", "non_finite", "out_of_range"]
    if authenticated:
        kinds.append("random_payload")
    kind = rng.choice(kinds)
    fd = dict(is_fd=True, bitrate_switch=rng.random() < 0.5)
    if kind == "unknown_id":
        fid = rng.randrange(0x800)
        while fid in known:
            fid = rng.randrange(0x800)
        return kind, can.Message(arbitration_id=fid, data=rng.randbytes(rng.randint(0, 64)), is_extended_id=False, **fd)
    if kind == "extended_id":
        fid = rng.choice([rng.randrange(1 << 29), *known])
        return kind, can.Message(arbitration_id=fid, data=rng.randbytes(rng.randint(0, 64)), is_extended_id=True, **fd)
    if kind == "bad_length":
        fid = rng.choice(list(known))
        n = rng.choice([x for x in range(65) if x != known[fid]])
        return kind, can.Message(arbitration_id=fid, data=rng.randbytes(n), is_extended_id=False, **fd)
    if kind == "remote":
        fid = rng.choice(list(known))
        return kind, can.Message(arbitration_id=fid, is_remote_frame=True, is_extended_id=False, dlc=known[fid],
                                 data=b"", check=False)
    if kind == "error":
        return kind, can.Message(arbitration_id=rng.choice([*known, rng.randrange(0x800)]), is_error_frame=True,
                                 data=rng.randbytes(rng.randint(0, 8)), is_extended_id=False, check=False)
    if kind == "random_payload":
        fid = rng.choice(list(known))
        return kind, can.Message(arbitration_id=fid, data=rng.randbytes(known[fid]), is_extended_id=False, **fd)
    # a well-formed frame with one signal made non-finite or out of its DBC range
    valid = {SENSOR_ID: lambda: codec.sensor(SensorReading(rng.randrange(10 ** 6), 60.0, 10.0)),
             0x110: lambda: codec.command(TorqueCommand(rng.randrange(10 ** 6), 1000.0))}
    fid, at, name = rng.choice([s for s in _float_signals(codec.db)
                                if s[0] in valid or s[0] in (STATUS_ID, RESULT_ID, INTERVAL_ID, SAMPLE_ID)])
    data = bytearray(valid[fid]().data if fid in valid else bytes(known[fid]))
    if kind == "non_finite":
        value = rng.choice([float("nan"), float("inf"), float("-inf")])
    else:
        value = rng.choice([1e12, -1e12, 1e300])
    data[at:at + 8] = struct.pack("<d", value)
    if fid not in valid:             # the other fields: in range (ParamCount 1, IntervalLevel 50)
        if fid == RESULT_ID:
            data[9] = 1
        if fid == INTERVAL_ID:
            data[7] = 50
    return f"{kind}:{name}", can.Message(arbitration_id=fid, data=bytes(data), is_extended_id=False, **fd)


#: what a third node forges or replays; with authentication off only the kinds the plant can tell
FORGE_ON = ("replay_sensor", "replay_command", "replay_status", "replay_plant_hb", "replay_tcu_hb",
            "sensor_ahead", "command_ahead", "result_early", "tcu_hb_ahead", "status_ahead", "sample_bad",
            "interval_bad", "plant_hb", "altered", "random_trailer")
FORGE_OFF = ("replay_sensor", "replay_command", "replay_status", "replay_plant_hb", "sensor_ahead", "command_ahead",
             "result_early", "tcu_hb_ahead", "status_ahead", "sample_bad", "interval_bad", "plant_hb")


#: how many frames of its id back a replayed frame is.  The newest frame sent again at once can overtake
#: the genuine copy still queued at a receiver (another socket of the mesh): the copy is then taken (the
#: same bytes) and the genuine frame before it rejected as replayed, so a receiver counts one frame more
#: than the third node sent (docs/design/benchmarks.md has the counts seen).
REPLAY_AGE = 16


class _Seen(dict):
    """The last ``REPLAY_AGE`` genuine frames per id; ``self[id]`` is the newest."""

    def __init__(self):
        super().__init__()
        self.history: dict = {}

    def __setitem__(self, fid, msg):
        from ...bus.frames import PLANT_HEARTBEAT_ID, SENSOR_ID, TCU_HEARTBEAT_ID

        super().__setitem__(fid, msg)
        if fid in (PLANT_HEARTBEAT_ID, TCU_HEARTBEAT_ID) and SENSOR_ID not in self:
            # a heartbeat from before the exchange began may never have reached the other node (it was
            # starting): sent again it would be fresh there, not a replay
            return
        h = self.history.setdefault(fid, collections.deque(maxlen=REPLAY_AGE))
        h.append(msg)

    def old(self, fid):
        """A frame of ``fid`` seen ``REPLAY_AGE`` frames ago; of a heartbeat (4 a second in lockstep),
        the one before the newest."""
        from ...bus.frames import PLANT_HEARTBEAT_ID, TCU_HEARTBEAT_ID

        h = self.history.get(fid)
        age = 2 if fid in (PLANT_HEARTBEAT_ID, TCU_HEARTBEAT_ID) else REPLAY_AGE
        return h[-age] if h and len(h) >= age else None


class Forger:
    """Builds the third node's forged and replayed frames from what it saw on the bus (no key)."""

    def __init__(self, codec, rng: random.Random):
        self.codec, self.rng = codec, rng
        self.seen = _Seen()         # id -> the genuine frames seen lately
        self.step = 0
        self.ahead = 0

    def make(self, kind: str):
        import can

        from ...bus.frames import (COMMAND_ID, INTERVAL_ID, PLANT_HEARTBEAT_ID, SENSOR_ID, STATE_RUNNING, STATUS_ID,
                              TCU_HEARTBEAT_ID, SampleReport)
        from identifier.messages import (IdentificationEvent, ObserverSample, SensorReading, TcuStatus,
                                         TorqueCommand)

        c, k, rng = self.codec, self.step, self.rng
        replay = {"replay_sensor": SENSOR_ID, "replay_command": COMMAND_ID, "replay_status": STATUS_ID,
                  "replay_plant_hb": PLANT_HEARTBEAT_ID, "replay_tcu_hb": TCU_HEARTBEAT_ID}
        if kind in replay:          # a frame seen REPLAY_AGE frames of its id ago (see _Seen)
            m = self.seen.old(replay[kind])
            if m is None:
                return None
            return can.Message(arbitration_id=m.arbitration_id, data=bytes(m.data), is_extended_id=False, is_fd=True,
                               bitrate_switch=m.bitrate_switch)
        if kind == "sensor_ahead":       # never two consecutive steps: the TCU would resync to them
            self.ahead += 1
            return c.sensor(SensorReading(k + 1000 + 7 * self.ahead, 60.0 + rng.random(), 10.0))
        if kind == "command_ahead":
            return c.command(TorqueCommand(k + 1000 + rng.randrange(1000), rng.uniform(0, 5000)))
        if kind == "result_early":
            return c.result(IdentificationEvent(k, k * 1e-3, "correction", rng.randrange(1, 50),
                                                (0.3, 0.1, 0.2, 1.0, 5.0), 0.0, 10))
        if kind == "tcu_hb_ahead":
            return c.tcu_heartbeat(rng.randrange(65536), STATE_RUNNING, k + 1000 + rng.randrange(1000))
        if kind == "status_ahead":
            return c.status(TcuStatus(k + 1000 + rng.randrange(1000), 1, 0),
                            ObserverSample(k, k * 1e-3, 0.5, 0.2, 1000.0))
        if kind == "sample_bad":
            return c.sample(SampleReport(k, 30000 + rng.randrange(30000), k, 1.0, 0.2))
        if kind == "interval_bad":      # an interval for a result that was never sent
            return c._msg(INTERVAL_ID, {"IntervalStep": k, "IntervalCorrection": 40000 + rng.randrange(20000),
                                        "IntervalKind": 0, "IntervalLevel": 90, "PeakMuLo": 0.1, "PeakMuHi": 0.2,
                                        "PeakCreepLo": 1.0, "PeakCreepHi": 2.0, "IntervalOpen": 0,
                                        "SamplesStated": 0, "SamplesFromStep": 0, "SamplesToStep": 0})
        if kind == "plant_hb":
            return c.plant_heartbeat(rng.randrange(65536), STATE_RUNNING, k)
        if kind in ("altered", "random_trailer"):
            m = self.seen.get(rng.choice([SENSOR_ID, COMMAND_ID, STATUS_ID]))
            if m is None:
                return None
            data = bytearray(m.data)
            if kind == "altered":
                data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
            else:
                at = c.trailer_offsets[m.arbitration_id]
                data[at:at + 8] = rng.randbytes(8)
            return can.Message(arbitration_id=m.arbitration_id, data=bytes(data), is_extended_id=False, is_fd=True)
        raise ValueError(kind)


def _plan(rng, garbage: int, forged: int, authenticated: bool) -> list[tuple[str, str]]:
    kinds = FORGE_ON if authenticated else FORGE_OFF
    items = [("garbage", "")] * garbage + [("forged", kinds[i % len(kinds)]) for i in range(forged)]
    rng.shuffle(items)
    return items


def frame_run(tmp: Path, seed: int, run_seed: int, garbage: int, forged: int, auth: str, rng: random.Random,
              batch: int = 20, log=None) -> dict:
    """One lockstep ``hil run`` on a fresh localbus channel with a third node sending ``garbage`` +
    ``forged`` frames (none when both are 0); the run's summary, what was sent, and per receiver what
    it should have counted."""
    from ...bus.frames import SENSOR_ID, FrameCodec
    from ...bus.localbus import LocalBus, create_channel, remove_channel

    out = tmp / f"{auth}-{garbage}-{forged}"
    out.mkdir(parents=True, exist_ok=True)
    channel = create_channel()
    spy = LocalBus(channel)
    extra = ["--set", "bus.auth=off"] if auth == "off" else []
    # output to files, not pipes: nobody reads a pipe while the third node works
    with open(out / "stdout", "w") as so, open(out / "stderr", "w") as se:
        proc = subprocess.Popen(hil_cmd("run", SCENARIOS / "ffcc_a.toml", "--bus", f"localbus:{channel}", "--seed",
                                        run_seed, "--out", out, "--no-rrd", "--json", *FRAME_RUN, *extra),
                                stdout=so, stderr=se, stdin=subprocess.DEVNULL, env=subprocess_env(), cwd=ROOT)
    codec = FrameCodec(1e-3)                     # the third node has no key
    forger = Forger(codec, rng)
    plan = _plan(rng, garbage, forged, auth != "off")
    sent = collections.Counter()
    # per receiver: frames it should count (delivered ones only), and how many the bus could not deliver
    expect = {"plant": 0, "tcu": 0}
    undelivered = {"plant": 0, "tcu": 0, "other": 0}
    tcu_pid = None
    start_step = rng.randrange(50, 150)
    hung = False
    deadline = time.monotonic() + RUN_TIMEOUT_S
    try:
        while proc.poll() is None:
            if time.monotonic() > deadline:
                hung = True
                break
            msg = spy.recv(0.2)
            if tcu_pid is None:
                tcu = [p for p in children_of(proc.pid) if "hil.tcu_node" in cmdline(p)]
                tcu_pid = tcu[0] if tcu else None
            if msg is None:
                continue
            forger.seen[msg.arbitration_id] = msg
            if msg.arbitration_id != SENSOR_ID or not plan:
                continue
            frame, _ = codec.classify(msg)
            if frame is None or frame.value.step < start_step:
                continue
            forger.step = frame.value.step
            # catch up with the bus first (the newest frames to replay, and no burst of batches for a
            # backlog of old sensor frames: the receivers' socket buffers would overflow)
            while (m2 := spy.recv(0.0)) is not None:
                forger.seen[m2.arbitration_id] = m2
                if m2.arbitration_id == SENSOR_ID:
                    f2, _ = codec.classify(m2)
                    forger.step = f2.value.step if f2 is not None else forger.step
            for _ in range(min(batch, len(plan))):
                what, kind = plan.pop()
                if what == "garbage":
                    kind, m = garbage_frame(rng, codec, auth != "off")
                    at_tcu = 1
                else:
                    m = forger.make(kind)
                    if m is None:
                        plan.insert(0, (what, kind))
                        continue
                    at_tcu = 1 if auth != "off" or kind in ("replay_sensor", "sensor_ahead") else 0
                before = dict(spy.dropped)
                spy.send(m)
                missed = {p for p, n in spy.dropped.items() if n > before.get(p, 0)}
                sent[(what, kind.split(":")[0])] += 1
                for who, pid, count in (("plant", proc.pid, 1), ("tcu", tcu_pid, at_tcu)):
                    if any(p.startswith(f"{pid}-") for p in missed):
                        undelivered[who] += 1
                    else:
                        expect[who] += count
                undelivered["other"] += sum(1 for p in missed if not p.startswith((f"{proc.pid}-", f"{tcu_pid}-")))
        if hung:
            stop(proc)
        proc.wait(60)
    finally:
        stop(proc)
        spy.shutdown()
        remove_channel(channel)
    out_text, err = (out / "stdout").read_text(), (out / "stderr").read_text()
    try:
        summary = json.loads(out_text) if out_text.strip() else None
    except ValueError:  # no JSON (the run crashed): its exit and stderr are judged
        summary = None
    return {"summary": summary, "exit": proc.returncode, "stderr": err, "hung": hung, "unsent": len(plan),
            "sent": sum(sent.values()), "sent_by_kind": {f"{a}:{b}": n for (a, b), n in sorted(sent.items())},
            "expect": expect, "undelivered": undelivered}


def _plant_reported(s: dict) -> int:
    """What the plant counted of a third node's frames: every rejection, and the suspicious frames it
    took (a result before the fault, a heartbeat ahead); the other suspicious kinds come with a
    rejection (answered_twice, duplicate, foreign) and are not counted twice."""
    sus = s.get("suspicious") or {}
    return sum((s.get("rejected_frames") or {}).values()) + sus.get("result_before_fault", 0) + \
        sus.get("heartbeat_ahead", 0)


def part_frames(seed: int, garbage: int, forged: int, log) -> dict:
    part = Part("frames", seed, f"{garbage} garbage and {forged} forged/replayed frames from a third node, auth on and "
                "off: 0 crashes, 0 hangs, every frame counted on both sides; identification unchanged with auth on; "
                "every forgery reported with auth off")
    rng = random.Random(f"{seed}:frames")
    run_seed = rng.randrange(1, 10 ** 6)
    part.figures["run_seed"] = run_seed
    with tempfile.TemporaryDirectory(prefix="hil-robust-frames-") as tmp:
        tmp = Path(tmp)
        log(f"bench robustness: frames: clean run (seed {run_seed})")
        clean = frame_run(tmp, seed, run_seed, 0, 0, "on", rng)
        part.cases += 1
        ref = clean["summary"]
        if clean["exit"] != 0 or ref is None:
            part.fail("clean", "the clean run failed", f"exit {clean['exit']}: {last_line(clean['stderr'])}")
            return part.done()
        for auth in ("on", "off"):
            log(f"bench robustness: frames: auth {auth}: {garbage} garbage + {forged} forged/replayed frames")
            r = frame_run(tmp, seed, run_seed, garbage, forged, auth, rng, log=log)
            part.cases += 1
            s = r["summary"] or {}
            fig = {"exit": r["exit"], "sent": r["sent"], "sent_by_kind": r["sent_by_kind"], "unsent": r["unsent"],
                   "undelivered": r["undelivered"], "expected_plant": r["expect"]["plant"],
                   "expected_tcu": r["expect"]["tcu"], "frame_auth": s.get("frame_auth"),
                   "rejected_frames": s.get("rejected_frames"), "tcu_rejected_frames": s.get("tcu_rejected_frames"),
                   "suspicious": s.get("suspicious"), "traceback": "Traceback" in r["stderr"], "hung": r["hung"]}
            part.figures[f"auth_{auth}"] = fig
            case = f"auth {auth}"
            if r["hung"]:
                part.fail(case, "hang", f"the run did not end within {RUN_TIMEOUT_S:g} s")
                continue
            if r["exit"] != 0 or not s:
                part.fail(case, "the run failed", f"exit {r['exit']}: {last_line(r['stderr'])}")
                continue
            if fig["traceback"]:
                part.fail(case, "traceback on stderr", r["stderr"])
            if r["unsent"]:
                part.fail(case, "the run ended before the third node sent everything", f"{r['unsent']} frames unsent")
            fig["plant_counted"] = plant = _plant_reported(s) if auth == "off" else \
                sum((s.get("rejected_frames") or {}).values())
            fig["tcu_counted"] = tcu = sum((s.get("tcu_rejected_frames") or {}).values())
            if plant != r["expect"]["plant"]:
                part.fail(case, "plant count", f"the plant counted {plant} of the third node's frames, "
                          f"{r['expect']['plant']} delivered to it (rejected {s.get('rejected_frames')}, suspicious "
                          f"{s.get('suspicious')})")
            if tcu != r["expect"]["tcu"]:
                part.fail(case, "TCU count", f"the TCU rejected {tcu} frames, {r['expect']['tcu']} expected "
                          f"({s.get('tcu_rejected_frames')})")
            if s.get("frame_auth") != auth:
                part.fail(case, "frame_auth", f"summary says frame_auth {s.get('frame_auth')!r}")
            if auth == "on":
                if s.get("suspicious"):
                    part.fail(case, "suspicious with auth on", f"{s.get('suspicious')}")
                diff = {k: (s.get(k), ref.get(k)) for k in IDENT_KEYS if s.get(k) != ref.get(k)}
                fig["identification_unchanged"] = not diff
                if diff:
                    part.fail(case, "identification changed", f"(with third node, clean): {diff}")
            else:
                fig["identification_unchanged"] = all(s.get(k) == ref.get(k) for k in IDENT_KEYS)
    return part.done()
