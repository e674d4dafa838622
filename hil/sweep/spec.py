"""A sweep file (TOML) -> the points of the study, every axis value checked before anything runs.

    base = "../ffcc_a.toml"        # the base scenario, relative to this file (required)
    transport = "inprocess"        # "inprocess" (lockstep, one process per point: the default) or
                                   # "process" (plant and TCU processes on a local bus of their own)
    strategy = "gp"                # the strategy when no axis sets it (default: DEFAULT_STRATEGY, gp)
    seed = 1                       # the run seed when no axis sets it (default: the scenario's)
    combine = "product"            # "product": every combination of the axes' values (the default);
                                   # "zip": the i-th value of every axis together (equal lengths)
    [set]                          # fixed overrides of every point, the --set syntax
    "run.duration_s" = 1.0

    [axes."run.mu_required"]       # any scenario field in the --set syntax: a grid ...
    values = [0.155, 0.16, 0.165]
    [axes."sensors.motor_speed_noise_rad_s"]   # ... or seeded random draws
    log_uniform = [0.001, 0.02]    # or uniform = [lo, hi], integers = [lo, hi] (inclusive)
    draws = 3
    seed = 7                       # required: the same file gives the same points (and --resume works)
    [axes.strategy]                # the identification strategy
    values = ["nlls", "bayes"]
    [axes.seed]                    # the run seed (sensor noise and identifier)
    range = [1, 4]                 # first and last, inclusive (any integer field takes range)
    [axes.family]                  # fault curves drawn from plant/families.py (a curve and mu_required)
    family = "default"
    draws = 4                      # indices 0..draws-1, or indices = [...]
    seed = 12345
    [axes.reality]                 # --reality effects: "" for none, one spec, or a list of specs
    values = ["", "load_transfer:bogie_height_m=1.5", ["can:delay_ms=3", "sensor_delay:delay_ms=2"]]

Each axis value is checked against the base once (the field exists, the value has its type and range,
the strategy and effect exist, the family exists; an axis of more than ``MAX_CHECKED`` distinct values
at its first ones and its extremes); an error is one ``ConfigError`` line naming the
sweep file and the axis.  Combinations are not checked ahead (a point whose combination is refused
by the scenario loader is a failed point with that line).  A point's ``key`` is a digest of
everything that makes it (base text, fixed overrides, transport, its inputs): ``--resume`` skips the
keys already in the table.
"""
from __future__ import annotations

import hashlib
import itertools
import json
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from identifier import DEFAULT_STRATEGY

from ..config import parse_scenario
from ..errors import ConfigError

TRANSPORTS = ("inprocess", "process")
COMBINE = ("product", "zip")
SPECIAL_AXES = ("strategy", "seed", "family", "reality")
RANDOM_KINDS = ("uniform", "log_uniform", "integers")
TOP_KEYS = ("base", "transport", "strategy", "seed", "combine", "set", "axes", "name", "description")
#: a sweep with more points is refused (a typo in draws = ... should not queue a billion runs)
MAX_POINTS = 10_000_000


@dataclass(frozen=True)
class Point:
    index: int
    key: str
    inputs: dict          # axis field -> value (a family axis: the draw index)


@dataclass
class Sweep:
    path: str
    name: str
    base_path: str
    base_text: str
    transport: str
    strategy: str
    seed: int | None
    overrides: dict                        # [set]
    axes: dict                             # field -> list of values, in file order
    family: dict | None = None             # {"family": name, "seed": S} when a family axis exists
    points: list = field(default_factory=list)

    def task(self, point: Point, keep_logs_dir: str | None = None) -> dict:
        """What a worker needs to run ``point`` (plain data: it travels to other machines)."""
        return {"index": point.index, "key": point.key, "inputs": point.inputs, "base_text": self.base_text,
                "base_path": self.base_path, "set": self.overrides, "transport": self.transport,
                "strategy": self.strategy, "seed": self.seed, "family": self.family, "keep_logs_dir": keep_logs_dir}


