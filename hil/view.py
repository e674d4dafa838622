"""An MCAP log of ``hil run`` as a Rerun recording (.rrd) with a blueprint: ``hil view``.

Timelines
- ``sim_time`` (duration, s): everything against simulation time.
- ``creep_m_per_h`` (sequence): creep speed in metres per hour (1 km/h = 1000), the x axis of the
  friction-curve plot.  Rerun 0.41 has no general x-y plot view; a ``TimeSeriesView`` plots against
  whichever timeline is active, so selecting ``creep_m_per_h`` in the time panel turns the
  "mu-v_s curve" tab into a mu over creep-speed plot with real axes and ticks.  The same figure is
  also drawn with matplotlib and logged as an image (``/figures/curve``), visible on any timeline.

Streaming: ``write_rrd`` opens the .rrd's file sink first and reads the log twice in chunks
(``hil.log.read.read_log``'s ``on_message``): a first pass for the events and the first identifying
status (``LogHead``), a second that sends the per-step topics in batches of ``BATCH_ROWS`` rows.
What stays in memory is bounded by the batch, plus the curve samples of the identification window
and one bus-count bin per 10 ms of sim time.

Entities (all scalars sent with ``rr.send_columns``)
- ``/speed/{train,wheel}_kmh``: true train speed and wheel peripheral speed (train + creep), km/h;
- ``/creep/{true,measured}_kmh``: true creep (plant) and the TCU's creep from measured speeds;
  ``/creep/fault_onset``, ``/creep/serious_start``: vertical markers at t_f and t_serious;
  ``/creep/peak_creep_kmh``: the fault curve's peak creep (crossing it starts the serious stage);
- ``/mu/{true,observed}``: true adhesion mu and the observer's mu^, with the same markers;
- ``/creep/true_peak_kmh``, ``/mu/true_peak``: the current rail's true peak (closed-loop runs, ``/plant/rail``),
  and ``/creep/estimate/{peak,lo,hi}_kmh``, ``/mu/estimate/{peak,lo,hi}``: the TCU's estimate of it with its
  90 % interval (``/tcu/estimate``, from its TcuEstimate frames);
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

from .log.read import LogError, read_log, scenario_from_log
from .bus.verdicts import REJECTED, kind
from .traction import response_text

CREEP_TIMELINE = "creep_m_per_h"
TIME_TIMELINE = "sim_time"
BUS_BIN_S = 0.01
STAGE_CODES = {"normal": 0, "early": 1, "serious": 2}

# colours (RGB)
C_TRAIN, C_WHEEL = (31, 119, 180), (255, 127, 14)
C_TRUE, C_MEAS = (44, 160, 44), (214, 39, 40)
C_FAULT, C_SERIOUS = (148, 103, 189), (140, 86, 75)
C_ESTIMATE = (23, 190, 207)
#: the TCU's estimate of the current rail's peak (``/tcu/estimate``): centre and 90 % interval, creep then mu
ESTIMATE_ENTITIES = ("/creep/estimate/peak_kmh", "/creep/estimate/lo_kmh", "/creep/estimate/hi_kmh",
                     "/mu/estimate/peak", "/mu/estimate/lo", "/mu/estimate/hi")
ESTIMATE_NAMES = ("TCU's estimate of the peak creep (km/h)", "its 90 % interval, low end", "its 90 % interval, high end",
                  "TCU's estimate of the peak mu", "its 90 % interval, low end", "its 90 % interval, high end")


def corrections_and_final(events) -> tuple[list, object]:
    """The correction events, and the curve a run ended with: the confirmed one, else the last correction."""
    corrections = [e for e in events if e.kind == "correction"]
    final = next((e for e in events if e.kind == "confirmed"), corrections[-1] if corrections else None)
    return corrections, final


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


def curve_figure_png(data: "LogHead", samples_v, samples_mu, events) -> bytes:
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


#: the topics the recording streams (read in a second pass, never held whole)
STREAMED_TOPICS = {"/plant/state", "/tcu/observer", "/tcu/status", "/can/frames", "/loop/timing", "/plant/rail",
                   "/control/metrics", "/tcu/estimate"}
#: rows a streamed entity holds before they go to the .rrd in one ``rr.send_columns``
BATCH_ROWS = 20_000


class LogHead:
    """What the recording needs before the per-step topics stream by: the log's metadata and
    scenario, its identification and run events, and the first TCU status of the identifying stage
    (a first pass over the log, the per-step messages decoded one at a time and dropped)."""

    def __init__(self, path):
        self.path = str(path)
        self.t_detect = None
        small = {"/tcu/identification": [], "/run/events": []}

        def take(topic, _, m):
            if topic in small:
                small[topic].append(m)
            elif self.t_detect is None and m.stage >= 1:
                self.t_detect = m.t_s

        self.log = read_log(path, set(small) | {"/tcu/status"}, on_message=take)
        self.scenario = scenario_from_log(self.log)
        self.run = self.log.metadata.get("run") or {}
        self.events = small["/tcu/identification"]
        self.run_events = small["/run/events"]


class _Column:
    """One scalar entity's rows, sent to the recording every ``BATCH_ROWS`` rows (``_scalars``)."""

    def __init__(self, rr, rec, entity: str):
        self.rr, self.rec, self.entity = rr, rec, entity
        self.t: list[float] = []
        self.v: list[float] = []

    def add(self, t: float, v: float) -> None:
        self.t.append(t)
        self.v.append(v)
        if len(self.t) >= BATCH_ROWS:
            self.flush()

    def flush(self) -> None:
        _scalars(self.rr, self.rec, self.entity, self.t, self.v)
        self.t, self.v = [], []


