"""An MCAP log of ``hil run`` as a Rerun recording (.rrd) with a blueprint: ``hil view``.

Timelines
- ``sim_time`` (duration, s): everything against simulation time.
- ``creep_m_per_h`` (sequence): creep speed in metres per hour (1 km/h = 1000), the x axis of the
  friction-curve plot.  Rerun 0.41 has no general x-y plot view; a ``TimeSeriesView`` plots against
  whichever timeline is active, so selecting ``creep_m_per_h`` in the time panel turns the
  "mu-v_s curve" tab into a mu over creep-speed plot with real axes and ticks.  The same figure is
  also drawn with matplotlib and logged as an image (``/figures/curve``), visible on any timeline.

Entities (all scalars sent in bulk with ``rr.send_columns``)
- ``/speed/{train,wheel}_kmh``: true train speed and wheel peripheral speed (train + creep), km/h;
- ``/creep/{true,measured}_kmh``: true creep (plant) and the TCU's creep from measured speeds;
  ``/creep/fault_onset``, ``/creep/serious_start``: vertical markers at t_f and t_serious;
  ``/creep/peak_creep_kmh``: the fault curve's peak creep (crossing it starts the serious stage);
- ``/mu/{true,observed}``: true adhesion mu and the observer's mu^, with the same markers;
- ``/tcu/{stage,corrections}``: TCU stage (0 monitoring, 1 identifying, 2 confirmed, 3 gave up) and
  correction count;
- ``/curve/samples`` (mu^ over measured creep from slip detection to confirmation),
  ``/curve/true_fault``, ``/curve/identified/qNN`` (the identified curve after correction NN) and
  ``/curve/identified/final`` on the ``creep_m_per_h`` timeline;
- ``/events``: identification events and run events as ``TextLog``;
- ``/bus/{frames_tx,frames_rx,rejected}`` per 10 ms of sim time; in realtime runs
  ``/timing/{round_trip_us,lateness_us,missed_deadlines}`` from ``/loop/timing``.
"""
from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np

from .logread import LogError, read_log, scenario_from_log

CREEP_TIMELINE = "creep_m_per_h"
TIME_TIMELINE = "sim_time"
BUS_BIN_S = 0.01
STAGE_CODES = {"normal": 0, "early": 1, "serious": 2}

# colours (RGB)
C_TRAIN, C_WHEEL = (31, 119, 180), (255, 127, 14)
C_TRUE, C_MEAS = (44, 160, 44), (214, 39, 40)
C_FAULT, C_SERIOUS = (148, 103, 189), (140, 86, 75)


def corrections_and_final(events) -> tuple[list, object]:
    """The correction events, and the curve a run ended with: the confirmed one, else the last correction."""
    corrections = [e for e in events if e.kind == "correction"]
    final = next((e for e in events if e.kind == "confirmed"), corrections[-1] if corrections else None)
    return corrections, final


class LogData:
    """The arrays a view needs, pulled out of one log."""

    def __init__(self, path):
        log = read_log(path)
        self.path = str(path)
        self.log = log
        meta = log.metadata
        self.scenario = scenario_from_log(log)
        self.run = meta.get("run") or {}
        by_topic: dict[str, list] = {}
        for topic, _, m in log.messages:
            by_topic.setdefault(topic, []).append(m)
        self.topics = by_topic
        if not by_topic.get("/plant/state") and not by_topic.get("/tcu/observer"):
            raise LogError(f"{path}: no /plant/state or /tcu/observer messages"
                           + (f" outside the damage ({log.damage})" if log.damage else ""))

    def arrays(self, topic: str, *fields: str) -> list[np.ndarray]:
        msgs = self.topics.get(topic, [])
        return [np.array([getattr(m, f) for m in msgs], dtype=float) for f in fields]


def _scalars(rr, rec, entity: str, t, values, timeline: str = TIME_TIMELINE, sequence: bool = False) -> None:
    values = np.asarray(values, dtype=float)
    if values.size == 0:
        return
    index = rr.TimeColumn(timeline, sequence=np.asarray(t, dtype=np.int64)) if sequence else \
        rr.TimeColumn(timeline, duration=np.asarray(t, dtype=float))
    rr.send_columns(entity, indexes=[index], columns=rr.Scalars.columns(scalars=values), recording=rec)


