"""A recorded run as the checks see it: its summary, its events and its signals as numpy arrays.

``Run.open(path)`` reads an MCAP log written by ``hil run`` (``hil.log.read.read_log``) once; each
signal is decoded on first use and kept.  Signals are named two ways:

- as in the DBC, ``Message.Signal`` (``PlantSensor.MotorSpeed``, ``TcuStatus.MuHat``,
  ``TorqueCommand.TorqueCmd``): decoded from the ``/can/frames`` topic (every frame on the bus, with
  the simulated time of its exchange step and its receive wall time) with the DBC the run used (the
  log's ``dbc`` metadata; ``hil/hil.dbc`` when the log has none).  Frames the receiving node rejected
  (``hil.bus.verdicts``) are left out: they never reached the plant or the TCU; so are a mapped bus's
  answers to the plant's start-up probes (before step 0, not part of the run).
- as log topic and field, ``/topic.field`` (``/plant/state.creep_speed_kmh``, ``/tcu/observer.mu_hat``).

A signal is a ``Series``: times ``t_s`` (simulated seconds since the run's start), values, unit (the
DBC's, or read from the field name's unit suffix), and for frames the receive wall times ``wall_s``.

Events are times in the run a check's window can start from: ``start`` (0), ``fault``, ``serious``,
``detection``, ``identification`` (the summary's ``t_fault_s``, ``t_serious_s``, ``t_detected_s``,
``t_identified_s``), ``rail.N`` (the start of rail segment N, from 0, of a scenario with ``[[rail]]``),
and any other summary key ``t_NAME_s`` by ``NAME``.  ``None`` when it did not happen in this run (no
detection, no identification, a segment after the run's end).
"""
from __future__ import annotations

import difflib
import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ConfigError, LogError

#: event name -> the summary key that dates it
EVENTS = {"fault": "t_fault_s", "serious": "t_serious_s", "detection": "t_detected_s",
          "identification": "t_identified_s"}

#: a field name's unit suffix -> its unit (the project names units in field names)
_SUFFIX_UNITS = (("_rad_s", "rad/s"), ("_kmh", "km/h"), ("_ms", "m/s"), ("_nm", "N.m"), ("_us", "us"),
                 ("_percent", "%"), ("_s", "s"))


@dataclass
class Series:
    """One signal: ``t_s`` and ``values`` (float arrays of the same length), ``unit``, and for a frame's
    signal ``wall_s`` (receive wall times, in s since the first frame of the log)."""
    name: str
    t_s: np.ndarray
    values: np.ndarray
    unit: str = ""
    wall_s: np.ndarray | None = None

    def at(self, t_s: np.ndarray) -> np.ndarray:
        """The value held at each of ``t_s`` (zero-order hold: the newest sample at or before it; NaN
        before the first)."""
        i = np.searchsorted(self.t_s, t_s, side="right") - 1
        out = np.full(len(t_s), np.nan)
        ok = i >= 0
        out[ok] = self.values[i[ok]]
        return out


def _unit_of(field_name: str) -> str:
    for suffix, unit in _SUFFIX_UNITS:
        if field_name.endswith(suffix):
            return unit
    return ""


