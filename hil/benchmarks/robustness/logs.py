"""Part ``logs``: a real run's MCAP damaged in many ways (``damage_log``); ``hil.log.read.read_log``
must recover every message of every chunk the damage left intact, and nothing else.
"""
from __future__ import annotations

import collections
import json
import random
import subprocess
import tempfile
from pathlib import Path

from ...errors import ConfigError
from ...testing import ROOT, SCENARIOS, chunk_map, expected_messages, hil_cmd, in_payload, last_line, still_intact, \
    subprocess_env
from .probe import RUN_TIMEOUT_S, Part

DAMAGES = ("flip", "flips", "zero_early", "cut", "flip_cut", "length_cut", "first_cut")


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



def part_logs(seed: int, count: int, log) -> dict:
    from ...log.read import read_log
    from ...progress import Progress

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
            part.fail("run", "the run to damage failed", last_line(r.stderr))
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