class _Range:
    """Running min and max of the finite values seen (``_span``'s figures without the arrays)."""

    def __init__(self):
        self.lo, self.hi, self.seen = math.inf, -math.inf, False

    def add(self, v: float) -> None:
        if math.isfinite(v):
            self.lo, self.hi, self.seen = min(self.lo, v), max(self.hi, v), True

    def span(self, *others: "_Range") -> tuple[float, float]:
        ranges = [r for r in (self, *others) if r.seen]
        if not ranges:
            return _span()
        return _span([min(r.lo for r in ranges), max(r.hi for r in ranges)])


class _Stream:
    """The per-step topics, taken one message at a time (``read_log``'s ``on_message``) and sent in
    batches; what needs the whole run (marker heights, time range, bus bins, curve samples in the
    identification window) is kept as running figures or small arrays."""

    def __init__(self, rr, rec, t_f: float, t_from: float, t_to: float):
        col = lambda entity: _Column(rr, rec, entity)   # noqa: E731
        self.cols = {e: col(e) for e in (
            "/speed/train_kmh", "/speed/wheel_kmh", "/creep/true_kmh", "/creep/measured_kmh", "/mu/true",
            "/mu/observed", "/tcu/stage", "/tcu/corrections", "/tcu/plant_stage", "/timing/round_trip_us",
            "/timing/lateness_us", "/timing/missed_deadlines", "/creep/true_peak_kmh", "/mu/true_peak",
            "/torque/applied_nm", "/torque/demand_nm", *ESTIMATE_ENTITIES)}
        self.t_f, self.t_from, self.t_to = t_f, t_from, t_to
        self.t_range = _Range()
        self.creep, self.creep_meas, self.mu, self.mu_hat = _Range(), _Range(), _Range(), _Range()
        self.t_serious = None
        self.states = self.observers = self.timings = self.frames = 0
        self.missed_total = 0.0
        self.nb = 0                                       # bus bins in use
        self.finite_round_trip = False
        self.bins = {k: np.zeros(0) for k in ("frames_tx", "frames_rx", "rejected")}
        self.samples_v: list[float] = []
        self.samples_mu: list[float] = []
        self.rail = 0                                     # /plant/rail rows (logs before closed loop: none)
        self.estimates = 0                                # /tcu/estimate rows (a TCU that sends no estimate: none)
        self.metrics = None                               # /control/metrics
        self.torque_per_mu_nm = None

    def _bin(self, name: str, b: int, w: float) -> None:
        arr = self.bins[name]
        if b >= arr.size:
            arr = self.bins[name] = np.concatenate([arr, np.zeros(max(b + 1 - arr.size, 1024))])
        arr[b] += w

    def take(self, topic: str, _, m) -> None:
        c = self.cols
        if topic == "/plant/state":
            self.states += 1
            t, train_kmh, creep = m.t_s, 3.6 * m.train_speed_ms, m.creep_speed_kmh
            c["/speed/train_kmh"].add(t, train_kmh)
            c["/speed/wheel_kmh"].add(t, train_kmh + creep)
            c["/creep/true_kmh"].add(t, creep)
            c["/mu/true"].add(t, m.mu)
            c["/tcu/plant_stage"].add(t, float(STAGE_CODES.get(m.stage, -1)))
            self.t_range.add(t)
            self.creep.add(creep)
            if t >= self.t_f - 0.05:
                self.mu.add(m.mu)
            if self.t_serious is None and m.stage == "serious":
                self.t_serious = t
            c["/torque/applied_nm"].add(t, m.torque_nm)
        elif topic == "/plant/rail":
            self.rail += 1
            c["/creep/true_peak_kmh"].add(m.t_s, m.peak_creep_kmh)
            c["/mu/true_peak"].add(m.t_s, m.peak_mu)
            if self.torque_per_mu_nm is not None:
                c["/torque/demand_nm"].add(m.t_s, m.demand_mu * self.torque_per_mu_nm)
        elif topic == "/control/metrics":
            self.metrics = m
        elif topic == "/tcu/estimate":
            self.estimates += 1
            for entity, value in zip(ESTIMATE_ENTITIES, (m.peak_creep_kmh, m.peak_creep_lo_kmh, m.peak_creep_hi_kmh,
                                                         m.peak_mu, m.peak_mu_lo, m.peak_mu_hi)):
                c[entity].add(m.t_s, value)
        elif topic == "/tcu/observer":
            self.observers += 1
            t = m.t_s
            c["/creep/measured_kmh"].add(t, m.creep_speed_kmh)
            c["/mu/observed"].add(t, m.mu_hat)
            self.t_range.add(t)
            self.creep_meas.add(m.creep_speed_kmh)
            if t >= self.t_f - 0.05:
                self.mu_hat.add(m.mu_hat)
            if self.t_from <= t <= self.t_to:
                self.samples_v.append(m.creep_speed_kmh)
                self.samples_mu.append(m.mu_hat)
        elif topic == "/tcu/status":
            c["/tcu/stage"].add(m.t_s, m.stage)
            c["/tcu/corrections"].add(m.t_s, m.correction)
        elif topic == "/can/frames":
            self.frames += 1
            b = int(math.floor(m.t_s / BUS_BIN_S))
            self._bin("frames_tx", b, float(m.direction == "tx"))
            self._bin("frames_rx", b, float(m.direction == "rx"))
            self._bin("rejected", b, float(kind(m.status) == REJECTED))
            self.nb = max(self.nb, b + 1)
        elif topic == "/loop/timing":
            self.timings += 1
            self.missed_total += m.missed_deadline
            self.finite_round_trip = self.finite_round_trip or math.isfinite(m.round_trip_us)
            c["/timing/round_trip_us"].add(m.t_s, m.round_trip_us)
            c["/timing/lateness_us"].add(m.t_s, m.lateness_us)
            c["/timing/missed_deadlines"].add(m.t_s, self.missed_total)

    def flush(self) -> None:
        for column in self.cols.values():
            column.flush()


