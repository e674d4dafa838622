"""What the tests and the benchmarks share to probe the project from outside: ``hil`` as a
subprocess and the processes it starts, a log's chunk map read with the ``mcap`` library (never
with ``hil.log.read``, the reader under test), and generators of bad input (scenario mutants,
rebuilt FMUs).

Library code never imports this module; ``tests/`` and ``hil/benchmarks/`` do (``hil bench
robustness`` repeats at scale what the tests check once), so a probe and its test cannot drift apart.
"""
from __future__ import annotations

import collections
import os
import random
import re
import subprocess
import sys
import zipfile
from pathlib import Path

from .errors import HilError

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "scenarios"


# -- hil as a subprocess, and the processes it starts ---------------------------------------------------
def hil_command() -> list[str]:
    """The installed console script when present, else the module (same code)."""
    exe = Path(sys.executable).with_name("hil")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "hil.cli"]


def hil_cmd(*args) -> list[str]:
    """The command line of ``hil ARGS`` (each argument made a string)."""
    return [*hil_command(), *[str(a) for a in args]]


def subprocess_env(**extra) -> dict:
    """The environment a ``hil`` subprocess runs with: this tree first on PYTHONPATH."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    env.update({k: str(v) for k, v in extra.items()})
    return env


def run_hil(*args, timeout: float = 300, cwd=None) -> subprocess.CompletedProcess:
    """``hil ARGS`` as a user runs it, output captured."""
    return subprocess.run(hil_cmd(*args), capture_output=True, text=True, env=subprocess_env(), timeout=timeout,
                          cwd=cwd)


def children_of(pid: int) -> list[int]:
    """The pids of ``pid``'s children (every thread's), from /proc."""
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(x) for x in (task / "children").read_text().split()]
        except OSError:  # a thread that ended while listed
            pass
    return out


def cmdline(pid: int) -> str:
    """``pid``'s command line, words joined by spaces ("" when it is gone)."""
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:  # the process has ended
        return ""


def alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie does not)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
    except OSError:  # the process has ended
        return False
    return state != "Z"


def stop(proc: subprocess.Popen) -> None:
    """SIGKILL ``proc`` unless it has ended, and reap it (waiting at most 10 s)."""
    if proc.poll() is None:
        proc.kill()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:  # unkillable (D state): left to the caller's check
            pass


def last_line(text: str) -> str:
    """The last non-blank line of a stderr ("" when there is none)."""
    lines = (text or "").strip().splitlines()
    return lines[-1] if lines else ""


def first_traceback(text: str, n: int = 1500) -> str:
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


def files_under(root: Path) -> set[str]:
    """Every file and folder under ``root``, as paths relative to it."""
    out = set()
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            out.add(os.path.relpath(os.path.join(dirpath, name), root))
    return out



# -- a log's chunks, read with the mcap library ---------------------------------------------------------
#: where damage goes in a chunk: past its head (opcode, length, start and end times, sizes, CRC and
#: compression name: 52 bytes) and its LZ4 frame header (up to 15 bytes), and before the frame's end
#: mark.  Those fields are covered by no CRC and some are inert (a flipped bit of a time, of the
#: uncompressed size or of a block-size flag reads the very same records), so a reader that keeps
#: such a chunk is right; in the compressed payload the chunk's CRC must catch every flip.
PAYLOAD = (80, 8)


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



# -- bad input: scenario mutants, rebuilt FMUs ----------------------------------------------------------
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

