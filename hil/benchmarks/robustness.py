"""``hil bench robustness``: the reliability probes, repeated with seeds drawn at run time.

One master seed (drawn now unless ``--seed``, printed with how to repeat) gives every part its own
``random.Random(f"{seed}:{part}")``, so ``--seed S --only PART`` with the same counts repeats a part's
cases exactly; a failure names the part, the case index and what was done.

Parts (``--only`` takes a comma-separated subset):

- ``frames``: a clean lockstep run on a fresh ``localbus`` channel, then the same run (same seed) with
  a third node on the channel sending ``--garbage`` malformed frames and ``--forged`` forged or
  replayed frames, once with frame authentication on (the default there) and once with
  ``bus.auth=off``.  Every frame the third node sends is accounted for at each receiver (plant and
  TCU; frames the bus could not deliver to a peer, ``LocalBus.dropped``, are taken out of that peer's
  expectation and reported).  Authentication on: each one is rejected on both sides
  (``rejected_frames``, ``tcu_rejected_frames``), nothing is ``suspicious``, and the identification is
  the clean run's.  Authentication off: the garbage is rejected on both sides, and every forgery is
  reported by the plant: rejected (``bad_sequence``, ``answered_twice``, ``foreign`` ...) or counted in
  ``suspicious`` (``result_before_fault``, ``heartbeat_ahead``); the TCU rejects the forged sensor
  frames.  (Off, the forgeries are of the kinds the stream can show to be wrong; a forged command for
  the pending step, or a status in sequence, cannot be told from the TCU's without the MAC.)
- ``scenarios``: ``--scenarios`` mutants of a full scenario file (``mutate``) loaded in process, each
  under a 10 s watchdog: a ``HilError`` of one line naming the file, or a scenario; never another
  exception.  ``--scenario-runs`` of them then go through the real ``hil run`` (``--bus inprocess``) in
  a subprocess in a sandbox (its own cwd, HOME, TMPDIR, XDG_RUNTIME_DIR), with a timeout: no
  traceback, no hang, exit 0 or 2, nothing written in the sandbox outside ``--out``.
- ``logs``: a real run's MCAP damaged ``--logs`` times (``damage_log``: flipped bytes in chunks, zeroed
  bytes early in the file, cut short, damage and a cut, a damaged chunk length, the first chunk lost):
  ``hil.log.read.read_log`` must read each and recover every message of every chunk the damage left
  intact (the expectation comes from the undamaged file read with the ``mcap`` library), and nothing
  that was not in the log.
- ``fmus``: ``--fmus`` broken FMUs made from our exported FMU (a modelIdentifier that is a path to a
  library outside the FMU, archive members that climb out, a zip bomb, not a zip, a folder, FMI 1.0, no
  binary, Model Exchange only, a garbage binary, another GUID, a member that inflates to more than it
  declares) through ``hil.plants.make_plant``: each refused with a one-line ``PlantError``, the
  library outside never loaded, nothing unpacked outside the temporary folder (and that removed).
- ``kills``: SIGKILL of the TCU process (exit 3, the log closed with the fault) and of the plant (the
  ``hil run`` process: its TCU ends, the log is readable up to the kill), ``--kills`` of each, at a
  random point.
- ``disk``: ``hil run`` under a random file size limit (RLIMIT_FSIZE: a disk that fills mid-run; exit 2
  in one line, the TCU stopped, the log readable up to the limit) ``--disk`` times, and a limit of 0
  on ``inprocess`` and ``local`` (no empty log left).
- ``memory``: peak RSS (the process's VmHWM, sampled) of an in-process lockstep ``hil run`` of ``--memory-seconds`` A and B
  simulated seconds: the long run's peak over the short one's (flat: at most 1.2).

The result: a terminal table by default, one JSON object with ``--json``, and with ``--report DIR``
``DIR/robustness.md`` and ``DIR/robustness.json``.  Exit code 1 when a probe failed.
"""
from __future__ import annotations

import collections
import json
import os
import platform
import random
import re
import resource
import secrets
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

from ..errors import ConfigError, HilError

ROOT = Path(__file__).resolve().parents[2]
SCENARIOS = ROOT / "scenarios"
PARTS = ("frames", "scenarios", "logs", "fmus", "kills", "disk", "memory")
IDENT_KEYS = ("identified", "t_identified_s", "corrections", "params", "samples", "r2", "peak_mu_err_percent")
#: the long run's peak RSS over the short one's that still counts as flat
MEMORY_RATIO_MAX = 1.2
#: a probe that takes longer than this is a hang (in-process scenario loading)
LOAD_TIMEOUT_S = 10.0
RUN_TIMEOUT_S = 300.0


# -- shared generators (also used by tests/test_bad_input.py and tests/test_logread.py) -------------------
#: the tables FFCC-a leaves out, filled in so that mutations reach them too
FULL_SCENARIO_EXTRA = """
[identifier]
observer_pole_rad_s = 500.0
baseline_samples = 50
settle_time_s = 0.008
window_samples = 6
max_corrections = 200
drill_particles = 64

[identifier.options.proposed]
particles = 200
noise_block = 8
init_std = [0.003, 0.02, 0.03]
projector = "clip"

[identifier.options.nlls]
window_samples = 7

[identifier.options.bayes]
particles = 100
peak_mu = [0.05, 0.25]

[bus]
heartbeat_period_s = 0.002
silence_periods = 25
lockstep_silence_s = 1.0
startup_timeout_s = 60

[reality.resistance]
factor = 1.2
"""

#: what a value may be replaced with: wrong types, extremes, non-finite, huge, negative, strings
VALUES = ['"text"', '""', "true", "false", "[1, 2]", "[]", "{ a = 1 }", "0", "-1", "-0.0", "1e-300", "-1e-300",
          "1e300", "-1e300", "nan", "inf", "-inf", "9223372036854775807", "-9223372036854775808", "1000000000",
          "1e9", "0.5", "2", '"\\u0000"', '"../../x"', "1979-05-27", "[[1], [2]]", '"' + "x" * 300 + '"']
#: bytes inserted at random places
JUNK = [b"\xff", b"\xfe\xff", b"\x00", b"\xc3", b"[", b"]", b"=", b'"', b"\n[run]\n", b"\n[[vehicle]]\n",
        b"[" * 2000, b"\x1b[2J", "é".encode(), b"\r", b"\\"]