def build_recording(head: LogHead, rec):
    """Stream every entity of the log at ``head.path`` into ``rec`` (whose file sink is already open):
    the per-step topics in a second pass over the log, in batches of ``BATCH_ROWS``.  Returns the
    blueprint and the second pass's ``LogContents``.  ``LogError`` when the log holds no
    /plant/state or /tcu/observer message."""
    import rerun as rr
    import rerun.blueprint as rrb

    from identifier.curve import mu_model

    sc = head.scenario
    t_f = sc.run.fault_time_s
    v_peak = sc.fault_curve.peak()[0]
    events = head.events
    conf = next((e for e in events if e.kind == "confirmed"), None)
    stream = _Stream(rr, rec, t_f, head.t_detect if head.t_detect is not None else t_f,
                     conf.t_s if conf is not None else math.inf)
    # entity styles first (static), then the rows as they stream
    _line(rr, rec, "/speed/train_kmh", "train speed (km/h)", C_TRAIN)
    _line(rr, rec, "/speed/wheel_kmh", "wheel speed (km/h)", C_WHEEL)
    _line(rr, rec, "/creep/true_kmh", "true creep (km/h)", C_TRUE, 2.0)
    _line(rr, rec, "/creep/measured_kmh", "measured creep (km/h)", C_MEAS, 1.0)
    _line(rr, rec, "/mu/true", "true mu", C_TRUE, 2.0)
    _line(rr, rec, "/mu/observed", "observed mu^", C_MEAS, 1.0)
    _line(rr, rec, "/tcu/stage", "TCU stage (0 monitor, 1 identify, 2 confirmed, 3 gave up)", (31, 119, 180))
    _line(rr, rec, "/tcu/corrections", "corrections Q", (255, 127, 14))
    _line(rr, rec, "/creep/true_peak_kmh", "true peak creep of the current rail (km/h)", C_SERIOUS, 1.0)
    _line(rr, rec, "/mu/true_peak", "true peak mu of the current rail", C_SERIOUS, 1.0)
    for entity, name, width in zip(ESTIMATE_ENTITIES, ESTIMATE_NAMES, (1.5, 0.75, 0.75) * 2):
        _line(rr, rec, entity, name, C_ESTIMATE, width)
    _line(rr, rec, "/torque/applied_nm", "torque applied (N m)", C_TRUE, 2.0)
    _line(rr, rec, "/torque/demand_nm", "driver's demand (N m)", C_MEAS, 1.0)
    stream.torque_per_mu_nm = sc.vehicle.torque_per_mu_nm
    log = read_log(head.path, STREAMED_TOPICS, on_message=stream.take)
    stream.flush()
    if not stream.states and not stream.observers:
        raise LogError(f"{head.path}: no /plant/state or /tcu/observer messages"
                       + (f" outside the damage ({log.damage})" if log.damage else ""))
    if stream.states:
        _line(rr, rec, "/tcu/plant_stage", "plant stage (0 normal, 1 early, 2 serious)", C_SERIOUS)
    t_serious = stream.t_serious
    t_lo, t_hi = (stream.t_range.lo, stream.t_range.hi) if stream.t_range.seen else (0.0, 0.0)

    # -- markers (their heights need the whole run) -----------------------------------------------------
    _line(rr, rec, "/creep/peak_creep_kmh", "fault curve peak creep (km/h)", (127, 127, 127), 1.0)
    _scalars(rr, rec, "/creep/peak_creep_kmh", [t_lo, t_hi], [v_peak, v_peak])
    lo, hi = stream.creep.span(stream.creep_meas)
    _marker(rr, rec, "/creep/fault_onset", f"fault onset t_f = {t_f:.3f} s", C_FAULT, t_f, lo, hi)
    _marker(rr, rec, "/creep/serious_start", "serious stage starts" + (f" {t_serious:.3f} s" if t_serious else ""),
            C_SERIOUS, t_serious, lo, hi)
    lo, hi = stream.mu.span(stream.mu_hat)
    _marker(rr, rec, "/mu/fault_onset", "fault onset", C_FAULT, t_f, lo, hi)
    _marker(rr, rec, "/mu/serious_start", "serious stage starts", C_SERIOUS, t_serious, lo, hi)

    # -- events as text ---------------------------------------------------------------------------------
    texts = []
    for e in events:
        texts.append((e.t_s, "INFO", f"{e.kind} Q={e.correction} ({e.strategy}) after {e.samples} samples, "
                      f"J_EF {e.j_ef:.4g}: " + ", ".join(f"{x:.5g}" for x in e.params)))
    for m in head.run_events:
        if not m.text.startswith(("correction Q=", "confirmed Q=")):     # already above, with more detail
            texts.append((m.t_s, m.level or "INFO", m.text))
    texts.append((t_f, "WARN", f"fault onset (t_f = {t_f:.3f} s)"))
    if t_serious is not None:
        texts.append((t_serious, "WARN", f"serious stage starts (creep >= {v_peak:.3f} km/h, "
                                         f"T_det = {1e3 * (t_serious - t_f):.1f} ms)"))
    m = stream.metrics
    if m is not None:
        texts.append((m.t_s, "INFO", f"control {m.control}: adhesion utilisation {m.adhesion_utilisation:.3f} "
                      f"(low {m.adhesion_utilisation_low:.3f}), macro-slip {m.macro_slip_s:.3f} s "
                      f"({m.macro_slip_count}x), {response_text(m.reaction_ms, m.recovery_s)}, "
                      f"ripple {m.torque_ripple_percent:.2f} %"))
    if not log.complete:
        texts.append((t_hi, "ERROR", f"log incomplete: {log.problem()}"))
    texts.sort(key=lambda x: x[0])
    if texts:
        rr.send_columns("/events", indexes=[rr.TimeColumn(TIME_TIMELINE, duration=[x[0] for x in texts])],
                        columns=rr.TextLog.columns(text=[x[2] for x in texts], level=[x[1] for x in texts]),
                        recording=rec)

    # -- bus and timing ---------------------------------------------------------------------------------
    if stream.frames:
        nb = stream.nb
        tb = (np.arange(nb) + 0.5) * BUS_BIN_S
        for name, color in (("frames_tx", C_TRAIN), ("frames_rx", C_WHEEL), ("rejected", C_MEAS)):
            _line(rr, rec, f"/bus/{name}", f"{name.replace('_', ' ')} per {BUS_BIN_S * 1e3:g} ms", color)
            vals = stream.bins[name][:nb]
            for i in range(0, nb, BATCH_ROWS):
                _scalars(rr, rec, f"/bus/{name}", tb[i:i + BATCH_ROWS], vals[i:i + BATCH_ROWS])
    realtime = head.run.get("mode") == "realtime"
    if stream.timings:
        _line(rr, rec, "/timing/round_trip_us", "round trip (us)", C_TRAIN)
        _line(rr, rec, "/timing/lateness_us", "period start lateness = jitter (us)", C_WHEEL)
        _line(rr, rec, "/timing/missed_deadlines", "missed deadlines (cumulative)", C_MEAS)

    # -- the mu-v_s curve on the creep timeline ---------------------------------------------------------
    sv, smu = np.array(stream.samples_v, dtype=float), np.array(stream.samples_mu, dtype=float)
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
    png = curve_figure_png(head, sv, smu, events)
    rec.log("/figures/curve", rr.EncodedImage(contents=png, media_type="image/png"), static=True)

    # -- blueprint --------------------------------------------------------------------------------------
    time_views = [
        rrb.TimeSeriesView(origin="/speed", name="Train and wheel speed (km/h) vs sim time"),
        rrb.TimeSeriesView(origin="/creep", name="Creep speed (km/h): fault onset, serious stage"),
        rrb.TimeSeriesView(origin="/mu", name="True mu and observed mu^"),
        rrb.TimeSeriesView(origin="/tcu", name="TCU stage and corrections"),
    ]
    if stream.rail:
        time_views.append(rrb.TimeSeriesView(origin="/torque", name="Torque applied and the driver's demand (N m)"))
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
    if stream.frames:
        lower.append(rrb.TimeSeriesView(origin="/bus", name="CAN frames per 10 ms"))
    if stream.timings and (realtime or stream.finite_round_trip):
        lower.append(rrb.TimeSeriesView(origin="/timing", name="Loop timing: round trip, jitter, missed deadlines"))
    # one page, no tabs: the time plots fill on sim_time, the mu-v_s plot on creep_m_per_h, the figure on both
    blueprint = rrb.Blueprint(
        rrb.Vertical(rrb.Grid(*time_views, *curve_views, grid_columns=3), rrb.Horizontal(*lower),
                     row_shares=[3, 1], name="HIL run"),
        rrb.TimePanel(timeline=TIME_TIMELINE), rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"), collapse_panels=False)
    return blueprint, log


def default_rrd_path(mcap_path) -> Path:
    return Path(mcap_path).with_suffix(".rrd")


def write_rrd(mcap_path, out=None) -> tuple[Path, LogHead]:
    """Read ``mcap_path``, write the .rrd (default: beside it); returns (rrd path, the log's head, whose
    ``log`` is the streamed pass's ``LogContents``: completeness, damage, message count).  The recording
    goes to a file sink as it is built (``.rrd.part``, renamed when whole), the log is read in chunks:
    memory does not grow with the run's length."""
    import rerun as rr

    head = LogHead(mcap_path)
    out = Path(out) if out else default_rrd_path(mcap_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    part = out.with_name(out.name + ".part")
    rec = rr.RecordingStream("railway_hil", recording_id=Path(head.path).stem)
    rec.save(str(part))
    try:
        blueprint, head.log = build_recording(head, rec)
        rec.send_blueprint(blueprint, make_active=False, make_default=True)
        rec.flush()
    except BaseException:
        rec.disconnect()
        part.unlink(missing_ok=True)
        raise
    rec.disconnect()       # closes the file sink: the .rrd is complete (footer written) when this returns
    part.replace(out)
    return out, head
