"""A run's summary (the ``hil run --json`` object, docs/reference/run-json.md) read into typed records,
and the text ``hil run`` and ``hil replay`` print from them.

Why: the summary is a JSON object of about 50 keys that scripts, the log's ``/run/summary`` and the
sweeps read, so its keys stay as they are.  The text reads the few figures a person decides on, each
from one field of a record here rather than from string keys scattered through f-strings, and every
line is filled to ``hil.terminal.WIDTH`` (100 characters) by the one width helper.  A figure the
source lacks (a CAN log has no truth, an external TCU no strategy) prints "n/a".
"""
from __future__ import annotations

from dataclasses import dataclass, field

from .terminal import wrap
from .trace import fmt
from .traction import response_text


@dataclass(frozen=True)
class Stages:
    """When the fault came, when its serious stage began (T_det after it), and when the TCU flagged slip."""
    t_fault_s: float | None
    t_serious_s: float | None
    t_det_s: float | None
    t_detected_s: float | None


@dataclass(frozen=True)
class Identification:
    """What the TCU answered: confirmed, gave up (``unconfirmed``) or neither, and the curve it last sent."""
    identified: bool
    unconfirmed: bool
    t_identified_s: float | None
    rt_percent: float | None
    corrections: int | None
    params: tuple[float, ...] | None
    peak_mu_ci: tuple[float, float] | None
    peak_creep_ci: tuple[float, float] | None
    peak_interval_open: bool | None


@dataclass(frozen=True)
class CurveFigures:
    """The identified curve against the TCU's mu^ samples (fit) and against the true fault curve."""
    mse: float | None
    rmse: float | None
    mae: float | None
    r2: float | None
    peak_mu_err_percent: float | None
    peak_creep_err_percent: float | None
    r2_vs_truth: float | None
    peak_ci_holds_truth: bool | None


@dataclass(frozen=True)
class Traction:
    """The closed-loop figures (hil/traction.py), present in every run the plant side summarised."""
    control: str | None
    adhesion_utilisation: float
    adhesion_utilisation_low: float | None
    macro_slip_s: float | None
    macro_slip_count: int | None
    reaction_ms: float | None
    recovery_s: float | None
    torque_ripple_percent: float | None


@dataclass(frozen=True)
class Exchange:
    """How plant and TCU exchanged frames: the round trip, and in real time the deadlines and jitter."""
    mode: str
    bus: str
    round_trip_p50_us: float | None
    missed_deadlines: int | None = None
    missed_plant_started_late: int | None = None
    missed_cpu_away: int | None = None
    jitter_p99_us: float | None = None
    rejected_plant: int = 0
    rejected_tcu: int = 0