#: --set items a mutant is loaded with (one drawn per mutant)
SET_CHOICES = ([], [], ["run.duration_s=0.9"], ["vehicle.gear_ratio=3"])


def full_scenario_text() -> str:
    """FFCC-a with every optional table filled in: the text the scenario mutants start from."""
    return (SCENARIOS / "ffcc_a.toml").read_text() + FULL_SCENARIO_EXTRA


def mutate(text: str, rng: random.Random) -> tuple[str, bytes]:
    """One mutation of ``text``: (what was done, the mutant's bytes)."""
    lines = text.splitlines(keepends=True)
    assignments = [i for i, line in enumerate(lines) if re.match(r"\s*[A-Za-z_\"]\S*\s*=", line)]
    headers = [i for i, line in enumerate(lines) if line.startswith("[")]
    kind = rng.choice(["delete", "value", "value", "value", "junk", "truncate", "table_scalar", "duplicate",
                       "nest", "rename"])
    if kind == "delete":
        i = rng.choice(assignments + headers)
        del lines[i]
        return f"delete line {i + 1}", "".join(lines).encode()
    if kind == "value":
        i = rng.choice(assignments)
        key = lines[i].split("=", 1)[0]
        value = rng.choice(VALUES)
        lines[i] = f"{key}= {value}\n"
        return f"line {i + 1}: {key.strip()} = {value[:40]}", "".join(lines).encode()
    if kind == "junk":
        data = text.encode()
        at = rng.randrange(len(data) + 1)
        junk = rng.choice(JUNK)
        return f"junk {junk[:10]!r} at byte {at}", data[:at] + junk + data[at:]
    if kind == "truncate":
        data = text.encode()
        at = rng.randrange(len(data))
        return f"truncated at byte {at}", data[:at]
    if kind == "table_scalar":
        i = rng.choice(headers)
        name = lines[i].strip().strip("[]").split(".")[0]
        body = "".join(line for line in lines if not line.startswith(f"[{name}"))
        return f"[{name}] made a scalar", f"{name} = {rng.choice(VALUES)}\n{body}".encode()
    if kind == "duplicate":
        i = rng.choice(assignments + headers)
        lines.insert(i, lines[i])
        return f"line {i + 1} twice", "".join(lines).encode()
    if kind == "nest":
        depth = rng.choice([10, 500, 5000, 100_000])
        return f"nesting {depth}", (f"deep = {'[' * depth}{']' * depth}\n" + text).encode()
    i = rng.choice(headers)
    lines[i] = lines[i].replace("[", "[x", 1)
    return f"table on line {i + 1} renamed", "".join(lines).encode()


#: where damage goes in a chunk: past its head (opcode, length, start and end times, sizes, CRC and
#: compression name: 52 bytes) and its LZ4 frame header (up to 15 bytes), and before the frame's end
#: mark.  Those fields are covered by no CRC and some are inert (a flipped bit of a time, of the
#: uncompressed size or of a block-size flag reads the very same records), so a reader that keeps
#: such a chunk is right; in the compressed payload the chunk's CRC must catch every flip.
PAYLOAD = (80, 8)
DAMAGES = ("flip", "flips", "zero_early", "cut", "flip_cut", "length_cut", "first_cut")


def in_payload(rng: random.Random, a: int, b: int) -> int:
    """A byte position inside the compressed payload of the chunk at bytes ``a``-``b``."""
    return rng.randrange(a + PAYLOAD[0], b - PAYLOAD[1])


def chunk_map(path) -> tuple[bytes, list]:
    """A log's bytes and, per chunk, (first byte, end byte, [(topic, log_time)]), read with the ``mcap``
    library's own readers (never ``hil.log.read``): the expectation damaged copies are judged by."""
    from mcap.reader import make_reader
    from mcap.records import Chunk, Message
    from mcap.stream_reader import StreamReader, breakup_chunk

    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {cid: ch.topic for cid, ch in summary.channels.items()}
        every = collections.Counter((ch.topic, m.log_time) for _, ch, m in reader.iter_messages())
        spans = sorted((c.chunk_start_offset, c.chunk_start_offset + c.chunk_length) for c in summary.chunk_indexes)
    with open(path, "rb") as f:
        chunks = [r for r in StreamReader(f, emit_chunks=True).records if isinstance(r, Chunk)]
    if len(chunks) != len(spans):
        raise HilError(f"{path}: {len(chunks)} chunks in the file, {len(spans)} in its index")
    per_chunk = [[(topics[m.channel_id], m.log_time) for m in breakup_chunk(c) if isinstance(m, Message)]
                 for c in chunks]
    if collections.Counter(x for msgs in per_chunk for x in msgs) != every:
        raise HilError(f"{path}: the chunks' messages are not the log's")
    return Path(path).read_bytes(), [(a, b, msgs) for (a, b), msgs in zip(spans, per_chunk)]


def chunk_records(data: bytes, a: int) -> bytes | None:
    """The uncompressed records of the chunk record at byte ``a`` of ``data`` (compression "" or
    "lz4"), decompressed by the ``lz4`` package (never by ``hil.log.read``), or None when they do not
    decompress.  The chunk's head: opcode 1, length 8, start and end times 8 + 8, uncompressed size
    8, CRC 4, compression name (4-byte length + bytes), records (8-byte length + bytes)."""
    import lz4.frame

    try:
        n = int.from_bytes(data[a + 37:a + 41], "little")
        compression = data[a + 41:a + 41 + n]
        size = int.from_bytes(data[a + 41 + n:a + 49 + n], "little")
        records = data[a + 49 + n:a + 49 + n + size]
        return records if compression == b"" else lz4.frame.decompress(records) if compression == b"lz4" else None
    except Exception:  # noqa: BLE001 - damaged: not decompressible
        return None


def still_intact(original: bytes, damaged: bytes, a: int) -> bool:
    """A chunk damaged only inside its compressed payload is intact after all when its records
    decompress to the original's very bytes: some flips are inert (an LZ4 match offset moved onto
    identical bytes), and a reader that keeps such a chunk is right."""
    got = chunk_records(damaged, a)
    return got is not None and got == chunk_records(original, a)