def _line(rr, rec, entity: str, name: str, color, width: float = 1.5) -> None:
    rec.log(entity, rr.SeriesLines(names=name, colors=[color], widths=width), static=True)


def _points(rr, rec, entity: str, name: str, color, size: float = 2.0) -> None:
    rec.log(entity, rr.SeriesPoints(names=name, colors=[color], marker_sizes=size), static=True)


def _marker(rr, rec, entity: str, name: str, color, t: float | None, lo: float, hi: float) -> None:
    """A vertical line at sim time ``t``: two values at the same instant, not aggregated."""
    if t is None or not math.isfinite(t):
        return
    rec.log(entity, rr.SeriesLines(names=name, colors=[color], widths=2.0, aggregation_policy="off"), static=True)
    _scalars(rr, rec, entity, [t, t], [lo, hi])


def _span(*arrays) -> tuple[float, float]:
    vals = np.concatenate([np.asarray(a, float)[np.isfinite(a)] for a in arrays if np.size(a)] or [np.zeros(1)])
    if vals.size == 0:
        return 0.0, 1.0
    lo, hi = float(vals.min()), float(vals.max())
    pad = 0.05 * (hi - lo or 1.0)
    return lo - pad, hi + pad


def identification_events(data: LogData) -> list:
    return list(data.topics.get("/tcu/identification", []))


def serious_time(data: LogData) -> float | None:
    for m in data.topics.get("/plant/state", []):
        if m.stage == "serious":
            return m.t_s
    return None


