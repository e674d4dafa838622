"""Logs that survive damage: a real run's MCAP with a byte flipped inside a chunk, bytes zeroed early in
the file, cut short, or both; ``hil.log.read.read_log`` must recover every chunk the damage left intact,
say where the damage is, and not call a log closed properly after a fault damaged.

The expectation comes from the undamaged file read with the ``mcap`` library's own readers (which
messages each chunk holds, at which bytes), never from the reader under test.  Positions are drawn
at test time from a printed seed."""
import collections
import json
import os
import random
import signal
import subprocess

import pytest
from hil.testing import PAYLOAD, chunk_map, expected_messages, in_payload, still_intact
from hil.log.read import read_log

from .conftest import ROOT, SCENARIOS, case_seed, hil, hil_command, subprocess_env


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    """A real 1 s run, its bytes, and per chunk (first byte, end byte, [(topic, log_time)]) as the mcap
    library reads them (``hil.testing.chunk_map``, shared with ``hil bench robustness``)."""
    out = tmp_path_factory.mktemp("log")
    r = hil("run", SCENARIOS / "ffcc_a.toml", "--bus", "inprocess", "--out", out, "--no-rrd", "--json")
    assert r.returncode == 0, r.stderr
    data, chunks = chunk_map(out / "ffcc_a-gp-1.mcap")
    assert len(chunks) >= 10
    return data, chunks


def _seed() -> random.Random:
    seed = case_seed("damage")
    return random.Random(seed)


def _read(tmp_path, data: bytes):
    path = tmp_path / "damaged.mcap"
    path.write_bytes(data)
    return read_log(path)


_in_payload = in_payload          # where damage goes in a chunk: its compressed payload (PAYLOAD)
_expect = expected_messages


def _got(contents) -> collections.Counter:
    return collections.Counter((topic, t) for topic, t, _ in contents.messages)


def test_the_whole_log_reads_as_the_mcap_library_reads_it(log, tmp_path):
    data, chunks = log
    got = _read(tmp_path, data)
    assert got.complete and not got.damaged and got.damage == "" and got.ended_early == ""
    assert _got(got) == _expect(chunks, lambda a, b: True)