def _fail(path, where, msg) -> ConfigError:
    return ConfigError(f"{path}: {where}: {msg}".replace("\n", " "))


def load_sweep(path) -> Sweep:
    """Read and check a sweep file; raises ``ConfigError`` (one line) before anything runs."""
    p = Path(path)
    try:
        text = p.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such sweep file") from None
    except (IsADirectoryError, UnicodeDecodeError, OSError) as e:
        raise ConfigError(f"{path}: cannot read the sweep file ({type(e).__name__})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not valid TOML: {e}") from None
    return parse_sweep(data, str(path), p.parent)


def parse_sweep(data: dict, path: str = "<sweep>", folder: Path = Path(".")) -> Sweep:
    for key in data:
        if key not in TOP_KEYS:
            raise _fail(path, key, f"unknown key (known: {', '.join(TOP_KEYS)})")
    if not isinstance(data.get("base"), str):
        raise _fail(path, "base", "missing: the base scenario's path (relative to the sweep file)")
    base = Path(data["base"])
    base = base if base.is_absolute() else folder / base
    try:
        base_text = base.read_bytes().decode("utf-8")
    except OSError:
        raise _fail(path, "base", f"no scenario file {base}") from None
    transport = data.get("transport", "inprocess")
    if transport not in TRANSPORTS:
        raise _fail(path, "transport", f"must be one of {', '.join(TRANSPORTS)}, got {transport!r}")
    combine = data.get("combine", "product")
    if combine not in COMBINE:
        raise _fail(path, "combine", f"must be one of {', '.join(COMBINE)}, got {combine!r}")
    overrides = data.get("set", {})
    if not isinstance(overrides, dict) or any(isinstance(v, dict) for v in overrides.values()):
        raise _fail(path, "[set]", 'must hold "TABLE.KEY" = value pairs (the --set syntax)')
    try:
        base_scenario = parse_scenario(base_text, str(base), overrides)
    except ConfigError as e:
        raise _fail(path, "[set]", e) from None
    strategy = data.get("strategy", DEFAULT_STRATEGY)
    _check_strategy(path, "strategy", strategy)
    seed = data.get("seed")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2 ** 63):
        raise _fail(path, "seed", f"must be an integer in [0, 2^63), got {seed!r}")
    axes_raw = data.get("axes", {})
    if not isinstance(axes_raw, dict) or not axes_raw:
        raise _fail(path, "[axes]", "missing: at least one axis, e.g. [axes.\"run.mu_required\"] values = [...]")
    axes, family = {}, None
    for name, spec in axes_raw.items():
        where = f'[axes."{name}"]'
        if not isinstance(spec, dict):
            raise _fail(path, where, "must be a table (values = [...], or a random draw, or range = [a, b])")
        if name == "family":
            axes[name], family = _family_axis(path, where, spec)
        else:
            axes[name] = _axis_values(path, where, spec)
            _check_axis(path, where, name, axes[name], base_text, str(base), overrides)
    sweep = Sweep(path, str(data.get("name", Path(path).stem)), str(base), base_text, transport, strategy, seed,
                  dict(overrides), axes, family)
    sweep.points = make_points(sweep, combine, path)
    del base_scenario
    return sweep


def _check_strategy(path, where, name) -> None:
    from identifier import STRATEGIES

    if not isinstance(name, str) or name not in STRATEGIES:
        raise _fail(path, where, f"unknown strategy {name!r} (known: {', '.join(sorted(STRATEGIES))})")