@dataclass
class Run:
    """A run to judge: ``summary`` (the ``hil run --json`` dict), ``path`` of its log, the log's contents
    (``log``, a ``hil.log.read.LogContents``) and what ``hil_run`` adds (``command`` that reproduces it,
    ``rrd`` path)."""
    path: str
    summary: dict
    log: object
    command: str = ""
    rrd: str | None = None
    _series: dict = field(default_factory=dict, repr=False)
    _frames: dict | None = field(default=None, repr=False)
    _dbc: object = field(default=None, repr=False)
    _wall0: int = field(default=0, repr=False)

    @classmethod
    def open(cls, path, summary: dict | None = None, **extra) -> "Run":
        """Read the log at ``path``; ``summary`` given (a failed run's partial summary) or read from the
        log.  LogError (one line) for a file that is not a readable ``hil run`` log."""
        from ..log.read import read_log

        log = read_log(path)
        if not log.metadata and not log.message_count:
            raise LogError(f"{path}: nothing readable ({log.damage or 'an empty log'})")
        if summary is None:
            summary = _summary_of(log)
        return cls(str(path), summary, log, **extra)

    # -- what the run ran ----------------------------------------------------------------------------
    @property
    def mode(self) -> str:
        return self.summary.get("mode") or (self.log.metadata.get("run") or {}).get("mode", "lockstep")

    @property
    def period_s(self) -> float:
        meta = (self.log.metadata.get("run") or {}).get("exchange_period_s")
        return float(meta) if meta else 1e-3

    @property
    def duration_s(self) -> float:
        return float(self.summary.get("sim_s") or _scenario_value(self.log, "run", "duration_s") or 0.0)

    @property
    def planned_duration_s(self) -> float:
        """The simulated time the run was to last (its scenario's ``run.duration_s``, overrides applied):
        more than ``duration_s`` for a run that ended early."""
        planned = _scenario_value(self.log, "run", "duration_s")
        return max(float(planned), self.duration_s) if planned else self.duration_s

    def event(self, name: str) -> float | None:
        """The time (s) of event ``name`` (module docstring), None when it did not happen; ConfigError for
        a name that is no event."""
        if name == "start":
            return 0.0
        if name.startswith("rail."):
            return self._rail_start(name)
        key = EVENTS.get(name, name if name in self.summary else f"t_{name}_s")
        if key not in self.summary and key != "t_fault_s":
            known = ["start", *EVENTS] + sorted(k[2:-2] for k in self.summary if k.startswith("t_") and k.endswith("_s"))
            raise ConfigError(f"unknown event {name!r}; known: {', '.join(dict.fromkeys(known))}")
        value = self.summary.get(key)
        if value is None and key == "t_fault_s":
            value = _scenario_value(self.log, "run", "fault_time_s")
        return None if value is None else float(value)

    def _rail_start(self, name: str) -> float | None:
        segs = _scenario_table(self.log, "rail") or []
        n = name.split(".", 1)[1]
        if not (n.isdigit() and int(n) < len(segs)):
            raise ConfigError(f"unknown event {name!r}: the run's scenario has "
                              + (f"rail segments rail.0 .. rail.{len(segs) - 1}" if segs else "no [[rail]] segments"))
        overrides = _overrides(self.log)
        start = overrides.get(f"rail.{n}.start_s", segs[int(n)].get("start_s", 0.0))
        return float(start) if float(start) <= self.duration_s else None

    def fault(self) -> str:
        """Why the run ended early (the log's fault or damage), '' for a run that finished."""
        return self.summary.get("fault") or self.log.problem()

    # -- signals -------------------------------------------------------------------------------------
    def signal(self, name: str) -> Series:
        """The signal ``name`` (module docstring); ConfigError naming the close matches for one the log
        does not have."""
        if name not in self._series:
            self._series[name] = self._topic_field(name) if name.startswith("/") else self._dbc_signal(name)
        return self._series[name]

    def frame_times(self, frame: str) -> tuple[np.ndarray, np.ndarray]:
        """(t_s, wall_s) of every accepted frame named ``frame`` in the DBC."""
        message = self._message(frame)
        rows = self._frame_rows().get(message.frame_id, [])
        return np.array([r[0] for r in rows], dtype=float), self._wall_s(rows)

    def frames_end(self) -> tuple[float, float]:
        """(t_s, wall_s) of the log's last accepted frame of any id: where the bus's record ends (a frame
        that stops before it fell silent)."""
        rows = [r for rr in self._frame_rows().values() for r in rr]
        if not rows:
            return 0.0, 0.0
        return max(r[0] for r in rows), (max(r[1] for r in rows) - self._wall0) * 1e-9

    def _wall_s(self, rows) -> np.ndarray:
        """Receive wall times in s since the log's first frame (from integer ns: seconds since the epoch
        as doubles would keep only 0.4 us)."""
        return (np.array([r[1] for r in rows], dtype=np.int64) - self._wall0) * 1e-9

    def _topic_field(self, name: str) -> Series:
        topic, _, fname = name.rpartition(".")
        from ..log.schemas import MESSAGES, TOPICS

        if topic not in TOPICS:
            raise ConfigError(f"signal {name!r}: no topic {topic!r}; topics: {', '.join(TOPICS)}")
        fields = [f for f, typ, repeated in MESSAGES[TOPICS[topic]] if not repeated and typ not in ("string", "bytes")]
        if fname not in fields:
            raise ConfigError(f"signal {name!r}: {topic} has no numeric field {fname!r}; fields: {', '.join(fields)}")
        msgs = self.log.topic(topic)
        t = np.array([m.t_s for m in msgs], dtype=float)
        v = np.array([float(getattr(m, fname)) for m in msgs], dtype=float)
        order = np.argsort(t, kind="stable")
        return Series(name, t[order], v[order], _unit_of(fname))

    def _db(self):
        if self._dbc is None:
            import cantools

            text = (self.log.metadata.get("dbc") or {}).get("text")
            if text:
                self._dbc = cantools.database.load_string(text, database_format="dbc")
            else:                        # a log of a version that did not record its DBC
                self._dbc = cantools.database.load_file(str(Path(__file__).resolve().parents[1] / "hil.dbc"),
                                                        database_format="dbc")
        return self._dbc

    def _message(self, frame: str):
        db = self._db()
        try:
            return db.get_message_by_name(frame)
        except KeyError:
            names = [m.name for m in db.messages]
            close = difflib.get_close_matches(frame, names, n=3)
            raise ConfigError(f"no frame {frame!r} in the run's DBC" + (f" (did you mean {', '.join(close)}?)" if close
                              else f"; frames: {', '.join(names)}")) from None

    def _frame_rows(self) -> dict:
        """frame id -> [(t_s, wall_time_ns, data)] of the frames the receiving node did not reject."""
        if self._frames is None:
            from ..bus.verdicts import PROBE, REJECTED, kind

            rows: dict[int, list] = {}
            for f in self.log.topic("/can/frames"):
                if f.is_error_frame or f.is_remote_frame or kind(f.status or "ok") == REJECTED or f.status == PROBE:
                    continue
                rows.setdefault(f.arbitration_id, []).append((f.t_s, f.wall_time_ns, f.data))
            self._frames = rows
            self._wall0 = min((r[1] for rr in rows.values() for r in rr), default=0)
        return self._frames

    def _dbc_signal(self, name: str) -> Series:
        frame, _, sig = name.partition(".")
        if not sig:
            raise ConfigError(f"signal {name!r}: expected Message.Signal (as in the DBC) or /topic.field")
        message = self._message(frame)
        names = [s.name for s in message.signals]
        if sig not in names:
            close = difflib.get_close_matches(sig, names, n=3)
            raise ConfigError(f"signal {name!r}: {frame} has no signal {sig!r}"
                              + (f" (did you mean {', '.join(close)}?)" if close else f"; signals: {', '.join(names)}"))
        rows = self._frame_rows().get(message.frame_id, [])
        t = np.array([r[0] for r in rows], dtype=float)
        wall = self._wall_s(rows)
        order = np.argsort(t, kind="stable")
        values = {n: np.full(len(rows), np.nan) for n in names}
        for i, (_, _, data) in enumerate(rows):
            try:
                decoded = message.decode(data, decode_choices=False)
            except Exception:  # noqa: BLE001 - an undecodable frame is a missing sample (NaN)
                continue
            for n, x in decoded.items():
                values[n][i] = float(x)
        for n in names:                   # every signal of the frame decoded once, kept
            self._series.setdefault(f"{frame}.{n}", Series(f"{frame}.{n}", t[order], values[n][order],
                                                           message.get_signal_by_name(n).unit or "",
                                                           wall[order]))
        return self._series[name]


