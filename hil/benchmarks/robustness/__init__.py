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
- ``scenarios``: ``--scenarios`` mutants of a full scenario file (``hil.testing.mutate``) loaded in process, each
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

Each part is a module of this package (``frames``, ``scenarios``, ``logs``, ``fmus``, ``kills``,
``disk``, ``memory``: ``part_NAME(seed, counts..., log)`` returns the record of ``probe.Part``);
``report`` writes the table and the markdown.  What a probe shares with the tests (``hil`` as a
subprocess, a log's chunk map, the scenario mutants) is ``hil.testing``.

The result: a terminal table by default (lines within ``hil.terminal.WIDTH``), the markdown report
with ``--markdown``, one JSON object with ``--json``, and with ``--report DIR``
``DIR/robustness.md`` and ``DIR/robustness.json``.  Exit code 1 when a probe failed.
"""
from __future__ import annotations

import json
import os
import platform
import secrets
import sys
import time
from pathlib import Path

from ...errors import ConfigError
from .disk import part_disk
from .fmus import part_fmus
from .frames import part_frames
from .kills import part_kills
from .logs import part_logs
from .memory import part_memory
from .report import markdown, table
from .scenarios import part_scenarios

PARTS = ("frames", "scenarios", "logs", "fmus", "kills", "disk", "memory")


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
    p.add_argument("--markdown", action="store_true", help="print the report as markdown (every figure in one table; "
                   "what --report writes to robustness.md)")
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
    print(json.dumps(doc) if args.json else markdown(doc) if args.markdown else table(doc))
    if not doc["passed"]:
        log(f"bench robustness: failures found; repeat with: {cmd}")
    return 0 if doc["passed"] else 1
