"""Checks as data: a TOML file of ``[[check]]`` tables (``hil check LOG CHECKS.toml``, and the
``test_*.toml`` files the pytest plugin collects), for engineers who do not write Python.

    scenario = "../ffcc_a.toml"          # what the plugin runs (relative to this file); hil check ignores it
    set = { "run.duration_s" = 1.0 }     # --set items
    seed = 1                             # optional; strategy = "gp" optional

    [[check]]
    kind = "in_range"                    # in_range | limit | responds | cycle_time | settles | torque_sign
    signal = "TcuStatus.MuHat"
    lo = 0.0
    hi = 0.35
    during = ["fault", 0.0, 0.3]         # or "fault" (to the end); left out: the whole run
    valid = "TcuStatus.ObserverValid"
    req = "REQ-OBS-1"                    # optional, with name

Every field is checked when the file is read: a wrong one is one ``ConfigError`` line naming the file,
the check (its number and name) and the field.  The fields of each kind are ``FIELDS``; the reference
page is docs/reference/checks.md.
"""
from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import ConfigError
from .kinds import Check, cycle_time, in_range, limit, responds, settles, torque_sign

_NUM, _STR, _WINDOW, _PAIR = "a number", "a string", "a window", "a pair of numbers"

#: kind -> (builder, {field: (type, required)}); every kind also takes name and req (strings)
FIELDS: dict[str, tuple] = {
    "in_range": (in_range, {"signal": (_STR, True), "lo": (_NUM, False), "hi": (_NUM, False),
                            "during": (_WINDOW, False), "valid": (_STR, False)}),
    "limit": (limit, {"key": (_STR, True), "lo": (_NUM, False), "hi": (_NUM, False)}),
    "responds": (responds, {"trigger": (_STR, True), "condition": (_STR, True), "within_s": (_NUM, True),
                            "during": (_WINDOW, False)}),
    "cycle_time": (cycle_time, {"frame": (_STR, True), "nominal_s": (_NUM, True), "tolerance_s": (_NUM, True),
                                "during": (_WINDOW, False), "max_outside_fraction": (_NUM, False)}),
    "settles": (settles, {"signal": (_STR, True), "band": (_PAIR, True), "within_s": (_NUM, True),
                          "hold_s": (_NUM, True), "after": (_WINDOW, False), "valid": (_STR, False)}),
    "torque_sign": (torque_sign, {"torque": (_STR, True), "demand": (_STR, True), "during": (_WINDOW, False),
                                  "tolerance": (_NUM, False)}),
}
#: the keys a file may hold outside its [[check]] tables
TOP = {"scenario": _STR, "set": "a table", "seed": "an integer", "strategy": _STR, "description": _STR,
       "check": "an array of tables"}

#: the argument name of a field where the builder calls it otherwise
_ARG = {"key": "summary_key"}


@dataclass
class Suite:
    """A checks file read: its checks and (for the plugin) the run they judge."""
    path: str
    checks: list[Check]
    scenario: str | None = None                 # resolved against the file's directory
    set: dict = field(default_factory=dict)
    seed: int | None = None
    strategy: str | None = None


def _typed(value, typ) -> bool:
    if typ == _NUM:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if typ == _STR:
        return isinstance(value, str) and value != ""
    if typ == _PAIR:
        return (isinstance(value, list) and len(value) == 2
                and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value))
    if typ == _WINDOW:
        return (isinstance(value, str) and value != "") or (
            isinstance(value, list) and len(value) in (2, 3) and isinstance(value[0], str)
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value[1:]))
    return True


def _show(value) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def parse_checks(text: str, path: str = "<checks>") -> Suite:
    """The suite in ``text`` (TOML); ConfigError naming ``path``, the check and the field for anything wrong."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not valid TOML: {e}") from None
    for key, value in data.items():
        if key not in TOP:
            raise ConfigError(f"{path}: unknown key {key!r} (a file holds {', '.join(TOP)})")
    tables = data.get("check")
    if not isinstance(tables, list) or not tables or not all(isinstance(t, dict) for t in tables):
        raise ConfigError(f"{path}: no [[check]] tables (each check is a [[check]] table with a kind)")
    checks = [_check(path, i, t) for i, t in enumerate(tables, start=1)]
    scenario = data.get("scenario")
    if scenario is not None and not _typed(scenario, _STR):
        raise ConfigError(f"{path}: scenario: expected a path string, got {_show(scenario)}")
    overrides = data.get("set", {})
    if not isinstance(overrides, dict):
        raise ConfigError(f"{path}: set: expected a table of TABLE.KEY = value, got {_show(overrides)}")
    seed = data.get("seed")
    if seed is not None and (not isinstance(seed, int) or isinstance(seed, bool)):
        raise ConfigError(f"{path}: seed: expected an integer, got {_show(seed)}")
    strategy = data.get("strategy")
    if strategy is not None and not _typed(strategy, _STR):
        raise ConfigError(f"{path}: strategy: expected a strategy name, got {_show(strategy)}")
    if scenario is not None and path != "<checks>":
        scenario = str((Path(path).parent / scenario))
    return Suite(path, checks, scenario, overrides, seed, strategy)


def _check(path: str, i: int, table: dict) -> Check:
    name = table.get("name")
    where = f"{path}: [[check]] {i}" + (f" ({name})" if isinstance(name, str) else "")
    kind = table.get("kind")
    if kind not in FIELDS:
        got = "no kind" if kind is None else f"kind {_show(kind)}"
        raise ConfigError(f"{where}: {got}; expected kind = one of {', '.join(FIELDS)}")
    build, fields = FIELDS[kind]
    args = {}
    for key, value in table.items():
        if key in ("kind",):
            continue
        if key in ("name", "req"):
            if not _typed(value, _STR):
                raise ConfigError(f"{where}: field {key!r}: expected a string, got {_show(value)}")
            args[key] = value
            continue
        if key not in fields:
            raise ConfigError(f"{where}: field {key!r} is not one of a {kind} check's: "
                              f"{', '.join([*fields, 'name', 'req'])}")
        typ = fields[key][0]
        if not _typed(value, typ):
            raise ConfigError(f"{where}: field {key!r}: expected {typ}, got {_show(value)}"
                              + (" (e.g. \"fault\" or [\"fault\", 0.0, 0.3])" if typ == _WINDOW else ""))
        args[_ARG.get(key, key)] = value
    missing = [k for k, (_, required) in fields.items() if required and _ARG.get(k, k) not in args]
    if missing:
        raise ConfigError(f"{where}: missing field {missing[0]!r} (a {kind} check needs "
                          f"{', '.join(k for k, (_, r) in fields.items() if r)})")
    try:
        check = build(**args)
    except ConfigError as e:
        raise ConfigError(f"{where}: {e}") from None
    check.where = where
    return check


def judge(suite: Suite, run) -> list:
    """Every check of ``suite`` judged over ``run``: the results, in the file's order.  A check naming a
    signal, frame or event the run does not have is a ConfigError naming the file and the check."""
    results = []
    for check in suite.checks:
        try:
            results.append(check(run))
        except ConfigError as e:
            raise ConfigError(f"{check.where}: {e}") from None
    return results


def load_checks(path) -> Suite:
    """Read the checks file at ``path`` (``parse_checks``); ConfigError when it cannot be read."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as e:
        raise ConfigError(f"{path}: cannot read: {e.strerror or e}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text file (UTF-8)") from None
    return parse_checks(text, str(path))