def test_a_flipped_byte_in_a_middle_chunk_loses_that_chunk_only(log, tmp_path):
    data, chunks = log
    rng = _seed()
    for _ in range(5):
        i = rng.randrange(len(chunks) // 4, 3 * len(chunks) // 4)
        a, b, msgs = chunks[i]
        at = _in_payload(rng, a, b)
        bad = bytearray(data)
        bad[at] ^= 1 << rng.randrange(8)
        got = _read(tmp_path, bytes(bad))
        if still_intact(data, bytes(bad), a):       # an inert flip: the records decompress unchanged
            print(f"chunk {i}: the flip at byte {at} is inert (lz4 gives the same records)")
            assert _got(got) == _expect(chunks, lambda x, y: True), (i, at)
            continue
        assert _got(got) == _expect(chunks, lambda x, y: x != a), (i, at)
        assert got.message_count == sum(len(m) for _, _, m in chunks) - len(msgs)
        assert not got.complete and not got.cut and f"bytes {a}-{b}" in got.damage, (at, got.damage)
        assert got.skipped_bytes == b - a and "summary" in got.metadata and "scenario" in got.metadata


def test_zeroed_bytes_early_in_the_file_lose_nothing_else(log, tmp_path):
    """16 zero bytes somewhere in the first 4 KB (header, metadata, the first chunk)."""
    data, chunks = log
    rng = _seed()
    for _ in range(5):
        at = rng.randrange(8, 4096)
        bad = bytearray(data)
        bad[at:at + 16] = bytes(16)
        got = _read(tmp_path, bytes(bad))
        assert _got(got) == _expect(chunks, lambda a, b: b <= at or a >= at + 16), at
        if bytes(bad) != data and not got.complete:
            assert got.damaged and all(str(x) in got.damage for x in got.damaged[0][:2]), got.damage


def test_a_cut_log_keeps_every_chunk_before_the_cut(log, tmp_path):
    data, chunks = log
    rng = _seed()
    for _ in range(5):
        cut = rng.randrange(len(data) // 4, len(data) - 1)
        got = _read(tmp_path, data[:cut])
        assert _got(got) == _expect(chunks, lambda a, b: b <= cut), cut
        assert got.cut and not got.complete and str(cut) in got.damage, got.damage


def test_damage_in_the_middle_of_a_cut_log_is_stepped_over(log, tmp_path):
    """No summary to go by: records are read in order and the reader searches on for the next chunk
    whose CRC matches.  The damage hits a chunk's data or its length field."""
    data, chunks = log
    rng = _seed()
    for where in ("data", "length", "data", "length"):
        i = rng.randrange(2, len(chunks) // 2)
        a, b, _ = chunks[i]
        bad = bytearray(data)
        if where == "data":
            bad[_in_payload(rng, a, b)] ^= 0xFF
            if still_intact(data, bytes(bad), a):      # an inert flip (lz4 gives the same records): none
                print(f"chunk {i}: inert flip, drawn again")
                continue
        else:
            bad[a + 1:a + 9] = rng.randbytes(8)
        cut = rng.randrange(chunks[-3][0], len(data) - 1)
        got = _read(tmp_path, bytes(bad[:cut]))
        assert _got(got) == _expect(chunks, lambda x, y: x != a and y <= cut), (where, i, cut)
        assert got.cut and got.damaged[0][0] == a, got.damaged


def test_channels_lost_with_the_first_chunk_are_rebuilt(log, tmp_path):
    """The first chunk holds every schema and channel record; damaged there and cut (no summary to
    repeat them), a railway-hil log's channels are rebuilt from hil.log.schemas.TOPICS."""
    data, chunks = log
    rng = _seed()
    a, b, _ = chunks[0]
    while True:                  # a flip that changes the records (an inert one is drawn again)
        bad = bytearray(data)
        bad[_in_payload(rng, a, b)] ^= 0x55
        if not still_intact(data, bytes(bad), a):
            break
    cut = chunks[-2][0] + 10
    got = _read(tmp_path, bytes(bad[:cut]))
    assert _got(got) == _expect(chunks, lambda x, y: x != a and y <= cut)
    assert got.rebuilt_channels >= 5 and "rebuilt from hil.log.schemas.TOPICS" in got.damage
    states = got.topic("/plant/state")
    assert states and all(s.t_s == pytest.approx(s.step * 1e-3) for s in states)


def test_replay_of_a_log_with_a_damaged_chunk_names_the_bytes(log, tmp_path):
    data, chunks = log
    a, b, _ = chunks[len(chunks) // 2]
    for at in range((a + b) // 2, b - PAYLOAD[1]):   # the first flip from the middle that is not inert
        bad = bytearray(data)
        bad[at] ^= 0x08
        if not still_intact(data, bytes(bad), a):
            break
    path = tmp_path / "hole.mcap"
    path.write_bytes(bytes(bad))
    r = subprocess.run(hil_command() + ["replay", str(path), "--json"], capture_output=True, text=True,
                       env=subprocess_env(), timeout=120, cwd=ROOT)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 0 and len(lines) == 1 and "is damaged" in lines[0] and f"bytes {a}-{b}" in lines[0], r.stderr
    s = json.loads(r.stdout)
    assert s["messages_read"] == sum(len(m) for _, _, m in chunks) - len(chunks[len(chunks) // 2][2])


def test_a_log_closed_after_a_fault_is_not_called_damaged(tmp_path):
    """The TCU killed mid-run: exit 3, the log closed properly with the fault; reading it says the run
    did not finish, not that the log is damaged, and so does hil replay."""
    from .test_bus import children_of, cmdline, wait_for

    path = tmp_path / "ffcc_a-gp-1.mcap"
    proc = subprocess.Popen(hil_command() + ["run", "scenarios/ffcc_a.toml", "--bus", "local", "--out", str(tmp_path),
                                             "--no-rrd", "--set", "run.duration_s=60", "--set", "run.fault_time_s=55"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=subprocess_env(), cwd=ROOT)
    wait_for(lambda: path.exists() and path.stat().st_size > 100_000 or proc.poll() is not None, 120, "the run")
    tcu = [p for p in children_of(proc.pid) if "hil.tcu_node" in cmdline(p)]
    assert len(tcu) == 1, proc.communicate()
    os.kill(tcu[0], signal.SIGKILL)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 3, err
    got = read_log(path)
    assert not got.complete and not got.cut and got.damage == "" and not got.damaged
    assert got.ended_early.startswith("fault at step ") and "TCU process was killed by SIGKILL" in got.ended_early
    assert got.problem().startswith("the run did not finish (fault at step ") and "closed properly" in got.problem()
    r = hil("replay", path, "--json", cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert "damaged" not in r.stderr and "holds a run that did not finish (fault at step" in r.stderr
    assert "the log was closed properly" in r.stderr