@dataclass(frozen=True)
class BusFindings:
    """Frames a mapped or watched bus carried that the run did not act on, by id, signal or kind."""
    unmapped_ids: dict[str, int] = field(default_factory=dict)
    out_of_range_signals: dict[str, int] = field(default_factory=dict)   # only those with a frame outside
    suspicious: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class RunSummary:
    """The figures of one run's summary that its text shows, typed (``from_json``)."""
    scenario: str
    strategy: str | None           # None: an external TCU, whose strategy is its own
    seed: int | None
    bus: str
    plant: str | None
    frame_auth: str | None
    reality: dict[str, dict]
    stages: Stages
    identification: Identification
    curve: CurveFigures | None     # None: no curve was sent
    observer_lag_ms: float | None
    sim_s: float | None
    wall_s: float | None
    traction: Traction | None
    exchange: Exchange | None      # None: a summary of neither lockstep nor real time (a CAN log's replay)
    findings: BusFindings
    mcap: str | None

    @classmethod
    def from_json(cls, s: dict) -> RunSummary:
        """Read the summary object (the keys docs/reference/run-json.md documents; absent ones as None)."""
        external = s.get("transport") == "external"
        pair = (lambda x: tuple(x) if x else None)
        ident = Identification(
            identified=bool(s.get("identified")), unconfirmed=bool(s.get("unconfirmed")),
            t_identified_s=s.get("t_identified_s"), rt_percent=s.get("rt_percent"),
            corrections=s.get("corrections"), params=tuple(s["params"]) if s.get("params") else None,
            peak_mu_ci=pair(s.get("peak_mu_ci")), peak_creep_ci=pair(s.get("peak_creep_ci")),
            peak_interval_open=s.get("peak_interval_open"))
        curve = None if not s.get("params") else CurveFigures(
            **{k: s.get(k) for k in ("mse", "rmse", "mae", "r2", "peak_mu_err_percent", "peak_creep_err_percent",
                                     "r2_vs_truth", "peak_ci_holds_truth")})
        traction = None if s.get("adhesion_utilisation") is None else Traction(
            **{k: s.get(k) for k in ("control", "adhesion_utilisation", "adhesion_utilisation_low", "macro_slip_s",
                                     "macro_slip_count", "reaction_ms", "recovery_s", "torque_ripple_percent")})
        exchange = None
        if s.get("mode") in ("lockstep", "realtime"):
            realtime = s["mode"] == "realtime"
            exchange = Exchange(
                mode=s["mode"], bus=s["bus"], round_trip_p50_us=s.get("round_trip_p50_us"),
                missed_deadlines=s.get("missed_deadlines") if realtime else None,
                missed_plant_started_late=s.get("missed_deadlines_plant_started_late") if realtime else None,
                missed_cpu_away=s.get("missed_deadlines_cpu_away") if realtime else None,
                jitter_p99_us=s.get("jitter_p99_us") if realtime else None,
                rejected_plant=sum((s.get("rejected_frames") or {}).values()),
                rejected_tcu=sum((s.get("tcu_rejected_frames") or {}).values()))
        findings = BusFindings(
            unmapped_ids=dict(s.get("unmapped_ids") or {}),
            out_of_range_signals={k: n for k, n in (s.get("out_of_range_signals") or {}).items() if n},
            suspicious=dict(sorted((s.get("suspicious") or {}).items())))
        return cls(scenario=s["scenario"], strategy=None if external else s["strategy"], seed=s.get("seed"),
                   bus=s["bus"], plant=s.get("plant"), frame_auth=s.get("frame_auth"),
                   reality={k: dict(v or {}) for k, v in (s.get("reality") or {}).items()},
                   stages=Stages(s.get("t_fault_s"), s.get("t_serious_s"), s.get("t_det_s"), s.get("t_detected_s")),
                   identification=ident, curve=curve, observer_lag_ms=s.get("observer_lag_ms"),
                   sim_s=s.get("sim_s"), wall_s=s.get("wall_s"), traction=traction, exchange=exchange,
                   findings=findings, mcap=s.get("mcap"))

    @property
    def external(self) -> bool:
        return self.strategy is None

    def heading(self) -> str:
        strategy = self.strategy or "(the external TCU's own)"
        return (f"scenario {self.scenario}  strategy {strategy}  "
                f"seed {self.seed}  bus {self.bus}" + (f"  plant {self.plant}" if self.plant else "")
                + (f"  frames {'authenticated' if self.frame_auth == 'on' else 'not authenticated'}"
                   if self.frame_auth else ""))

    def lines(self) -> list[str]:
        """The body's lines, unwrapped: a top line starts with two spaces, its detail with four."""
        st = self.stages
        out = []
        if self.reality:
            out.append("  reality: " + "; ".join(f"{name}(" + ", ".join(f"{k}={v}" for k, v in params.items()) + ")"
                                                 for name, params in self.reality.items()))
        out.append(f"  fault at {fmt(st.t_fault_s, '.3f')} s, serious stage at {fmt(st.t_serious_s, '.3f')} s "
                   f"(T_det {fmt(st.t_det_s and st.t_det_s * 1e3, '.1f')} ms), slip detected at "
                   f"{fmt(st.t_detected_s, '.3f')} s")
        out += self._identification_lines()
        out.append(f"  observer lag {fmt(self.observer_lag_ms, '.1f')} ms; "
                   f"{fmt(self.sim_s, '.2f')} s simulated in {fmt(self.wall_s, '.2f')} s")
        if self.traction is not None:
            t = self.traction
            out.append(f"  traction ({t.control}): adhesion utilisation {fmt(t.adhesion_utilisation, '.3f')}, "
                       f"where it matters {fmt(t.adhesion_utilisation_low, '.3f')}; macro-slip "
                       f"{fmt(t.macro_slip_s, '.3f')} s ({t.macro_slip_count}x)")
            out.append(f"    {response_text(t.reaction_ms, t.recovery_s)}, "
                       f"ripple {fmt(t.torque_ripple_percent, '.2f')} %")
        if self.exchange is not None:
            out.append(self._exchange_line())
        f = self.findings
        if f.unmapped_ids:
            out.append("  frames of ids the mapping does not name (not acted on): "
                       + ", ".join(f"{k} x{n}" for k, n in f.unmapped_ids.items()))
        if f.out_of_range_signals:
            out.append("  signals outside their DBC range: "
                       + ", ".join(f"{k} x{n}" for k, n in f.out_of_range_signals.items()))
        if f.suspicious:
            out.append("  suspicious frames (another node on the bus?): "
                       + ", ".join(f"{k} x{n}" for k, n in f.suspicious.items()))
        if self.mcap:
            out.append(f"  log: {self.mcap}")
        return out

    def _identification_lines(self) -> list[str]:
        idf, c = self.identification, self.curve
        if idf.identified:
            out = [f"  identified at {fmt(idf.t_identified_s, '.3f')} s: RT {fmt(idf.rt_percent, '.1f')} % after "
                   f"{idf.corrections} corrections"]
        elif idf.unconfirmed:
            out = [f"  UNCONFIRMED: the TCU gave up after {idf.corrections} corrections (the data did not pin the "
                   "curve)", "  its best estimate:"]
        elif self.external and not idf.corrections:
            out = ["  no identification result received (an external TCU need not send TcuResult frames)"]
        else:
            out = [f"  NOT identified within the run ({idf.corrections} corrections)"]
        if c is None:
            return out
        out.append("  params (l0, l1, l2, t1, t2): " + ", ".join(f"{x:.5g}" for x in idf.params))
        if idf.peak_mu_ci and idf.peak_creep_ci:
            (m0, m1), (c0, c1) = idf.peak_mu_ci, idf.peak_creep_ci
            out.append(f"  how sure (90 % intervals): peak mu {m0:.4f} .. {m1:.4f}, "
                       f"peak creep {c0:.3f} .. {c1:.3f} km/h")
            if idf.peak_interval_open:
                out.append("    (open: the peak may lie past the creeps seen; the upper ends are the TCU's range)")
        out.append(f"  fit: MSE {fmt(c.mse, '.3e')}  RMSE {fmt(c.rmse, '.3e')}  MAE {fmt(c.mae, '.3e')}  "
                   f"R2 {fmt(c.r2, '.5f')}")
        out.append(f"  vs true curve: peak mu error {fmt(c.peak_mu_err_percent, '.2f')} %, peak creep error "
                   f"{fmt(c.peak_creep_err_percent, '.2f')} %, R2 {fmt(c.r2_vs_truth, '.5f')} "
                   "(on 0..2x its peak creep)")
        if c.peak_ci_holds_truth is False:
            out.append("    its 90 % intervals MISS the true peak")
        return out

    def _exchange_line(self) -> str:
        x = self.exchange
        line = f"  {x.mode} over {x.bus}: round trip p50 {fmt(x.round_trip_p50_us, '.0f')} us"
        if x.mode == "realtime":
            why = ([f"{x.missed_plant_started_late} in periods the plant itself began past the deadline: a stall "
                    "of its process or CPU"] if x.missed_plant_started_late else []) + (
                [f"{x.missed_cpu_away} with a CPU taken away by the machine"] if x.missed_cpu_away else [])
            line += (f", missed deadlines {x.missed_deadlines}" + (f" ({'; '.join(why)})" if why else "")
                     + f", jitter p99 {fmt(x.jitter_p99_us, '.0f')} us")
        if x.rejected_plant or x.rejected_tcu:
            line += f"; rejected frames: plant {x.rejected_plant}, TCU {x.rejected_tcu}"
        return line

    def text(self, heading: str | None = None) -> str:
        """Heading and body, every line within ``WIDTH``: a longer line continues 4 characters further in."""
        out = []
        for line in [heading or self.heading(), *self.lines()]:
            lead = line[:len(line) - len(line.lstrip())]
            out.append(wrap(line, indent=lead + "    ", first=lead))
        return "\n".join(out)