def expected_messages(chunks, intact) -> collections.Counter:
    """The (topic, log_time) of every message in the chunks ``intact(first byte, end byte)`` keeps."""
    return collections.Counter(x for a, b, msgs in chunks if intact(a, b) for x in msgs)


def damage_log(data: bytes, chunks, rng: random.Random, kind: str | None = None):
    """One damaged copy of a log: (what was done, its bytes, the messages it must still give).
    ``chunks`` from ``chunk_map``; ``kind`` one of ``DAMAGES`` (drawn when None)."""
    kind = kind or rng.choice(DAMAGES)
    n = len(chunks)
    bad = bytearray(data)
    if kind in ("flip", "flips"):
        picked = rng.sample(range(n // 4, 3 * n // 4), 1 if kind == "flip" else min(rng.randint(2, 4), n // 2))
        for i in picked:
            a, b, _ = chunks[i]
            bad[in_payload(rng, a, b)] ^= 1 << rng.randrange(8)
        starts = {chunks[i][0] for i in picked} - {a for a in (chunks[i][0] for i in picked)
                                                   if still_intact(data, bytes(bad), a)}
        return (f"{kind}: a bit flipped in the payload of chunk(s) {sorted(picked)}", bytes(bad),
                expected_messages(chunks, lambda a, b: a not in starts))
    if kind == "zero_early":
        at = rng.randrange(8, 4096)
        bad[at:at + 16] = bytes(16)
        return (f"zero_early: 16 bytes zeroed at {at}", bytes(bad),
                expected_messages(chunks, lambda a, b: b <= at or a >= at + 16))
    if kind == "cut":
        cut = rng.randrange(len(data) // 4, len(data) - 1)
        return f"cut: cut at byte {cut}", bytes(bad[:cut]), expected_messages(chunks, lambda a, b: b <= cut)
    if kind in ("flip_cut", "length_cut"):
        i = rng.randrange(2, max(n // 2, 3))
        a0, b0, _ = chunks[i]
        if kind == "flip_cut":
            bad[in_payload(rng, a0, b0)] ^= 0xFF
        else:
            bad[a0 + 1:a0 + 9] = rng.randbytes(8)
        cut = rng.randrange(chunks[-3][0], len(data) - 1)
        lost = a0 if kind == "length_cut" or not still_intact(data, bytes(bad), a0) else None
        return (f"{kind}: chunk {i} ({'payload byte' if kind == 'flip_cut' else 'length field'}) damaged, cut at "
                f"byte {cut}", bytes(bad[:cut]), expected_messages(chunks, lambda a, b: a != lost and b <= cut))
    if kind == "first_cut":
        a0, b0, _ = chunks[0]
        bad[in_payload(rng, a0, b0)] ^= 0x55
        cut = chunks[-2][0] + 10
        lost = None if still_intact(data, bytes(bad), a0) else a0
        return (f"first_cut: the first chunk (schemas, channels) damaged, cut at byte {cut}", bytes(bad[:cut]),
                expected_messages(chunks, lambda a, b: a != lost and b <= cut))
    raise ConfigError(f"unknown damage {kind!r}; known: {', '.join(DAMAGES)}")


# -- helpers ------------------------------------------------------------------------------------------
def subprocess_env(**extra) -> dict:
    """The environment a ``hil`` subprocess runs with: this tree first on PYTHONPATH."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    env.update({k: str(v) for k, v in extra.items()})
    return env


def hil_cmd(*args) -> list[str]:
    return [sys.executable, "-m", "hil.cli", *[str(a) for a in args]]


def children_of(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(x) for x in (task / "children").read_text().split()]
        except OSError:
            pass
    return out


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _kill(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            pass


def _last_line(text: str) -> str:
    lines = (text or "").strip().splitlines()
    return lines[-1] if lines else ""


def _traceback(text: str, n: int = 1500) -> str:
    """The first traceback on a stderr (from an "Exception ignored in" / "Exception in thread" line
    before it, where there is one), cut to ``n`` characters; "" when there is none.  A failure quotes
    it: the last line alone does not say which process or thread printed it."""
    text = text or ""
    at = text.find("Traceback")
    if at < 0:
        return ""
    start = text.rfind("\n", 0, at) + 1
    before = text.rfind("\n", 0, max(start - 1, 0)) + 1
    if text[before:start].startswith(("Exception ignored", "Exception in thread")):
        start = before
    return text[start:start + n]


def _short(text: str, n: int = 300) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= n else text[:n - 3] + "..."


class _Timeout(Exception):
    pass


class Part:
    """A part's figures, its cases' failures and its verdict."""

    def __init__(self, name: str, seed: int, target: str):
        self.name, self.seed, self.target = name, seed, target
        self.figures: dict = {}
        self.failures: list[dict] = []
        self.cases = 0
        self.t0 = time.monotonic()

    def fail(self, case, what: str, detail: str) -> None:
        self.failures.append({"case": case, "what": _short(what, 200), "detail": _short(detail, 600)})

    def done(self, passed: bool | None = None) -> dict:
        ok = not self.failures if passed is None else (passed and not self.failures)
        return {"part": self.name, "cases": self.cases, "target": self.target, "passed": ok,
                "figures": self.figures, "failures": self.failures, "wall_s": round(time.monotonic() - self.t0, 1)}


# -- frames --------------------------------------------------------------------------------------------
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

    from ..bus.frames import INTERVAL_ID, RESULT_ID, SAMPLE_ID, SENSOR_ID, STATUS_ID
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
#: than the third node sent (seen with seed 12: 3 at the plant with authentication on, 10 with it off).
REPLAY_AGE = 16


class _Seen(dict):
    """The last ``REPLAY_AGE`` genuine frames per id; ``self[id]`` is the newest."""

    def __init__(self):
        super().__init__()
        self.history: dict = {}

    def __setitem__(self, fid, msg):
        from ..bus.frames import PLANT_HEARTBEAT_ID, SENSOR_ID, TCU_HEARTBEAT_ID

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
        from ..bus.frames import PLANT_HEARTBEAT_ID, TCU_HEARTBEAT_ID

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

        from ..bus.frames import (COMMAND_ID, INTERVAL_ID, PLANT_HEARTBEAT_ID, SENSOR_ID, STATE_RUNNING, STATUS_ID,
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
                                        "PeakCreepLo": 1.0, "PeakCreepHi": 2.0})
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
    from ..bus.frames import SENSOR_ID, FrameCodec
    from ..bus.localbus import LocalBus, create_channel, remove_channel

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
            _kill(proc)
        proc.wait(60)
    finally:
        _kill(proc)
        spy.shutdown()
        remove_channel(channel)
    out_text, err = (out / "stdout").read_text(), (out / "stderr").read_text()
    try:
        summary = json.loads(out_text) if out_text.strip() else None
    except ValueError:
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
            part.fail("clean", "the clean run failed", f"exit {clean['exit']}: {_last_line(clean['stderr'])}")
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
                part.fail(case, "the run failed", f"exit {r['exit']}: {_last_line(r['stderr'])}")
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


# -- scenarios -----------------------------------------------------------------------------------------
def _alarm(signum, frame):
    raise _Timeout()


def load_mutant(path: Path, sets) -> tuple[str, str]:
    """(outcome, detail): "loaded" (detail: steps), "refused" (the one line), "traceback", "hang"."""
    from ..config import load_scenario, parse_set

    old = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, LOAD_TIMEOUT_S)
    try:
        s = load_scenario(path, parse_set(sets))
        return "loaded", str(s.steps)
    except _Timeout:
        return "hang", f"load_scenario took more than {LOAD_TIMEOUT_S:g} s"
    except HilError as e:
        msg = str(e)
        if not msg or "\n" in msg or "\r" in msg or len(msg) >= 600 or not (msg.startswith(str(path))
                                                                           or msg.startswith("--set")):
            return "bad_message", repr(msg[:300])
        return "refused", msg
    except RecursionError as e:
        return "traceback", f"RecursionError: {e}"
    except Exception as e:  # noqa: BLE001 - the point of the probe
        return "traceback", f"{type(e).__name__}: {e}"
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def _tree(root: Path) -> set[str]:
    out = set()
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            out.add(os.path.relpath(os.path.join(dirpath, name), root))
    return out


def run_mutant(data: bytes, sets, sandbox_parent: Path, timeout_s: float) -> dict:
    """The mutant through ``hil run --bus inprocess`` in a sandbox: exit, traceback?, hang?, files written
    outside --out."""
    box = Path(tempfile.mkdtemp(prefix="box-", dir=sandbox_parent))
    for d in ("scen", "out", "home", "tmp", "run"):
        (box / d).mkdir(mode=0o700)
    (box / "scen" / "m.toml").write_bytes(data)
    before = _tree(box)
    cmd = hil_cmd("run", "scen/m.toml", "--bus", "inprocess", "--out", "out", "--no-rrd", "--json")
    for item in sets:
        cmd += ["--set", item]
    env = subprocess_env(HOME=box / "home", TMPDIR=box / "tmp", XDG_RUNTIME_DIR=box / "run", MPLCONFIGDIR=box / "tmp")
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=box, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            stdin=subprocess.DEVNULL)
    hung = False
    try:
        out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        hung = True
        _kill(proc)
        out, err = proc.communicate()
    outside = sorted(p for p in _tree(box) - before if not (p == "out" or p.startswith("out" + os.sep)))
    shutil.rmtree(box, ignore_errors=True)
    return {"exit": proc.returncode, "hung": hung, "traceback": "Traceback" in err, "traceback_text": _traceback(err),
            "outside": outside,
            "stderr_last": _last_line(err), "stderr_lines": len(err.strip().splitlines()),
            "wall_s": time.monotonic() - t0}


def part_scenarios(seed: int, count: int, runs: int, log, max_run_steps: int = 30_000) -> dict:
    from ..progress import Progress

    part = Part("scenarios", seed, f"{count} mutated scenario files loaded in process and {runs} of them through "
                "`hil run`: 0 tracebacks, 0 hangs, 0 writes outside --out")
    rng = random.Random(f"{seed}:scenarios")
    base = full_scenario_text()
    outcomes = collections.Counter()
    slowest = (0.0, -1)
    mutants = []
    with tempfile.TemporaryDirectory(prefix="hil-robust-scen-") as tmp:
        tmp = Path(tmp)
        path = tmp / "m.toml"
        path.write_text(base)
        for sets in SET_CHOICES:     # warm: the first load imports and compiles what a scenario needs (not timed)
            from ..config import load_scenario, parse_set
            load_scenario(path, parse_set(list(sets)))
        bar = Progress(count, "bench robustness: scenarios: loading")
        for i in range(count):
            what, data = mutate(base, rng)
            sets = list(rng.choice(SET_CHOICES))
            path.write_bytes(data)
            t0 = time.perf_counter()
            outcome, detail = load_mutant(path, sets)
            took = time.perf_counter() - t0
            slowest = max(slowest, (took, i))
            outcomes[outcome] += 1
            part.cases += 1
            mutants.append((i, what, data, sets, outcome, detail))
            if outcome in ("traceback", "hang", "bad_message"):
                part.fail(i, what, f"{outcome}: {detail}")
            bar.update(i + 1)
        bar.close()
        # the full runs: loaded mutants of a sensible length and refused ones, half each where possible
        loaded = [m for m in mutants if m[4] == "loaded" and int(m[5]) <= max_run_steps]
        refused = [m for m in mutants if m[4] == "refused"]
        long_ = sum(1 for m in mutants if m[4] == "loaded" and int(m[5]) > max_run_steps)
        pick = rng.sample(loaded, min(len(loaded), (runs + 1) // 2))
        pick += rng.sample(refused, min(len(refused), runs - len(pick)))
        run_out = collections.Counter()
        outside_total = run_tracebacks = 0
        run_refused = []           # loaded in process, refused by hil run in one line (exit 2): allowed, listed
        bar = Progress(max(len(pick), 1), "bench robustness: scenarios: hil run")
        for j, (i, what, data, sets, outcome, detail) in enumerate(sorted(pick)):
            r = run_mutant(data, sets, tmp, RUN_TIMEOUT_S)
            run_out[f"exit {r['exit']}" if not r["hung"] else "hang"] += 1
            outside_total += len(r["outside"])
            if r["hung"]:
                part.fail(i, what, f"hil run did not end within {RUN_TIMEOUT_S:g} s")
            elif r["traceback"]:
                run_tracebacks += 1
                part.fail(i, what, f"hil run printed a traceback: {r['stderr_last']}; {r['traceback_text']}")
            elif r["exit"] not in (0, 2):
                part.fail(i, what, f"hil run exit {r['exit']}: {r['stderr_last']}")
            elif r["exit"] == 2 and not r["stderr_last"].startswith("hil run: error: "):
                part.fail(i, what, f"exit 2 without the one error line: {r['stderr_last']}")
            elif r["exit"] == 0 and outcome != "loaded":
                part.fail(i, what, f"refused in process ({detail}) but hil run ran it")
            elif r["exit"] == 2 and outcome == "loaded":
                run_refused.append({"case": i, "what": what, "line": r["stderr_last"][:200]})
            if r["outside"]:
                part.fail(i, what, f"hil run wrote outside --out: {r['outside'][:5]}")
            bar.update(j + 1)
        bar.close()
    part.figures = {"mutants": count, "loaded": outcomes["loaded"], "refused": outcomes["refused"],
                    "tracebacks": outcomes["traceback"], "hangs": outcomes["hang"],
                    "bad_messages": outcomes["bad_message"], "slowest_load_s": round(slowest[0], 3),
                    "slowest_case": slowest[1], "runs": len(pick), "run_outcomes": dict(run_out),
                    "run_tracebacks": run_tracebacks, "loaded_but_refused_by_run": run_refused,
                    "run_hangs": run_out["hang"], "writes_outside_out": outside_total,
                    "loaded_but_too_long_to_run": long_}
    return part.done()


# -- logs ----------------------------------------------------------------------------------------------
def part_logs(seed: int, count: int, log) -> dict:
    from ..log.read import read_log
    from ..progress import Progress

    part = Part("logs", seed, f"{count} damaged copies of a real run's MCAP: every one read, every message of every "
                "intact chunk recovered, nothing invented")
    rng = random.Random(f"{seed}:logs")
    run_seed = rng.randrange(1, 10 ** 6)
    with tempfile.TemporaryDirectory(prefix="hil-robust-logs-") as tmp:
        tmp = Path(tmp)
        log(f"bench robustness: logs: a 2 s run (seed {run_seed}) to damage")
        r = subprocess.run(hil_cmd("run", SCENARIOS / "ffcc_a.toml", "--bus", "inprocess", "--seed", run_seed,
                                   "--out", tmp, "--no-rrd", "--json", "--set", "run.duration_s=2",
                                   "--set", "run.fault_time_s=1.5"),
                           capture_output=True, text=True, env=subprocess_env(), cwd=ROOT, timeout=RUN_TIMEOUT_S)
        if r.returncode != 0:
            part.fail("run", "the run to damage failed", _last_line(r.stderr))
            return part.done()
        src = Path(json.loads(r.stdout)["mcap"])
        data, chunks = chunk_map(src)
        every = expected_messages(chunks, lambda a, b: True)
        kinds = collections.Counter()
        expected_total = recovered_total = missing_total = invented_total = 0
        path = tmp / "damaged.mcap"
        bar = Progress(count, "bench robustness: logs")
        for i in range(count):
            kind = DAMAGES[i % len(DAMAGES)] if i < len(DAMAGES) else None
            what, bad, expected = damage_log(data, chunks, rng, kind)
            kinds[what.split(":")[0]] += 1
            path.write_bytes(bad)
            part.cases += 1
            try:
                got = read_log(path)
            except Exception as e:  # noqa: BLE001 - the point of the probe
                part.fail(i, what, f"read_log raised {type(e).__name__}: {e}")
                expected_total += sum(expected.values())
                missing_total += sum(expected.values())
                continue
            have = collections.Counter((topic, t) for topic, t, _ in got.messages)
            missing = expected - have
            invented = have - every
            expected_total += sum(expected.values())
            recovered_total += sum((expected & have).values())
            missing_total += sum(missing.values())
            invented_total += sum(invented.values())
            if missing:
                part.fail(i, what, f"{sum(missing.values())} of {sum(expected.values())} messages of intact chunks "
                          f"not recovered (damage said: {got.damage[:200]})")
            if invented:
                part.fail(i, what, f"{sum(invented.values())} messages that are not in the log")
            bar.update(i + 1)
        bar.close()
    part.figures = {"damaged_logs": count, "by_damage": dict(kinds), "chunks": len(chunks),
                    "log_bytes": len(data), "intact_chunk_messages": expected_total,
                    "recovered": recovered_total, "missing": missing_total, "invented": invented_total}
    return part.done()


# -- fmus ----------------------------------------------------------------------------------------------
FMU_KINDS = ("ident_abs", "ident_rel", "member_escape", "zip_bomb", "not_zip", "folder", "fmi1", "no_binary",
             "me_only", "garbage_binary", "other_guid", "liar")


def rezip(src: Path, dst: Path, drop_prefix: str | None = None, edit_md=None, edit_binary=None) -> Path:
    """``src`` (an FMU, a zip) copied to ``dst`` without the members under ``drop_prefix``, its
    modelDescription.xml passed through ``edit_md`` (text) and its binaries through ``edit_binary``."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for item in zin.infolist():
            if drop_prefix and item.filename.startswith(drop_prefix):
                continue
            data = zin.read(item)
            if item.filename == "modelDescription.xml" and edit_md:
                data = edit_md(data.decode()).encode()
            if item.filename.startswith("binaries/") and not item.is_dir() and edit_binary:
                data = edit_binary(data)
            zout.writestr(item, data)
    return dst


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
    from ..config import load_scenario
    from ..errors import PlantError
    from ..plants import make_plant

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
                before = _tree(tmp)
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
                new = sorted(_tree(tmp) - before)
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


# -- kills ---------------------------------------------------------------------------------------------
#: what kill_run kills: the TCU and the plant of a local-bus run, the hub process of a hub run
KILL_VICTIMS = ("tcu", "plant", "hub")


def kill_run(tmp: Path, victim: str, seed: int, min_bytes: int) -> dict:
    """A run SIGKILLed once its log has ``min_bytes``: its TCU or the plant (over the local bus), or
    the hub process the plant started (over the hub)."""
    from ..log.read import read_log

    out = tmp / f"{victim}-{seed}"
    path = out / f"ffcc_a-gp-{seed}.mcap"
    bus = "hub" if victim == "hub" else "local"
    proc = subprocess.Popen(hil_cmd("run", SCENARIOS / "ffcc_a.toml", "--bus", bus, "--seed", seed, "--out", out,
                                    "--no-rrd", "--set", "run.duration_s=60", "--set", "run.fault_time_s=55"),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=subprocess_env(), cwd=ROOT)
    res = {"victim": victim, "bus": bus, "seed": seed, "kill_at_bytes": min_bytes}
    try:
        end = time.monotonic() + 120
        tcu = hub = None
        while time.monotonic() < end and proc.poll() is None:
            kids = children_of(proc.pid)
            if tcu is None:
                tcu = next((p for p in kids if "hil.tcu_node" in cmdline(p)), None)
            if hub is None and bus == "hub":
                hub = next((p for p in kids if "can_remote" in cmdline(p)), None)
            if path.exists() and path.stat().st_size >= min_bytes and tcu is not None and (hub or bus != "hub"):
                break
            time.sleep(0.02)
        if proc.poll() is not None:
            res["error"] = f"the run ended before the kill (exit {proc.returncode})"
            return res
        os.kill({"tcu": tcu, "hub": hub}.get(victim, proc.pid), signal.SIGKILL)
        try:
            _, err = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            res["error"] = "the run did not end within 60 s of the kill"
            return res
        res["exit"] = proc.returncode
        res["traceback"] = "Traceback" in err
        res["traceback_text"] = _traceback(err)
        res["last_line"] = _last_line(err)
        t0 = time.monotonic()
        while alive(tcu) and time.monotonic() - t0 < 10:
            time.sleep(0.05)
        res["tcu_left_running"] = alive(tcu)
        got = read_log(path)
        res.update(log_bytes=path.stat().st_size, messages=got.message_count, cut=got.cut, damage=bool(got.damage),
                   ended_early=got.ended_early[:120], states=len(got.topic("/plant/state")))
    finally:
        _kill(proc)
    return res


def part_kills(seed: int, count: int, log) -> dict:
    part = Part("kills", seed, f"SIGKILL of the TCU, of the plant and of the hub, {count} each: the TCU's and the "
                "hub's give exit 3 in one line and a log closed with the fault; the plant's leaves no TCU and a log "
                "readable up to the kill")
    rng = random.Random(f"{seed}:kills")
    runs = []
    with tempfile.TemporaryDirectory(prefix="hil-robust-kills-") as tmp:
        for i in range(len(KILL_VICTIMS) * count):
            victim = KILL_VICTIMS[i % len(KILL_VICTIMS)]
            run_seed, at = rng.randrange(1, 10 ** 6), rng.randrange(100_000, 600_000)
            log(f"bench robustness: kills: case {i}: SIGKILL the {victim} at {at} log bytes (seed {run_seed})")
            r = kill_run(Path(tmp), victim, run_seed, at)
            runs.append(r)
            part.cases += 1
            what = f"SIGKILL {victim} at {at} bytes, run seed {run_seed}"
            if "error" in r:
                part.fail(i, what, r["error"])
                continue
            if r["traceback"]:
                part.fail(i, what, f"traceback: {r['last_line']}; {r['traceback_text']}")
            if r["tcu_left_running"]:
                part.fail(i, what, "the TCU process outlived its run")
            if not r["messages"] or not r["states"]:
                part.fail(i, what, "nothing readable in the log")
            if victim in ("tcu", "hub"):
                says = "TCU process exited" if victim == "tcu" else "its hub process or interface is gone"
                if r["exit"] != 3 or says not in r["last_line"] or not r["last_line"].startswith("hil run: error: "):
                    part.fail(i, what, f"exit {r['exit']}: {r['last_line']}")
                if r["damage"] or not r["ended_early"].startswith("fault at step"):
                    part.fail(i, what, f"log not closed with the fault: damage {r['damage']}, {r['ended_early']!r}")
            elif r["exit"] != -signal.SIGKILL:
                part.fail(i, what, f"exit {r['exit']}")
    part.figures = {"runs": runs}
    return part.done()


# -- disk ----------------------------------------------------------------------------------------------
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
    from ..log.read import read_log

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
    last = _last_line(r.stderr)
    logs = sorted(out.glob("*.mcap")) if out.exists() else []
    rec = {"kind": kind, "bus": bus, "limit": limit, "seed": run_seed, "exit": r.returncode, "last_line": last[:200],
           "log_bytes": logs[0].stat().st_size if logs else None, "tcu_left": bool(_tcus_of(run_seed))}
    if r.returncode != 2 or not last.startswith("hil run: error: "):
        part.fail(i, what, f"exit {r.returncode}: {last}")
    if "Traceback" in r.stderr:
        part.fail(i, what, f"a traceback on stderr: {_traceback(r.stderr)}")
    if rec["tcu_left"]:
        part.fail(i, what, "the TCU process outlived its run")
    if limit == 0:
        left = _tree(out) if out.exists() else set()
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


# -- memory --------------------------------------------------------------------------------------------
def _vm_hwm_kb(pid: int) -> int | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    except (OSError, ValueError):
        return None
    return None


def peak_rss_run(seconds: float, tmp: Path, seed: int) -> dict:
    """Peak RSS of one in-process ``hil run``: its own high-water mark (``VmHWM``), read every 50 ms until
    it exits (the last 50 ms can be missed).  Not ``wait4``'s ``ru_maxrss``: Linux carries the forking
    process's high-water mark into the child across ``exec``, so it reports this bench's own peak."""
    err_path = tmp / f"m{seconds:g}.err"
    with open(err_path, "w") as err:
        proc = subprocess.Popen(hil_cmd("run", SCENARIOS / "ffcc_a.toml", "--bus", "inprocess", "--seed", seed,
                                        "--out", tmp / f"m{seconds:g}", "--no-rrd", "--json",
                                        "--set", f"run.duration_s={seconds}", "--set", f"run.fault_time_s={seconds - 0.5}"),
                                cwd=ROOT, env=subprocess_env(), stdout=subprocess.DEVNULL, stderr=err,
                                stdin=subprocess.DEVNULL)
    t0 = time.monotonic()
    peak = 0
    while proc.poll() is None:
        peak = max(peak, _vm_hwm_kb(proc.pid) or 0)
        time.sleep(0.05)
    return {"seconds": seconds, "exit": proc.returncode, "peak_rss_mb": round(peak / 1024, 1),
            "wall_s": round(time.monotonic() - t0, 1), "last_line": _last_line(err_path.read_text())[:200]}


def part_memory(seed: int, seconds: tuple[float, float], log) -> dict:
    a, b = seconds
    part = Part("memory", seed, f"peak RSS of a {b:g} s run over a {a:g} s run (in-process lockstep): at most "
                f"{MEMORY_RATIO_MAX:g}")
    rng = random.Random(f"{seed}:memory")
    run_seed = rng.randrange(1, 10 ** 6)
    with tempfile.TemporaryDirectory(prefix="hil-robust-mem-") as tmp:
        runs = []
        for s in (a, b):
            log(f"bench robustness: memory: a {s:g} s run (seed {run_seed})")
            runs.append(peak_rss_run(s, Path(tmp), run_seed))
            part.cases += 1
    for r in runs:
        if r["exit"] != 0:
            part.fail(f"{r['seconds']:g} s", "run failed", f"exit {r['exit']}: {r['last_line']}")
    ratio = runs[1]["peak_rss_mb"] / runs[0]["peak_rss_mb"] if runs[0]["peak_rss_mb"] else None
    part.figures = {"run_seed": run_seed, "runs": runs, "ratio": None if ratio is None else round(ratio, 3)}
    if ratio is None or ratio > MEMORY_RATIO_MAX:
        part.fail("ratio", "memory grows with the run's length", f"peak RSS {runs[0]['peak_rss_mb']} MB ({a:g} s) -> "
                  f"{runs[1]['peak_rss_mb']} MB ({b:g} s): ratio {ratio}")
    return part.done()


# -- the bench -----------------------------------------------------------------------------------------
def register(sub) -> None:
    p = sub.add_parser("robustness", help="reliability probes with seeds drawn at run time: garbage and forged "
                       "frames, mutated scenarios, damaged logs, broken FMUs, kills, a full disk, memory")
    p.add_argument("--seed", type=int, default=None, help="master seed (default: drawn now, printed)")
    p.add_argument("--garbage", type=int, default=10_000, help="garbage frames per third-node run (default 10000)")
    p.add_argument("--forged", type=int, default=1_000, help="forged/replayed frames per third-node run (default 1000)")
    p.add_argument("--scenarios", type=int, default=500, help="mutated scenario files loaded (default 500)")
    p.add_argument("--scenario-runs", type=int, default=40, help="of them, through hil run (default 40)")
    p.add_argument("--logs", type=int, default=200, help="damaged logs (default 200)")
    p.add_argument("--fmus", type=int, default=24, help="broken FMUs (default 24: every kind twice)")
    p.add_argument("--kills", type=int, default=2, help="SIGKILLs of the TCU and of the plant, each (default 2)")
    p.add_argument("--disk", type=int, default=2, help="runs hitting a random file size limit (default 2)")
    p.add_argument("--memory-seconds", default="10,60", help="the two run lengths compared (default 10,60)")
    p.add_argument("--only", default=None, help=f"comma-separated parts ({', '.join(PARTS)}; default all)")
    p.add_argument("--report", metavar="DIR", default=None, help="write DIR/robustness.md and DIR/robustness.json")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    p.set_defaults(func=cmd_robustness)


def _check_args(args) -> tuple[list[str], tuple[float, float]]:
    parts = list(PARTS) if not args.only else [x.strip() for x in args.only.split(",") if x.strip()]
    unknown = [x for x in parts if x not in PARTS]
    if unknown or not parts:
        raise ConfigError(f"--only: unknown part(s) {', '.join(unknown) or '(none given)'}; known: {', '.join(PARTS)}")
    for name in ("garbage", "forged", "scenarios", "scenario_runs", "logs", "fmus", "kills", "disk"):
        if getattr(args, name) < 0:
            raise ConfigError(f"--{name.replace('_', '-')}: must be >= 0, got {getattr(args, name)}")
    if "frames" in parts and args.garbage + args.forged > 20 * 3000:
        raise ConfigError("--garbage + --forged: at most 60000 (the third node sends within one run's first steps)")
    try:
        a, b = (float(x) for x in args.memory_seconds.split(","))
    except ValueError:
        raise ConfigError(f"--memory-seconds: two run lengths in seconds, e.g. 10,60; got {args.memory_seconds!r}") \
            from None
    if not 1.0 <= a < b <= 3600:
        raise ConfigError(f"--memory-seconds: need 1 <= A < B <= 3600, got {a:g},{b:g}")
    return parts, (a, b)


def command_line(args, seed: int, parts: list[str]) -> str:
    cmd = f"hil bench robustness --seed {seed}"
    defaults = {"garbage": 10_000, "forged": 1_000, "scenarios": 500, "scenario_runs": 40, "logs": 200, "fmus": 24,
                "kills": 2, "disk": 2, "memory_seconds": "10,60"}
    for name, default in defaults.items():
        if getattr(args, name) != default:
            cmd += f" --{name.replace('_', '-')} {getattr(args, name)}"
    if parts != list(PARTS):
        cmd += f" --only {','.join(parts)}"
    return cmd


def cmd_robustness(args) -> int:
    parts, mem_seconds = _check_args(args)
    seed = secrets.randbits(31) if args.seed is None else args.seed
    log = lambda text: print(text, file=sys.stderr, flush=True)  # noqa: E731
    cmd = command_line(args, seed, parts)
    log(f"bench robustness: seed {seed} (repeat with: {cmd})")
    t0 = time.monotonic()
    load_before = os.getloadavg()[0]
    results = {}
    for name in parts:
        log(f"bench robustness: {name} ...")
        try:
            if name == "frames":
                r = part_frames(seed, args.garbage, args.forged, log)
            elif name == "scenarios":
                r = part_scenarios(seed, args.scenarios, args.scenario_runs, log)
            elif name == "logs":
                r = part_logs(seed, args.logs, log)
            elif name == "fmus":
                r = part_fmus(seed, args.fmus, log)
            elif name == "kills":
                r = part_kills(seed, args.kills, log)
            elif name == "disk":
                r = part_disk(seed, args.disk, log)
            else:
                r = part_memory(seed, mem_seconds, log)
        except KeyboardInterrupt:
            raise
        except Exception as e:  # noqa: BLE001 - a probe that breaks is a failure of that part, reported
            r = {"part": name, "cases": 0, "target": "", "passed": False, "figures": {}, "wall_s": None,
                 "failures": [{"case": "-", "what": "the probe itself failed", "detail": f"{type(e).__name__}: {e}"}]}
        results[name] = r
        log(f"bench robustness: {name}: {'pass' if r['passed'] else 'FAIL'} ({r['cases']} cases, {r['wall_s']} s)")
        for f in r["failures"]:
            log(f"bench robustness: FAIL {name} case {f['case']} (seed {seed}): {f['what']}: {f['detail']}")
    doc = {"seed": seed, "command": cmd, "utc": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
           "machine": platform.machine(), "cores": os.cpu_count(), "load_before": round(load_before, 2),
           "load_after": round(os.getloadavg()[0], 2), "wall_s": round(time.monotonic() - t0, 1),
           "passed": all(r["passed"] for r in results.values()), "parts": results}
    if args.report:
        out = Path(args.report)
        out.mkdir(parents=True, exist_ok=True)
        (out / "robustness.json").write_text(json.dumps(doc, indent=1) + "\n")
        (out / "robustness.md").write_text(markdown(doc))
        log(f"bench robustness: wrote {out / 'robustness.md'} and {out / 'robustness.json'}")
    print(json.dumps(doc) if args.json else table(doc))
    if not doc["passed"]:
        log(f"bench robustness: failures found; repeat with: {cmd}")
    return 0 if doc["passed"] else 1


def headline(r: dict) -> str:
    """A part's figures in one line."""
    f, name = r["figures"], r["part"]
    if not f:
        return "-"
    if name == "frames":
        bits = []
        for auth in ("on", "off"):
            x = f.get(f"auth_{auth}")
            if x and "plant_counted" in x:
                bits.append(f"auth {auth}: sent {x['sent']}, plant counted {x['plant_counted']}/{x['expected_plant']}, "
                            f"TCU {x['tcu_counted']}/{x['expected_tcu']}, undelivered {sum(x['undelivered'].values())}"
                            + (f", identification {'unchanged' if x['identification_unchanged'] else 'CHANGED'}"
                               if auth == "on" else f", suspicious {x['suspicious']}"))
        return "; ".join(bits) or "-"
    if name == "scenarios":
        return (f"{f['mutants']} loaded in process ({f['loaded']} loaded, {f['refused']} refused, {f['tracebacks']} "
                f"tracebacks, {f['hangs']} hangs, slowest {f['slowest_load_s']} s); {f['runs']} through hil run "
                f"({f['run_outcomes']}, {f['writes_outside_out']} writes outside --out)")
    if name == "logs":
        return (f"{f['damaged_logs']} damaged logs ({f['chunks']} chunks each): {f['recovered']} of "
                f"{f['intact_chunk_messages']} messages of intact chunks recovered, {f['missing']} missing, "
                f"{f['invented']} invented")
    if name == "fmus":
        return (f"{f['broken_fmus']} broken FMUs ({len(f['by_kind'])} kinds): {f['refused']} refused, "
                f"{f['loads_from_outside']} loads from outside, {f['cases_leaving_files']} leaving files")
    if name == "kills":
        return "; ".join(f"{r_['victim']}: exit {r_.get('exit')}, {r_.get('messages')} messages readable"
                         for r_ in f["runs"])
    if name == "disk":
        return "; ".join(f"{r_['bus']} {r_['kind']} {r_['limit']}: exit {r_['exit']}, log {r_.get('log_bytes')} B, "
                         f"{r_.get('messages', '-')} messages" for r_ in f["runs"]) \
            + (f"; no tmpfs here: {f['tmpfs_refused']}" if f.get("tmpfs_refused") else "")
    if name == "memory":
        a, b = f["runs"]
        return f"peak RSS {a['peak_rss_mb']} MB ({a['seconds']:g} s) -> {b['peak_rss_mb']} MB ({b['seconds']:g} s): " \
               f"ratio {f['ratio']}"
    return json.dumps(f)[:200]


def table(doc: dict) -> str:
    lines = [f"hil bench robustness, seed {doc['seed']}: {doc['wall_s']} s, load {doc['load_before']} -> "
             f"{doc['load_after']}", ""]
    for name, r in doc["parts"].items():
        lines.append(f"{name:<10} {'pass' if r['passed'] else 'FAIL':<5} {r['cases']:>5} cases  {headline(r)}")
        lines.append(f"{'':<10} target: {r['target']}")
    failures = [(name, f) for name, r in doc["parts"].items() for f in r["failures"]]
    if failures:
        lines += ["", f"{len(failures)} failure(s); repeat with: {doc['command']}"]
        lines += [f"  {name} case {f['case']}: {f['what']}: {f['detail']}" for name, f in failures]
    else:
        lines += ["", "0 failures"]
    return "\n".join(lines)


def markdown(doc: dict) -> str:
    lines = [f"# {doc['command']}", "",
             f"Written by `{doc['command']} --report docs` on {doc['utc']}, {doc['machine']}, {doc['cores']} cores "
             f"(load average {doc['load_before']} before, {doc['load_after']} after); {doc['wall_s']} s in all.  "
             "The seed was drawn at run time; the command above repeats every case.  What each part does: "
             "`hil/benchmarks/robustness.py`.", "",
             "| part | verdict | cases | figures | target | wall s |", "|---|---|---|---|---|---|"]
    for name, r in doc["parts"].items():
        lines.append(f"| {name} | {'pass' if r['passed'] else '**FAIL**'} | {r['cases']} | {headline(r)} | "
                     f"{r['target']} | {r['wall_s']} |")
    failures = [(name, f) for name, r in doc["parts"].items() for f in r["failures"]]
    lines += ["", "## Failures", ""]
    lines += [f"- {name} case {f['case']}: {f['what']}: {f['detail']}" for name, f in failures] or ["None."]
    fr = doc["parts"].get("frames", {}).get("figures", {})
    if fr:
        lines += ["", "## Frames, by kind sent", ""]
        for auth in ("on", "off"):
            x = fr.get(f"auth_{auth}")
            if x:
                lines += [f"- auth {auth}: sent {x['sent_by_kind']}; plant rejected {x['rejected_frames']}, "
                          f"suspicious {x['suspicious']}; TCU rejected {x['tcu_rejected_frames']}; not delivered by the "
                          f"bus {x['undelivered']}"]
    lines.append("")
    return "\n".join(lines)
