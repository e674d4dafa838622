"""What ``hil bench robustness`` prints and writes: a terminal table, and the markdown report.
"""
from __future__ import annotations

import json

from ... import terminal


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
    """The terminal's view: per part its verdict, cases and figures, then the failures, every line within
    ``terminal.WIDTH`` (the same text as the markdown report's, wrapped)."""
    lines = [f"hil bench robustness, seed {doc['seed']}: {doc['wall_s']} s, load {doc['load_before']} -> "
             f"{doc['load_after']}", ""]
    for name, r in doc["parts"].items():
        lines.append(terminal.wrap(f"{name:<10} {'pass' if r['passed'] else 'FAIL':<5} {r['cases']:>5} cases  "
                                   f"{headline(r)}", indent=" " * 11, first=""))
        lines.append(terminal.wrap(f"target: {r['target']}", indent=" " * 19, first=" " * 11))
    failures = [(name, f) for name, r in doc["parts"].items() for f in r["failures"]]
    if failures:
        lines += ["", terminal.wrap(f"{len(failures)} failure(s); repeat with: {doc['command']}", indent="    ")]
        lines += [terminal.wrap(f"  {name} case {f['case']}: {f['what']}: {f['detail']}", indent="    ")
                  for name, f in failures]
    else:
        lines += ["", "0 failures"]
    return "\n".join(lines)


def markdown(doc: dict) -> str:
    lines = [f"# {doc['command']}", "",
             f"Written by `{doc['command']} --report docs/benchmarks` on {doc['utc']}, {doc['machine']}, {doc['cores']} cores "
             f"(load average {doc['load_before']} before, {doc['load_after']} after); {doc['wall_s']} s in all.  "
             "The seed was drawn at run time; the command above repeats every case.  What each part does: "
             "`hil/benchmarks/robustness/`.", "",
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