@dataclass
class CanLogContents:
    """A rig's CAN log (any format python-can reads) as far as checks need it: its frames as ``/can/frames``
    rows (simulated time = seconds since its first frame; receive wall time = the frame's timestamp), the
    DBC to decode them with as the log's ``dbc`` metadata.  No summary, no plant topics: a rig records
    frames only, so ``limit`` checks and plant signals have nothing to judge there (and fail saying so)."""
    rows: list
    metadata: dict
    damage: str = ""
    ended_early: str = ""

    @property
    def message_count(self) -> int:
        return len(self.rows)

    def topic(self, name: str) -> list:
        return self.rows if name == "/can/frames" else []

    def problem(self) -> str:
        return self.damage


@dataclass
class _CanRow:
    t_s: float
    wall_time_ns: int
    arbitration_id: int
    data: bytes
    is_error_frame: bool
    is_remote_frame: bool
    status: str = "ok"


def open_can_log(path, dbc_path) -> Run:
    """A ``Run`` of a rig's CAN log at ``path`` whose frames ``dbc_path`` describes; LogError / ConfigError
    (one line) for a log python-can cannot read or a DBC cantools cannot."""
    import can
    import cantools

    try:
        text = Path(dbc_path).read_text()
        cantools.database.load_string(text, database_format="dbc")
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"--dbc {dbc_path}: cannot read: {getattr(e, 'strerror', None) or e}") from None
    except Exception as e:  # noqa: BLE001 - cantools raises many kinds for a bad file
        raise ConfigError(f"--dbc {dbc_path}: not a DBC cantools reads: {str(e).splitlines()[0][:200]}") from None
    rows, damage, t0 = [], "", None
    try:
        with can.LogReader(str(path)) as reader:
            for msg in reader:
                t0 = msg.timestamp if t0 is None else t0
                rows.append(_CanRow(msg.timestamp - t0, int(round(msg.timestamp * 1e9)), msg.arbitration_id,
                                    bytes(msg.data), bool(msg.is_error_frame), bool(msg.is_remote_frame)))
    except FileNotFoundError:
        raise LogError(f"{path}: no such file") from None
    except Exception as e:  # noqa: BLE001 - a cut or foreign file: judge what was read, say so
        if not rows:
            raise LogError(f"{path}: not a CAN log python-can reads: {str(e).splitlines()[0][:200]}") from None
        damage = f"read up to frame {len(rows)}: {type(e).__name__}"
    if not rows:
        raise LogError(f"{path}: no frames")
    log = CanLogContents(rows, {"dbc": {"name": Path(dbc_path).name, "text": text}}, damage)
    return Run(str(path), {"mode": "realtime", "sim_s": rows[-1].t_s}, log)