def curve_figure_png(data: LogData, samples_v, samples_mu, events) -> bytes:
    """The paper-style mu-v_s figure (matplotlib, Agg): samples, identified curves, true fault curve."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from identifier.curve import mu_model

    fault = data.scenario.fault_curve
    v_peak = fault.peak()[0]
    vmax = max(3.0 * v_peak, float(np.nanmax(samples_v)) * 1.1 if len(samples_v) else 0.0)
    grid = np.linspace(0.0, vmax, 400)
    fig, ax = plt.subplots(figsize=(7.0, 4.4), dpi=110)
    if len(samples_v):
        ax.plot(samples_v, samples_mu, ".", ms=3, color="0.55", label="samples (measured $v_s$, observed $\\hat\\mu$)")
    corrections, final = corrections_and_final(events)
    cmap = plt.get_cmap("Blues")
    for i, e in enumerate(corrections):
        ax.plot(grid, mu_model(grid, np.array(e.params)), lw=0.8,
                color=cmap(0.3 + 0.6 * (i + 1) / max(len(corrections), 1)),
                label="identified after each correction" if i == 0 else None)
    if final is not None:
        ax.plot(grid, mu_model(grid, np.array(final.params)), lw=2.2, color="tab:blue",
                label=f"identified ({final.kind}, Q={final.correction}, t={final.t_s:.3f} s)")
    ax.plot(grid, fault.mu(grid), "--", lw=2.0, color="tab:green", label="true fault curve")
    mu_peak = fault.peak()[1]
    ax.set_ylim(min(0.0, float(np.nanmin(samples_mu)) if len(samples_mu) else 0.0) - 0.01, 1.35 * mu_peak)
    ax.set_xlim(0.0, vmax)
    ax.set_xlabel("creep speed $v_s$ (km/h)")
    ax.set_ylabel("adhesion coefficient $\\mu$")
    ax.set_title(f"{data.scenario.name}: {data.run.get('strategy', '?')} seed {data.run.get('seed', '?')}")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()


def build_recording(data: LogData, application_id: str = "railway_hil"):
    """A ``rr.RecordingStream`` (not yet saved) with every entity; returns (recording, blueprint)."""
    import rerun as rr
    import rerun.blueprint as rrb

    from identifier.curve import mu_model

    rec = rr.RecordingStream(application_id, recording_id=Path(data.path).stem)
    sc = data.scenario
    t_f = sc.run.fault_time_s
    t_serious = serious_time(data)
    v_peak = sc.fault_curve.peak()[0]

    # -- against sim time -------------------------------------------------------------------------------
    t, train, creep, mu = data.arrays("/plant/state", "t_s", "train_speed_ms", "creep_speed_kmh", "mu")
    train_kmh = 3.6 * train
    wheel_kmh = train_kmh + creep
    _line(rr, rec, "/speed/train_kmh", "train speed (km/h)", C_TRAIN)
    _line(rr, rec, "/speed/wheel_kmh", "wheel speed (km/h)", C_WHEEL)
    _scalars(rr, rec, "/speed/train_kmh", t, train_kmh)
    _scalars(rr, rec, "/speed/wheel_kmh", t, wheel_kmh)

    to, creep_meas, mu_hat = data.arrays("/tcu/observer", "t_s", "creep_speed_kmh", "mu_hat")
    _line(rr, rec, "/creep/true_kmh", "true creep (km/h)", C_TRUE, 2.0)
    _line(rr, rec, "/creep/measured_kmh", "measured creep (km/h)", C_MEAS, 1.0)
    _scalars(rr, rec, "/creep/true_kmh", t, creep)
    _scalars(rr, rec, "/creep/measured_kmh", to, creep_meas)
    t_all = np.concatenate([t, to]) if t.size or to.size else np.zeros(1)
    if t_all.size:
        _line(rr, rec, "/creep/peak_creep_kmh", "fault curve peak creep (km/h)", (127, 127, 127), 1.0)
        _scalars(rr, rec, "/creep/peak_creep_kmh", [t_all.min(), t_all.max()], [v_peak, v_peak])
    lo, hi = _span(creep, creep_meas)
    _marker(rr, rec, "/creep/fault_onset", f"fault onset t_f = {t_f:.3f} s", C_FAULT, t_f, lo, hi)
    _marker(rr, rec, "/creep/serious_start", "serious stage starts" + (f" {t_serious:.3f} s" if t_serious else ""),
            C_SERIOUS, t_serious, lo, hi)

    _line(rr, rec, "/mu/true", "true mu", C_TRUE, 2.0)
    _line(rr, rec, "/mu/observed", "observed mu^", C_MEAS, 1.0)
    _scalars(rr, rec, "/mu/true", t, mu)
    _scalars(rr, rec, "/mu/observed", to, mu_hat)
    lo, hi = _span(mu[t >= t_f - 0.05] if t.size else mu, mu_hat[to >= t_f - 0.05] if to.size else mu_hat)
    _marker(rr, rec, "/mu/fault_onset", "fault onset", C_FAULT, t_f, lo, hi)
    _marker(rr, rec, "/mu/serious_start", "serious stage starts", C_SERIOUS, t_serious, lo, hi)

    ts, stage, corr = data.arrays("/tcu/status", "t_s", "stage", "correction")
    _line(rr, rec, "/tcu/stage", "TCU stage (0 monitor, 1 identify, 2 confirmed, 3 gave up)", (31, 119, 180))
    _line(rr, rec, "/tcu/corrections", "corrections Q", (255, 127, 14))
    _scalars(rr, rec, "/tcu/stage", ts, stage)
    _scalars(rr, rec, "/tcu/corrections", ts, corr)
    if t.size:
        codes = np.array([STAGE_CODES.get(m.stage, -1) for m in data.topics["/plant/state"]], dtype=float)
        _line(rr, rec, "/tcu/plant_stage", "plant stage (0 normal, 1 early, 2 serious)", C_SERIOUS)
        _scalars(rr, rec, "/tcu/plant_stage", t, codes)

    # -- events as text ---------------------------------------------------------------------------------
    events = identification_events(data)
    texts = []
    for e in events:
        texts.append((e.t_s, "INFO", f"{e.kind} Q={e.correction} ({e.strategy}) after {e.samples} samples, "
                      f"J_EF {e.j_ef:.4g}: " + ", ".join(f"{x:.5g}" for x in e.params)))
    for m in data.topics.get("/run/events", []):
        if not m.text.startswith(("correction Q=", "confirmed Q=")):     # already above, with more detail
            texts.append((m.t_s, m.level or "INFO", m.text))
    texts.append((t_f, "WARN", f"fault onset (t_f = {t_f:.3f} s)"))
    if t_serious is not None:
        texts.append((t_serious, "WARN", f"serious stage starts (creep >= {v_peak:.3f} km/h, "
                                         f"T_det = {1e3 * (t_serious - t_f):.1f} ms)"))
    if not data.log.complete:
        texts.append((float(t_all.max()) if t_all.size else 0.0, "ERROR", f"log incomplete: {data.log.problem()}"))
    texts.sort(key=lambda x: x[0])
    if texts:
        rr.send_columns("/events", indexes=[rr.TimeColumn(TIME_TIMELINE, duration=[x[0] for x in texts])],
                        columns=rr.TextLog.columns(text=[x[2] for x in texts], level=[x[1] for x in texts]),
                        recording=rec)

    # -- bus and timing ---------------------------------------------------------------------------------
    frames = data.topics.get("/can/frames", [])
    if frames:
        ft = np.array([m.t_s for m in frames])
        bins = np.floor(ft / BUS_BIN_S).astype(np.int64)
        nb = int(bins.max()) + 1
        tb = (np.arange(nb) + 0.5) * BUS_BIN_S
        tx = np.bincount(bins, weights=[m.direction == "tx" for m in frames], minlength=nb)
        rx = np.bincount(bins, weights=[m.direction == "rx" for m in frames], minlength=nb)
        bad = np.bincount(bins, weights=[m.status not in ("ok", "late") for m in frames], minlength=nb)
        for name, vals, color in (("frames_tx", tx, C_TRAIN), ("frames_rx", rx, C_WHEEL), ("rejected", bad, C_MEAS)):
            _line(rr, rec, f"/bus/{name}", f"{name.replace('_', ' ')} per {BUS_BIN_S * 1e3:g} ms", color)
            _scalars(rr, rec, f"/bus/{name}", tb, vals)
    timing = data.topics.get("/loop/timing", [])
    realtime = data.run.get("mode") == "realtime"
    if timing:
        tt, rt, late, missed = data.arrays("/loop/timing", "t_s", "round_trip_us", "lateness_us", "missed_deadline")
        _line(rr, rec, "/timing/round_trip_us", "round trip (us)", C_TRAIN)
        _line(rr, rec, "/timing/lateness_us", "period start lateness = jitter (us)", C_WHEEL)
        _line(rr, rec, "/timing/missed_deadlines", "missed deadlines (cumulative)", C_MEAS)
        _scalars(rr, rec, "/timing/round_trip_us", tt, rt)
        _scalars(rr, rec, "/timing/lateness_us", tt, late)
        _scalars(rr, rec, "/timing/missed_deadlines", tt, np.cumsum(missed))

    # -- the mu-v_s curve on the creep timeline ---------------------------------------------------------
    tdet = [m.t_s for m in data.topics.get("/tcu/status", []) if m.stage >= 1]
    t_from = tdet[0] if tdet else t_f
    conf = next((e for e in events if e.kind == "confirmed"), None)
    t_to = conf.t_s if conf is not None else math.inf
    sel = (to >= t_from) & (to <= t_to)
    sv, smu = creep_meas[sel], mu_hat[sel]
    order = np.argsort(sv, kind="stable")
    _points(rr, rec, "/curve/samples", "samples: observed mu^ over measured creep", (120, 120, 120), 2.5)
    _scalars(rr, rec, "/curve/samples", np.round(sv[order] * 1000), smu[order], CREEP_TIMELINE, sequence=True)
    vmax = max(3.0 * v_peak, float(sv.max()) * 1.1 if sv.size else 0.0)
    grid = np.linspace(0.0, vmax, 301)
    grid_idx = np.round(grid * 1000)
    _line(rr, rec, "/curve/true_fault", "true fault curve", (255, 200, 0), 3.0)
    _scalars(rr, rec, "/curve/true_fault", grid_idx, sc.fault_curve.mu(grid), CREEP_TIMELINE, sequence=True)
    corrections, final = corrections_and_final(events)
    for i, e in enumerate(corrections):
        shade = int(200 - 150 * (i + 1) / max(len(corrections), 1))
        _line(rr, rec, f"/curve/identified/q{e.correction:02d}", f"after correction {e.correction} "
              f"(t = {e.t_s:.3f} s)", (shade, shade, 255), 1.0)
        _scalars(rr, rec, f"/curve/identified/q{e.correction:02d}", grid_idx, mu_model(grid, np.array(e.params)),
                 CREEP_TIMELINE, sequence=True)
    if final is not None:
        _line(rr, rec, "/curve/identified/final", f"identified ({final.kind}, t = {final.t_s:.3f} s)",
              (31, 119, 180), 3.0)
        _scalars(rr, rec, "/curve/identified/final", grid_idx, mu_model(grid, np.array(final.params)),
                 CREEP_TIMELINE, sequence=True)
    mu_peak = sc.fault_curve.peak()[1]
    curve_mu_range = (min(0.0, float(smu.min()) if smu.size else 0.0) - 0.01, 1.35 * mu_peak)
    png = curve_figure_png(data, sv, smu, events)
    rec.log("/figures/curve", rr.EncodedImage(contents=png, media_type="image/png"), static=True)

    # -- blueprint --------------------------------------------------------------------------------------
    time_views = [
        rrb.TimeSeriesView(origin="/speed", name="Train and wheel speed (km/h) vs sim time"),
        rrb.TimeSeriesView(origin="/creep", name="Creep speed (km/h): fault onset, serious stage"),
        rrb.TimeSeriesView(origin="/mu", name="True mu and observed mu^"),
        rrb.TimeSeriesView(origin="/tcu", name="TCU stage and corrections"),
    ]
    curve_views = [
        rrb.TimeSeriesView(origin="/curve", name=f"mu vs creep speed: select timeline {CREEP_TIMELINE} (m/h)",
                           plot_legend=rrb.PlotLegend(visible=False),
                           axis_x=rrb.TimeAxis(view_range=rrb.TimeRange(
                               start=rrb.TimeRangeBoundary.absolute(seq=0),
                               end=rrb.TimeRangeBoundary.absolute(seq=int(grid_idx[-1])))),
                           axis_y=rrb.ScalarAxis(range=curve_mu_range)),
        rrb.Spatial2DView(origin="/figures", name="mu-v_s figure (matplotlib)"),
    ]
    lower = [rrb.TextLogView(origin="/events", name="Identification events")]
    if frames:
        lower.append(rrb.TimeSeriesView(origin="/bus", name="CAN frames per 10 ms"))
    if timing and (realtime or np.any(np.isfinite(rt))):
        lower.append(rrb.TimeSeriesView(origin="/timing", name="Loop timing: round trip, jitter, missed deadlines"))
    # one page, no tabs: the time plots fill on sim_time, the mu-v_s plot on creep_m_per_h, the figure on both
    blueprint = rrb.Blueprint(
        rrb.Vertical(rrb.Grid(*time_views, *curve_views, grid_columns=3), rrb.Horizontal(*lower),
                     row_shares=[3, 1], name="HIL run"),
        rrb.TimePanel(timeline=TIME_TIMELINE), rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"), collapse_panels=False)
    return rec, blueprint


def default_rrd_path(mcap_path) -> Path:
    return Path(mcap_path).with_suffix(".rrd")


def write_rrd(mcap_path, out=None) -> tuple[Path, LogData]:
    """Read ``mcap_path``, write the .rrd (default: beside it); returns (rrd path, the log's data)."""
    data = LogData(mcap_path)
    rec, blueprint = build_recording(data)
    out = Path(out) if out else default_rrd_path(mcap_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    rec.save(str(out), default_blueprint=blueprint)
    rec.flush()
    rec.disconnect()       # closes the file sink: the .rrd is complete (footer written) when this returns
    return out, data