def _axis_values(path, where, spec: dict) -> list:
    kinds = [k for k in ("values", "range", *RANDOM_KINDS) if k in spec]
    if len(kinds) != 1:
        raise _fail(path, where, "needs exactly one of values = [...], range = [first, last], "
                    + ", ".join(f"{k} = [lo, hi]" for k in RANDOM_KINDS))
    kind = kinds[0]
    allowed = {"values": {"values"}, "range": {"range"}}.get(kind, {kind, "draws", "seed"})
    for k in spec:
        if k not in allowed:
            raise _fail(path, f"{where} {k}", f"unknown key here (known: {', '.join(sorted(allowed))})")
    if kind == "values":
        values = spec["values"]
        if not isinstance(values, list) or not values:
            raise _fail(path, f"{where} values", f"must be a non-empty list, got {values!r}")
        return list(values)
    pair = spec[kind]
    if not isinstance(pair, list) or len(pair) != 2 or any(isinstance(x, bool) or not isinstance(x, (int, float))
                                                           for x in pair):
        raise _fail(path, f"{where} {kind}", f"must be [lo, hi] (two numbers), got {pair!r}")
    lo, hi = pair
    if kind == "range":
        if not all(isinstance(x, int) for x in pair) or hi < lo:
            raise _fail(path, f"{where} range", f"must be [first, last], integers with first <= last, got {pair!r}")
        if hi - lo + 1 > MAX_POINTS:
            raise _fail(path, f"{where} range", f"{hi - lo + 1} values: more than {MAX_POINTS} are refused")
        return list(range(lo, hi + 1))
    draws, seed = spec.get("draws"), spec.get("seed")
    if isinstance(draws, bool) or not isinstance(draws, int) or not 1 <= draws <= MAX_POINTS:
        raise _fail(path, f"{where} draws", f"must be an integer in [1, {MAX_POINTS}], got {draws!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise _fail(path, f"{where} seed", f"must be an integer >= 0 (random axes are seeded, so --resume finds "
                    f"the same points), got {seed!r}")
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise _fail(path, f"{where} {kind}", f"must be finite with lo <= hi, got {pair!r}")
    rng = np.random.default_rng([seed, 0x5EE])
    if kind == "uniform":
        return [float(x) for x in rng.uniform(lo, hi, draws)]
    if kind == "log_uniform":
        if lo <= 0:
            raise _fail(path, f"{where} log_uniform", f"needs lo > 0, got {pair!r}")
        return [float(x) for x in np.exp(rng.uniform(math.log(lo), math.log(hi), draws))]
    if not all(isinstance(x, int) for x in pair):
        raise _fail(path, f"{where} integers", f"must be two integers, got {pair!r}")
    return [int(x) for x in rng.integers(lo, hi, draws, endpoint=True)]


def _family_axis(path, where, spec: dict) -> tuple[list, dict]:
    from plant import families

    for k in spec:
        if k not in ("family", "draws", "indices", "seed"):
            raise _fail(path, f"{where} {k}", "unknown key here (known: family, draws, indices, seed)")
    name = spec.get("family", "default")
    if name not in families.FAMILIES:
        raise _fail(path, f"{where} family", f"unknown family {name!r} (known: {', '.join(families.FAMILIES)})")
    seed = spec.get("seed")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise _fail(path, f"{where} seed", f"must be an integer >= 0 (the draws' seed), got {seed!r}")
    if ("draws" in spec) == ("indices" in spec):
        raise _fail(path, where, "needs exactly one of draws = K (indices 0..K-1) or indices = [...]")
    if "draws" in spec:
        draws = spec["draws"]
        if isinstance(draws, bool) or not isinstance(draws, int) or not 1 <= draws <= MAX_POINTS:
            raise _fail(path, f"{where} draws", f"must be an integer in [1, {MAX_POINTS}], got {draws!r}")
        indices = list(range(draws))
    else:
        indices = spec["indices"]
        if not isinstance(indices, list) or not indices or any(
                isinstance(i, bool) or not isinstance(i, int) or i < 0 for i in indices):
            raise _fail(path, f"{where} indices", f"must be a non-empty list of integers >= 0, got {indices!r}")
    return list(indices), {"family": name, "seed": seed}


def _check_axis(path, where, name, values, base_text, base_path, overrides) -> None:
    """Every value of one axis against the base scenario (with [set]), one at a time."""
    if name == "strategy":
        for v in values:
            _check_strategy(path, f"{where} values", v)
        return
    if name == "seed":
        for v in values:
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < 2 ** 63:
                raise _fail(path, f"{where} values", f"a seed must be an integer in [0, 2^63), got {v!r}")
        return
    if name == "reality":
        from ..effects import parse_effect

        for v in values:
            for item in reality_items(v, lambda msg: _fail(path, f"{where} values", msg)):
                try:
                    parse_effect(item)
                except ValueError as e:
                    raise _fail(path, f"{where} values", e) from None
        return
    if "." not in name:
        raise _fail(path, where, f"not a scenario field: use TABLE.KEY as --set does (e.g. run.mu_required), or one "
                    f"of {', '.join(SPECIAL_AXES)}")
    if name in overrides:
        raise _fail(path, where, "also fixed in [set]; an axis and [set] cannot both set it")
    seen = set()
    for v in checked_values(values):
        if isinstance(v, dict):
            raise _fail(path, f"{where} values", f"a table is not a field value: {v!r}")
        token = json.dumps(v, sort_keys=True)
        if token in seen:
            continue
        seen.add(token)
        try:
            parse_scenario(base_text, base_path, {**overrides, name: v})
        except ConfigError as e:
            raise _fail(path, f"{where} value {v!r}", e) from None


#: at most this many distinct values of one field axis are loaded into the base ahead (plus its extremes)
MAX_CHECKED = 256


def checked_values(values: list) -> list:
    """The values of a field axis checked ahead: all distinct ones up to ``MAX_CHECKED``, else the first
    ``MAX_CHECKED`` and, for numbers, the smallest and the largest (a long random axis is checked at its
    bounds; every other value is still checked when its point loads)."""
    distinct = list({json.dumps(v, sort_keys=True): v for v in values}.values())
    if len(distinct) <= MAX_CHECKED:
        return distinct
    out = distinct[:MAX_CHECKED]
    numbers = [v for v in distinct if isinstance(v, (int, float)) and not isinstance(v, bool)]
    if numbers:
        out += [min(numbers), max(numbers)]
    return out


def reality_items(value, fail) -> list[str]:
    """An axis value of ``reality`` -> the ``--reality`` specs it stands for ("" or "none": none)."""
    if isinstance(value, str):
        return [] if value.strip() in ("", "none") else [value]
    if isinstance(value, list) and all(isinstance(x, str) for x in value):
        return [x for x in value if x.strip() not in ("", "none")]
    raise fail(f"a reality value is a --reality spec string or a list of them, got {value!r}")


def make_points(sweep: Sweep, combine: str, path: str) -> list[Point]:
    names = list(sweep.axes)
    lists = [sweep.axes[n] for n in names]
    if combine == "zip":
        lengths = {len(v) for v in lists}
        if len(lengths) != 1:
            raise _fail(path, "combine", "zip needs axes of equal length, got " + ", ".join(
                f"{n}: {len(v)}" for n, v in zip(names, lists)))
        combos = zip(*lists)
        total = lengths.pop()
    else:
        total = math.prod(len(v) for v in lists)
        combos = itertools.product(*lists)
    if total > MAX_POINTS:
        raise _fail(path, "[axes]", f"{total} points: more than {MAX_POINTS} are refused")
    digest = hashlib.sha256(json.dumps({"base": sweep.base_text, "set": sweep.overrides, "transport": sweep.transport,
                                        "strategy": sweep.strategy, "seed": sweep.seed, "family": sweep.family},
                                       sort_keys=True).encode()).hexdigest()
    points, seen = [], {}
    for i, combo in enumerate(combos):
        inputs = dict(zip(names, combo))
        token = json.dumps(inputs, sort_keys=True)
        seen[token] = seen.get(token, -1) + 1       # the same inputs twice (e.g. a repeated draw): two points
        key = hashlib.sha256(f"{digest}{token}#{seen[token]}".encode()).hexdigest()[:16]
        points.append(Point(i, key, inputs))
    return points