def _summary_of(log) -> dict:
    text = (log.metadata.get("summary") or {}).get("json")
    if text is None:
        summaries = log.topic("/run/summary")
        text = summaries[-1].json if summaries else None
    try:
        summary = json.loads(text) if text else {}
    except ValueError:  # a damaged summary: read as none (fault, mode from the metadata)
        summary = {}
    if not summary:
        fault = log.metadata.get("fault") or {}
        if fault.get("reason"):
            summary["fault"] = fault["reason"]
        run = log.metadata.get("run") or {}
        if run.get("mode"):
            summary["mode"] = run["mode"]
    summary.setdefault("mcap", log.path)
    return summary


def _overrides(log) -> dict:
    try:
        return json.loads((log.metadata.get("scenario") or {}).get("overrides") or "{}")
    except ValueError:  # damaged overrides: the scenario as its TOML has it
        return {}


def _scenario_table(log, table: str):
    """A table (or array of tables) of the scenario the log was recorded with, as its TOML text has it."""
    try:
        return tomllib.loads((log.metadata.get("scenario") or {}).get("toml", "")).get(table)
    except (ValueError, AttributeError):  # the scenario text is damaged or absent: the caller uses defaults
        return None


def _scenario_value(log, table: str, key: str):
    """A value of the scenario the log was recorded with (its TOML text and --set overrides)."""
    sc = log.metadata.get("scenario") or {}
    try:
        overrides = json.loads(sc.get("overrides") or "{}")
        if f"{table}.{key}" in overrides:
            return overrides[f"{table}.{key}"]
        return tomllib.loads(sc.get("toml", "")).get(table, {}).get(key)
    except (ValueError, AttributeError):  # the scenario text is damaged or absent: the caller uses defaults
        return None


def as_run(run) -> Run:
    """``run`` itself, or the log at a path opened as a ``Run``."""
    if isinstance(run, Run):
        return run
    if isinstance(run, (str, Path)):
        return Run.open(run)
    raise TypeError(f"expected a hil.checks.Run or the path of a log, not {type(run).__name__}")
