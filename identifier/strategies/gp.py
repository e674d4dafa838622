"""``gp``: the fault curve without a form: a Gaussian-process prior over mu(v_s) and the exact
Gaussian posterior from the motor-speed readings since the slip began (beyond the paper; the
recommended strategy: ``bayes``'s exponential form places the peak by its shape, which on curves of
another form confirms wrong peaks; docs/design/identification.md measures both).

State z = (omega, m) with m the curve's values at G creeps x_j, log-spaced over [``creep_min_kmh``,
``creep_max_kmh``] (``grid_points`` of them) and on at the same step to ``peak_creep_cap_kmh`` (the
working range's cap, below); mu(v) = h(v)^T m, h linear interpolation in log creep (below the first
point: the first value).  The wheelset (eq. A) and the sensor, with T_e held over the period and the
trapezoid over the creep's change (as ``bayes``, identifier/speed_likelihood.py):

    omega(k+1) = omega(k) + a (T_e(k) - c g(k)^T m) + w(k),   g(k) = (h(v_s(k)) + h(v_s(k+1))) / 2,
    m(k+1) = m(k),   a = dt / J,   w ~ N(0, q),   y(k) = omega(k) + n(k),   n ~ N(0, sigma_y^2)

is linear in z given the creeps, so a Kalman filter on z gives the exact posterior N(m^, P_mm):

    b = a c g                                                     (the curve's effect on the speed)
    omega^- = omega^ + a T_e - b^T m^                              predict
    P-_0m = P_0m - P_mm b,   P-_00 = P_00 - 2 b^T P_0m + b^T P_mm b + q
    S = P-_00 + sigma_y^2,   K = P-_{:,0} / S,   e = y - omega^-   innovation
    z^ = z^- + K e,   P = P- - K P-_{0,:}                           update

Prior: m ~ N(``prior_mu``, s^2 exp(-(ln x_i - ln x_j)^2 / (2 l^2))), s = ``prior_mu_std``, l =
``length_log`` (a smoothness over a ratio of creeps, not a shape).  sigma_y and the train-speed line
come from the readings before the slip (speed_model.py, as for ``bayes``).  The process noise is a
model-error allowance plus the creep's noise carried into mu by the posterior mean's slope there:

    q = (a c)^2 (model_mu_std^2 + (dm^/dv_s)^2 sigma_v^2 / 2),   sigma_v = the creep's noise (km/h)

(halved: the trapezoid averages two creeps).

Peak: ``draws`` functions from N(m^, P_mm); each one's maximum over the creeps seen so far (a fault
curve has one peak: a maximum inside the seen range with a fall after it is the peak; a maximum at
the newest creep says only that the peak lies beyond it, and counts as the working range's bound B).
Intervals: quantiles of the draws' peak mu and peak creep.  Confirmation: the interval at
``confirm_level`` within ``tol_peak_mu`` / ``tol_peak_creep`` of its median (speed_model.within_tolerance)
and below B, checked every ``check_samples`` samples.  The published theta is the exponential curve
through the median peak whose shape is nearest the posterior mean where the data were (``fit_shape``,
on a sample that draws no peak): the peak and its intervals are what this strategy states; the rest
of the curve is a convenience.

The working range follows the data.  B starts at ``upper_peak_creep_kmh``.  When the creep passes B
while more than (1 - ``confirm_level``) / 2 of the draws still put the peak at the newest creep (the
rise may go on: the confirmation's own interval cannot close below B), B grows by the factor
``range_growth`` (as often as the creep needs) up to ``peak_creep_cap_kmh``, and the sample budget
``max_samples`` with it, times B / ``upper_peak_creep_kmh`` (a slip takes about as long per km/h of
creep).  ``unconfirmed`` when the creep passes B with the fall seen (the peak is behind it: the serious
stage), or passes the cap, or after the budget.  Below ``upper_peak_creep_kmh`` this is the fixed bound
it was: no sample interpolates on the grid's points past ``creep_max_kmh`` there, so the filter's
values at the first ``grid_points`` creeps and the peak's draws are the same numbers.  An interval is
*open* (``IdentificationEvent.peak_open``) when more than (1 - ``report_level``) / 2 of the draws put
the peak at the newest creep: its upper ends (peak creep B, and those draws' peak mu, a value the
curve passes on its rise) are then the range's, not the data's, and it never counts as covering.

In closed loop (``Strategy.closed_loop``: the TCU's control law acts on the wheel) the rail may change
under a slip's samples: the law holds the creep while the new rail's mu falls, and an identifier of one
static curve explains a fall of mu at a held creep only as the fall past a peak, just below the creep
reached.  So there (``rail_changes``) the change is dated and the samples before it are dropped.  At
every sample, over the last 2W samples (W = ``change_window``), with mu^ the observer's estimate and
v the creep ``lag`` samples earlier (the observer's lag 2 / p: the creep mu^ belongs to):

    d_mu = mean(mu^, newest W) - mean(mu^, the W before),   d_v = the same of v
    a change of rail when  d_mu < -(``change_min_mu`` + s_f max(d_v, 0) + s_r max(-d_v, 0))

s_f = ``change_fall_slope``: no curve falls faster past its peak (mu per km/h); s_r =
``change_rise_slope``: none rises faster, so a creep that falls may take back at most s_r |d_v|
(docs/design/control.md gives the default family's steepest; a NaN mu^ never flags).  At a change,
and once ``change_settle_s`` after the slip's start (a change slow enough to keep mu^ level while the
creep rises under it escapes the test; a change of rail is taken to last no longer), the posterior
starts again from the prior at that sample: the sample budget and ``min_samples`` count from there,
the baseline's noise is kept, and the train-speed line is fitted again to the latest
``baseline_readings`` readings (in closed loop they go on into the buffer during the slip: a line
extrapolated from before the slip drifts over the tenths of a second a closed loop holds one).  The
test fires through a transition, so the last restart dates its end and the posterior holds the new
rail only.  With ``track_train_speed`` the line is fitted again at every sample, to the latest
``baseline_readings`` readings, and the creep uses it at that sample: a line extrapolated from a restart
drifts as the train's acceleration changes with the torque the law commands, and the creep with it,
always the same way, so the peak creep comes out biased and outside its interval.  And in closed loop
a published interval is never narrower than ``floor_peak_mu`` / ``floor_peak_creep_kmh`` either side of
its median (an open one excepted: its upper ends are the range's): the law holds the creep near the
peak for tenths of a second, and the posterior, whose errors are white, then narrows below what it
leaves out (the line's remaining lag, the model's own errors; the floors are of their size).  The
confirmation's test is unchanged, and in open loop, where the slip crosses the peak within tens of
milliseconds, so are the intervals (docs/design/control.md measures both).  Nothing is confirmed
before the settling restart.  And a maximum at the lowest creep seen since the restart is the data's
edge, not a peak (the fall may have begun below): while more than (1 - ``confirm_level``) / 2 of the
draws put it there, nothing is confirmed (as B bounds the rise above).  So a closed-loop confirmation
needs the new rail's samples to span creeps on both sides of the claimed peak.  In open loop the slip
starts from the stable side of one rail, and only that last guard applies (``open_loop_edge``): a rail
that changes under an open-loop slip (a transition blending two rails) makes mu^ fall from the slip's
first sample on, and the posterior's maximum is then the lowest creep seen, a point (every draw's
maximum on the same grid creep: an interval of zero width), whatever the new rail's peak (a drawn bench,
docs/design/identification.md).

And a closed-loop confirmation must rest on samples of one rail (``one_rail``): a transition between rails
lasts up to a second, and a patch recovers as the wheel cleans it, which the test above (a fast fall) does
not date.  Before confirming, with the window the samples since the last restart:

- the TCU's peak estimate (identifier/peak_estimate.py, set on ``rail_estimate`` before each sample) dates
  a change of rail after the window's first sample (``estimate_changes``): the window restarts;
- stationarity (``stationary_sigmas``): r = mu^ - m^(v), v the creep ``lag`` samples earlier, m^ the
  posterior mean, averaged over blocks of ``STATIONARY_BLOCK`` samples; d = mean(second half's blocks) -
  mean(first half's), se from the blocks' spread.  A static rail gives d = 0 within its noise; the rail may
  move by the published peak-mu interval's half-width w and the interval still hold it, so

      (|d| - w) / se > ``stationary_sigmas``   ->  the window restarts

  and a window of fewer than ``stationary_blocks`` blocks is too short to tell (no confirmation yet);
- the published intervals share no peak mu or no peak creep with the estimate's 90 % intervals
  (``estimate_agrees``): withheld, the window kept (one of the two is wrong; the next check may agree).

Every event states the span of the samples it rests on (``IdentificationEvent.samples_from_s`` to
``samples_to_s``: the slip's first sample, or the last restart, to its own), which a bench judges it over.

The numpy code here is the reference; ``compiled`` (default) runs the filter step, the peak draws
with their quantiles and the published curve's shape search by their twins in identifier/kernels.py
(``gp_update``, ``gp_peak``, ``exp_shape_fit``): the numpy calls' overhead, not their arithmetic,
was the cost of the samples that draw the peak (tests/test_gp.py checks the twins agree).  b has at
most four non-zeros (two creeps' interpolation weights), so the twin's predict is O(G); the update
stays O(G^2).  Compiled, every sample's work is bounded, so the TCU's drill (identifier/drill.py)
keeps this code warm before the fault with a copy of few draws on a synthetic slip: code that has
not run since the monitoring began costs more on the first samples after a fault than warm.
"""
from __future__ import annotations

import bisect
import math
from collections import deque

import numpy as np

from ..messages import IdentificationEvent
from ..prior import DEFAULT_BOX, theta_from_phi, theta_from_phi_floats
from .base import Sample, load_kernels
from .speed_model import BaselineStats, SpeedModelStrategy, within_tolerance

#: a grid point whose posterior mean + this many standard deviations is below another's mean - as
#: many is left out of the peak's draws (it holds the maximum with probability < 1e-8)
PLAUSIBLE_SIGMAS = 4.0

#: the shapes (mu(0), a, r) the published curve is chosen from: 3 x 8 x 8 over the prior's box (mu(0)
#: lies below the creeps a slip shows, so it is chosen with the shape, not read off the posterior)
SHAPE_AXES = (np.linspace(*DEFAULT_BOX["mu_at_zero"], 3), np.geomspace(*DEFAULT_BOX["shape_a"], 8),
              np.geomspace(*DEFAULT_BOX["shape_r"], 8))
#: the same grid flat (mu(0) slowest, r fastest): the numpy reference's, and kernels.exp_shape_fit's index
SHAPE_GRID = tuple(g.ravel() for g in np.meshgrid(*SHAPE_AXES, indexing="ij"))
#: the published curve's shape until the first fit
NOMINAL_SHAPE = (0.0, 1.0, 2.0)
#: the sample (modulo ``check_samples``) that fits the published shape, away from the peak's draws
SHAPE_SAMPLE = 2
#: the most seen creeps the shape is fitted at (evenly picked from the seen grid points)
SHAPE_FIT_POINTS = 8

DEFAULTS = {
    "grid_points": 64,                   # G, the creeps the curve is known at
    "creep_min_kmh": 0.02,               # the grid's first and last creep (log-spaced between)
    "creep_max_kmh": 4.0,
    "upper_peak_creep_kmh": 3.0,         # the working range's first bound B on the peak creep
    "peak_creep_cap_kmh": 10.0,          # the highest B may grow to (the grid continues past creep_max_kmh to it)
    "range_growth": 1.25,                # B's factor each time the data show the rise continuing past it
    "prior_mu": 0.15,                    # the prior's mean and standard deviation of mu at every creep
    "prior_mu_std": 0.1,
    "length_log": 1.4,                   # the prior's smoothness: a correlation length in ln(creep)
    "model_mu_std": 6.5e-4,              # model-error allowance, mu per period (process noise q)
    "draws": 400,                        # posterior draws for the peak's quantiles
    "confirm_level": 0.98,               # the interval that must be within tolerance to confirm
    "report_level": 0.90,                # the interval published with every event
    "tol_peak_mu": 0.03,                 # half-width / centre allowed at confirmation
    "tol_peak_creep": 0.10,
    "check_samples": 5,                  # the peak is drawn (and an event published) every this many samples
    "min_samples": 5,                    # no confirmation before this many
    "max_samples": 400,                  # unconfirmed after this many (times B / upper_peak_creep_kmh)
    "baseline_readings": 400,            # readings before the slip for sigma_y and the train-speed line
    "sigma_y_fallback": 0.005,           # rad/s, when there is no baseline
    "compiled": True,                    # the filter step and the peak draws by identifier/kernels.py; False: numpy
    "rail_changes": True,                # in closed loop: date changes of rail and drop the samples before them
    "track_train_speed": True,           # in closed loop (with rail_changes): the line refitted every sample
    "floor_peak_mu": 0.001,              # in closed loop: the published interval's least half-width, peak mu ...
    "floor_peak_creep_kmh": 0.02,        # ... and peak creep (km/h)
    "change_settle_s": 0.2,              # closed loop: the samples of this long from the slip's start are dropped
    "change_window": 20,                 # W, samples per window of the rail-change test
    "change_min_mu": 0.003,              # the fall of mean mu^ beyond the curve's allowance that flags a change
    "change_fall_slope": 0.15,           # s_f, the steepest fall of a curve past its peak, mu per km/h
    "change_rise_slope": 3.5,            # s_r, the steepest rise of a curve, mu per km/h
    "open_loop_edge": True,              # in open loop too: no confirmation of a maximum at the lowest creep seen
    "one_rail": True,                    # closed loop: confirm only from a window that holds one rail (the tests below)
    "stationary_sigmas": 1.0,            # mu^'s drift against the posterior beyond the interval, in standard errors
    "stationary_blocks": 10,             # the fewest of the drift test's blocks a confirmation's window spans
    "estimate_changes": True,            # a change the TCU's peak estimate dates inside the window restarts it
    "estimate_agrees": True,             # no confirmation whose intervals miss the estimate's entirely
}

#: the residuals of the stationarity test are averaged over blocks of this many samples (several of the
#: observer's lags 2 / p: the blocks' means are then nearly independent)
STATIONARY_BLOCK = 10


class GpStrategy(SpeedModelStrategy):
    """Gaussian-process posterior over the curve's values (module docstring)."""

    name = "gp"
    defaults = DEFAULTS
    drill_size_option = "draws"         # the TCU's drill (identifier/drill.py) runs a copy with few draws
    drill_size_min = 50                 # (the fewest ``_check`` allows)

    @property
    def keeps_warm(self) -> bool:
        # compiled, every sample's work is bounded (one filter step, every 5th the peak's draws)
        return self._compiled

    def __init__(self, settings, seed: int = 0):
        super().__init__(settings, seed)
        o = self.opts = self.merged_options()
        self._check(o)
        veh = settings.vehicle
        self.inertia = veh.equivalent_inertia_kgm2
        self.c = veh.torque_per_mu_nm
        self.log_x = self.grid_log_creeps(o)
        g = self.log_x.size
        self._log_x_list = self.log_x.tolist()        # for bisect: a scalar search without numpy's overhead
        d = self.log_x[:, None] - self.log_x[None, :]
        self.prior_cov = float(o["prior_mu_std"]) ** 2 * np.exp(-0.5 * (d / float(o["length_log"])) ** 2)
        self._z0 = np.concatenate([[0.0], np.full(g, float(o["prior_mu"]))])    # the prior of z, omega's set at the slip
        self._P0 = np.zeros((g + 1, g + 1))
        self._P0[1:, 1:] = self.prior_cov
        self.normals = self.rng.standard_normal((g, int(o["draws"])))
        self._compiled = bool(o["compiled"]) and load_kernels().AVAILABLE
        if self._compiled:
            load_kernels().warm_up()
        conf, rep = float(o["confirm_level"]), float(o["report_level"])
        self.bound_kmh = float(o["upper_peak_creep_kmh"])     # B, the working range's bound on the peak creep
        self.open_draws = 0                   # of the last peak draws, those whose maximum is the newest creep
        self.max_samples = int(o["max_samples"])     # the sample budget (grows with B)
        self._levels = np.array([0.5 * (1 - conf), 0.5 * (1 - rep), 0.5, 0.5 * (1 + rep), 0.5 * (1 + conf)])
        self._row0 = np.empty(g + 1)
        self._scratch = (np.empty((g, g)), np.empty((g, g)), np.empty((g, int(o["draws"]))))  # root, cov, f: gp_peak
        self._draw_mu, self._draw_creep = np.empty(int(o["draws"])), np.empty(int(o["draws"]))
        self._warm_up()
        self._shape = NOMINAL_SHAPE           # (mu(0), a, r) of the published curve (``fit_shape``)
        self.theta_peak = None                # the last published median peak (mu, creep km/h)
        self.baseline = BaselineStats(int(o["baseline_readings"]))
        self.z = self.P = None
        self._ix_prev = None                  # (grid index, fraction) of the previous sample's creep (``_interp``)
        self._b_idx, self._b_w = np.zeros(4, np.intp), np.zeros(4)     # b's non-zeros for kernels.gp_update
        self.seen_lo = self.seen_hi = math.nan
        self.peak_mu_ci = self.peak_creep_ci = (math.nan, math.nan)
        # the rail-change test (module docstring): its windows run over every sample, across restarts
        w = int(o["change_window"])
        self._lag = max(round(2.0 / settings.observer_pole_rad_s / settings.period_s), 0)
        self._test_v: deque[float] = deque(maxlen=2 * w + self._lag)
        self._test_mu: deque[float] = deque(maxlen=2 * w)
        self._n0 = 0                          # samples before the last restart (none in open loop)
        self._settle_until_s = math.inf       # closed loop: the restart that ends the slip's first stretch
        self.restarts = 0
        self.below_draws = 0                  # of the last peak draws, those whose maximum is the lowest seen creep
        #: set by the TCU before each sample (closed loop): its peak estimate of the current rail
        #: (identifier/peak_estimate.py ``PeakEstimate``), or None
        self.rail_estimate = None

    @property
    def _dates_changes(self) -> bool:
        return self.closed_loop and bool(self.opts["rail_changes"])

    @staticmethod
    def grid_log_creeps(o: dict) -> np.ndarray:
        """ln x_j: ``grid_points`` log-spaced over [``creep_min_kmh``, ``creep_max_kmh``], then on at
        the same step until ``peak_creep_cap_kmh`` is inside (the first ``grid_points`` are the same
        numbers whatever the cap)."""
        log_x = np.linspace(math.log(float(o["creep_min_kmh"])), math.log(float(o["creep_max_kmh"])),
                            int(o["grid_points"]))
        step = log_x[-1] - log_x[-2]
        extra = max(0, math.ceil((math.log(float(o["peak_creep_cap_kmh"])) - log_x[-1]) / step - 1e-9))
        return np.concatenate([log_x, log_x[-1] + step * np.arange(1, extra + 1)])

    def _check(self, o: dict) -> None:
        """Bad options are refused by name, before anything is built on them."""
        def need(ok: bool, key: str, what: str) -> None:
            if not ok:
                raise ValueError(f"{self.name}: {key} must be {what}, got {o[key]!r}")
        for key, low in (("grid_points", 8), ("draws", 50), ("check_samples", 1), ("min_samples", 1),
                         ("max_samples", 1), ("baseline_readings", 2)):
            need(isinstance(o[key], int) and not isinstance(o[key], bool) and o[key] >= low, key, f"an integer >= {low}")
        for key in ("creep_min_kmh", "creep_max_kmh", "upper_peak_creep_kmh", "peak_creep_cap_kmh", "prior_mu_std",
                    "length_log", "tol_peak_mu", "tol_peak_creep", "sigma_y_fallback"):
            need(isinstance(o[key], (int, float)) and math.isfinite(o[key]) and o[key] > 0, key, "a number > 0")
        for key in ("prior_mu", "model_mu_std"):
            need(isinstance(o[key], (int, float)) and math.isfinite(o[key]) and o[key] >= 0, key, "a number >= 0")
        need(isinstance(o["change_window"], int) and not isinstance(o["change_window"], bool) and o["change_window"] >= 2,
             "change_window", "an integer >= 2")
        need(isinstance(o["rail_changes"], bool), "rail_changes", "true or false")
        need(isinstance(o["open_loop_edge"], bool), "open_loop_edge", "true or false")
        for key in ("one_rail", "estimate_changes", "estimate_agrees"):
            need(isinstance(o[key], bool), key, "true or false")
        need(isinstance(o["stationary_blocks"], int) and not isinstance(o["stationary_blocks"], bool)
             and o["stationary_blocks"] >= 4, "stationary_blocks", "an integer >= 4")
        need(isinstance(o["stationary_sigmas"], (int, float)) and not isinstance(o["stationary_sigmas"], bool)
             and math.isfinite(o["stationary_sigmas"]) and o["stationary_sigmas"] >= 0, "stationary_sigmas", "a number >= 0")
        need(isinstance(o["track_train_speed"], bool), "track_train_speed", "true or false")
        for key, top in (("floor_peak_mu", 1.0), ("floor_peak_creep_kmh", 10.0)):
            need(isinstance(o[key], (int, float)) and not isinstance(o[key], bool) and 0.0 <= o[key] <= top,
                 key, f"a number in [0, {top}]")
        for key in ("change_settle_s", "change_min_mu", "change_fall_slope", "change_rise_slope"):
            need(isinstance(o[key], (int, float)) and math.isfinite(o[key]) and o[key] >= 0, key, "a number >= 0")
        for key in ("confirm_level", "report_level"):
            need(isinstance(o[key], (int, float)) and 0.5 < o[key] < 1.0, key, "in (0.5, 1)")
        need(o["creep_max_kmh"] > o["creep_min_kmh"], "creep_max_kmh", f"above creep_min_kmh ({o['creep_min_kmh']})")
        need(o["creep_min_kmh"] < o["upper_peak_creep_kmh"] <= o["creep_max_kmh"], "upper_peak_creep_kmh",
             "within the grid's creeps")
        need(o["peak_creep_cap_kmh"] >= o["upper_peak_creep_kmh"], "peak_creep_cap_kmh",
             f"at least upper_peak_creep_kmh ({o['upper_peak_creep_kmh']})")
        need(isinstance(o["range_growth"], (int, float)) and math.isfinite(o["range_growth"]) and o["range_growth"] > 1,
             "range_growth", "a number > 1")

    def _warm_up(self) -> None:
        """Run the peak's and the published curve's code once on the prior, before the fault: their
        first call in a process costs several times a later one (numpy's and numba's first-use work),
        and the first sample that checks the peak would pay it."""
        self.z, self.P = self._z0.copy(), self._P0.copy()
        self.seen_lo, self.seen_hi = 0.3, 1.0
        q = self.peak_quantiles(np.array([0.05, 0.5, 0.95]))
        self.fit_shape(float(q[1, 0]), float(q[1, 1]))
        self.z = self.P = None
        self.seen_lo = self.seen_hi = math.nan

    # -- the model -----------------------------------------------------------------------------
    def _interp(self, creep_kmh: float) -> tuple[int, float]:
        """(i, f): mu(v) = (1 - f) m_i + f m_(i+1), linear in log creep; below the first grid creep
        the first value, above the last the last."""
        g = self._log_x_list
        x = max(math.log(creep_kmh) if creep_kmh > 0.0 else g[0], g[0])
        if x >= g[-1]:
            return len(g) - 2, 1.0
        i = bisect.bisect_right(g, x) - 1
        return i, (x - g[i]) / (g[i + 1] - g[i])

    def h(self, creep_kmh: float) -> np.ndarray:
        """Interpolation weights of mu(v) on the grid (``_interp`` as a G-vector)."""
        i, f = self._interp(creep_kmh)
        out = np.zeros(self.log_x.size)
        out[i], out[i + 1] = 1.0 - f, f
        return out

    def slope_per_kmh(self, creep_kmh: float) -> float:
        """d mu / d v_s of the posterior mean at ``creep_kmh`` (its grid interval; 0 outside the grid)."""
        g = self._log_x_list
        if not creep_kmh > 0.0:
            return 0.0
        i = bisect.bisect_right(g, math.log(creep_kmh)) - 1
        if i < 0 or i >= len(g) - 1:
            return 0.0
        return (self.z[2 + i] - self.z[1 + i]) / (math.exp(g[i + 1]) - math.exp(g[i]))

    def _open(self, s: Sample) -> None:
        o = self.opts
        self.sigma_y = self.open_baseline(s, o["sigma_y_fallback"])
        # q: the model error, and the creep's noise carried into mu by the curve's slope there
        self._creep_var_kmh2 = 0.5 * (self.creep_per_motor_speed * self.sigma_y) ** 2      # halved by the trapezoid
        self._model_var = float(o["model_mu_std"]) ** 2
        if self._dates_changes:
            self._rail_changed(s, self.creep_for_likelihood(s))
            self._settle_until_s = s.t_s + float(o["change_settle_s"])
        self._restart(s)

    def on_reading(self, step: int, motor_speed_rad_s: float, train_speed_ms: float) -> None:
        """Every reading before the slip (the baseline); in closed loop every reading, so a restart
        takes the train-speed line from the readings just before it (module docstring)."""
        if self._prev is None or self._dates_changes:
            self.baseline.add(step, motor_speed_rad_s, train_speed_ms)

    def _restart(self, s: Sample) -> None:
        """The posterior from the prior at sample ``s`` (the slip's first, or a change of rail's)."""
        if self._prev is not None:        # a change of rail's: the train-speed line from the latest readings
            self._line = self.baseline.stats(self._compiled)[1]
        self.z = self._z0.copy()
        self.z[0] = s.motor_speed_rad_s
        self.P = self._P0.copy()
        self.P[0, 0] = self.sigma_y ** 2
        v = self.creep_for_likelihood(s)
        self._ix_prev = self._interp(v)
        self.seen_lo = self.seen_hi = v
        self._n0 = len(self._v) - 1

    def _rail_changed(self, s: Sample, v: float) -> bool:
        """The rail-change test of the module docstring on the windows that end at sample ``s``."""
        tv, tm = self._test_v, self._test_mu
        tv.append(v)
        tm.append(s.mu_hat)
        if len(tv) < tv.maxlen:
            return False
        o, w = self.opts, tm.maxlen // 2
        mus, vs = list(tm), list(tv)[:2 * w]          # v: the creeps ``lag`` samples before the mu^
        d_mu = (sum(mus[w:]) - sum(mus[:w])) / w
        d_v = (sum(vs[w:]) - sum(vs[:w])) / w
        allowed = (float(o["change_min_mu"]) + float(o["change_fall_slope"]) * max(d_v, 0.0)
                   + float(o["change_rise_slope"]) * max(-d_v, 0.0))
        return d_mu < -allowed

    def _step(self, s: Sample) -> None:
        periods = max(s.step - self._prev.step, 1)
        if self._dates_changes and self.opts["track_train_speed"]:     # the line through the latest readings
            self._line = self.baseline.stats(self._compiled)[1]
        v = self.creep_for_likelihood(s)
        if self._dates_changes and (self._rail_changed(s, v) or s.t_s >= self._settle_until_s):
            if s.t_s >= self._settle_until_s:
                self._settle_until_s = math.inf
            self._restart(s)
            self.restarts += 1
            return
        ix_new = self._interp(v)
        a = periods * self.period_s / self.inertia
        z, P = self.z, self.P
        slope = self.slope_per_kmh(v)
        q = periods * (self.period_s * self.c / self.inertia) ** 2 * (self._model_var + slope * slope * self._creep_var_kmh2)
        self.q_last = q
        (ip, fp), (i_new, f_new) = self._ix_prev, ix_new
        self._ix_prev = ix_new
        self.seen_lo, self.seen_hi = min(self.seen_lo, v), max(self.seen_hi, v)
        half_ac = 0.5 * a * self.c
        if self._compiled:      # b = a c g with g's four non-zeros (two creeps' interpolation weights)
            idx, w = self._b_idx, self._b_w
            idx[0], idx[1], idx[2], idx[3] = ip, ip + 1, i_new, i_new + 1
            w[0], w[1], w[2], w[3] = half_ac * (1.0 - fp), half_ac * fp, half_ac * (1.0 - f_new), half_ac * f_new
            load_kernels().gp_update(z, P, idx, w, a * self._prev.torque_nm, q, self.sigma_y ** 2,
                                     s.motor_speed_rad_s, self._row0)
            return
        b = np.zeros(self.log_x.size)                                                 # b = a c g
        b[ip] += half_ac * (1.0 - fp)
        b[ip + 1] += half_ac * fp
        b[i_new] += half_ac * (1.0 - f_new)
        b[i_new + 1] += half_ac * f_new
        z[0] += a * self._prev.torque_nm - b @ z[1:]                                 # predict
        p0m = P[0, 1:] - P[1:, 1:] @ b
        p00 = P[0, 0] - 2.0 * b @ P[0, 1:] + b @ P[1:, 1:] @ b + q
        P[0, 1:] = P[1:, 0] = p0m
        P[0, 0] = p00
        S = p00 + self.sigma_y ** 2                                                   # innovation
        e = s.motor_speed_rad_s - z[0]
        k = P[:, 0] / S
        z += k * e                                                                    # update
        P -= np.outer(k, P[0, :])

    # -- the peak --------------------------------------------------------------------------------
    def _seen(self) -> tuple[int, int]:
        """The grid indices (first, last) of the creeps seen so far; while they span fewer than three
        points, the three from the one below the seen creeps (the peak's draws need a neighbour on
        each side; a wider fallback, e.g. from the grid's start, costs the first checks most)."""
        g = self._log_x_list
        i0 = bisect.bisect_left(g, math.log(max(self.seen_lo, 1e-300)))
        i1 = bisect.bisect_right(g, math.log(max(self.seen_hi, 1e-300))) - 1
        if i1 - i0 < 2:
            i1 = min(max(i1 + 1, 2), len(g) - 1)
            i0 = i1 - 2
        return i0, i1

    def _region(self):
        """(grid indices, position of the newest seen creep among them or -1): the seen creeps
        where the maximum can be (points whose mean + PLAUSIBLE_SIGMAS sd reach what another surely
        has), with a neighbour on each side for the parabola."""
        i0, i1 = self._seen()
        idx = np.arange(i0, i1 + 1)
        m_all, sd = self.z[1:][idx], np.sqrt(np.clip(np.diag(self.P)[1:][idx], 0.0, None))
        cand = np.flatnonzero(m_all + PLAUSIBLE_SIGMAS * sd >= np.max(m_all - PLAUSIBLE_SIGMAS * sd))
        idx = idx[max(cand[0] - 1, 0):min(cand[-1] + 2, idx.size)]
        return idx, (idx.size - 1 if idx[-1] == i1 else -1)

    def peak_draws(self) -> tuple[np.ndarray, np.ndarray]:
        """(peak mu, peak creep km/h) of each draw from the posterior, over the creeps seen so far:
        the numpy reference of ``kernels.gp_peak``."""
        idx, last_pos = self._region()
        m = self.z[1:][idx]
        cov = self.P[1:, 1:][np.ix_(idx, idx)]
        cov = 0.5 * (cov + cov.T) + 1e-12 * np.eye(idx.size)
        try:
            root = np.linalg.cholesky(cov)
        except np.linalg.LinAlgError:       # numerically semi-definite: the symmetric root
            w, vecs = np.linalg.eigh(cov)
            root = vecs * np.sqrt(np.clip(w, 0.0, None))
        f = m[:, None] + root @ self.normals[:idx.size]
        cols = np.arange(f.shape[1])
        j = np.argmax(f, axis=0)
        peak_mu = f[j, cols]
        x = self.log_x[idx]
        off = np.zeros(f.shape[1])
        if idx.size >= 3:       # parabola through the maximum and its neighbours (in log creep) where it is inside
            jj = np.clip(j, 1, idx.size - 2)
            fl, fc, fr = (f[jj + d, cols] for d in (-1, 0, 1))
            denom = fl - 2.0 * fc + fr
            with np.errstate(divide="ignore", invalid="ignore"):
                off = np.clip(np.where((j == jj) & (denom < 0), 0.5 * (fl - fr) / denom, 0.0), -0.5, 0.5)
        step = x[1] - x[0] if x.size > 1 else 0.0
        creep = np.exp(x[j] + off * step)
        creep[j == last_pos] = self.bound_kmh     # the peak lies further on
        return peak_mu, creep

    def peak_quantiles(self, qs: np.ndarray) -> np.ndarray:
        """(len(qs), 2): the quantiles ``qs`` of the draws' peak mu and peak creep; ``open_draws`` <-
        how many draws put the peak at the newest creep (their peak creep is B)."""
        if not self._compiled:
            draws = np.vstack(self.peak_draws())
            self.open_draws = int(np.count_nonzero(draws[1] == self.bound_kmh))
            if self._guards_edge:
                self.below_draws = int(np.count_nonzero(draws[1] <= self._lowest_seen_kmh()))
            return np.quantile(draws, qs, axis=1)
        out = np.empty((qs.size, 2))
        load_kernels().gp_peak(self.z, self.P, *self._seen(), PLAUSIBLE_SIGMAS, self.normals, self.log_x,
                               self.bound_kmh, qs, *self._scratch, self._draw_mu, self._draw_creep, out)
        self.open_draws = int(np.count_nonzero(self._draw_creep == self.bound_kmh))
        if self._guards_edge:
            self.below_draws = int(np.count_nonzero(self._draw_creep <= self._lowest_seen_kmh()))
        return out

    def _lowest_seen_kmh(self) -> float:
        """The lowest seen grid creep, a hair above: a draw's maximum there has that creep (no parabola at a
        region's end), any other lies at least half a grid step above it."""
        return math.exp(self._log_x_list[self._seen()[0]]) * (1.0 + 1e-9)

    def _open_beyond(self, level: float) -> bool:
        """The last draws' interval at ``level`` reaches past the creeps seen: more than (1 - level) / 2
        of them put the peak at the newest creep."""
        return self.open_draws > 0.5 * (1.0 - level) * self._draw_creep.size

    @property
    def _guards_edge(self) -> bool:
        """Whether a maximum at the lowest creep seen holds a confirmation back (module docstring)."""
        return self._dates_changes or (not self.closed_loop and bool(self.opts["open_loop_edge"]))

    def _at_edge(self) -> bool:
        """More than (1 - confirm_level) / 2 of the last draws put the peak at the lowest creep seen since
        the slip began (closed loop: since the restart): the data's edge, not a peak."""
        return self.below_draws > 0.5 * (1.0 - float(self.opts["confirm_level"])) * self._draw_creep.size

    def _held_back(self) -> bool:
        """No confirmation (module docstring): in closed loop while the settling restart is still ahead
        (or the rail-change test has not filled its windows); in both, with the guard, at the data's edge."""
        if self._dates_changes and (len(self._test_v) < self._test_v.maxlen or math.isfinite(self._settle_until_s)):
            return True
        return self._guards_edge and self._at_edge()

    def _evaluate(self, s: Sample) -> list[IdentificationEvent]:
        o = self.opts
        n = len(self._v) - self._n0           # samples since the slip began (closed loop: since the last restart)
        check = n % int(o["check_samples"]) == 0
        cap = float(o["peak_creep_cap_kmh"])
        if s.creep_speed_kmh > self.bound_kmh and self.bound_kmh < cap:
            self.peak_quantiles(self._levels)          # does the rise continue past B? (open_draws)
            if self._open_beyond(float(o["confirm_level"])):
                while s.creep_speed_kmh > self.bound_kmh and self.bound_kmh < cap:
                    self.bound_kmh = min(self.bound_kmh * float(o["range_growth"]), cap)
                self.max_samples = round(int(o["max_samples"]) * self.bound_kmh / float(o["upper_peak_creep_kmh"]))
        ends = s.creep_speed_kmh > self.bound_kmh or n >= self.max_samples
        if n % int(o["check_samples"]) == SHAPE_SAMPLE and self.theta_peak is not None and not ends:
            self._shape = self.fit_shape(*self.theta_peak)     # on a sample that draws no peak
        if not (check or ends):
            return []
        # one set of draws, one quantile pass: the confirmation's interval, the median, the published one
        q = self.peak_quantiles(self._levels)
        (mu_lo, creep_lo), _, (mu_mid, creep_mid), _, (mu_hi, creep_hi) = q
        if (check and n >= int(o["min_samples"]) and within_tolerance(mu_lo, mu_mid, mu_hi, float(o["tol_peak_mu"]))
                and within_tolerance(creep_lo, creep_mid, creep_hi, float(o["tol_peak_creep"]))
                and creep_hi < self.bound_kmh and not self._held_back()):
            refusal = self._unattributable(s, q)
            if refusal is None:
                return [self._publish(s, "confirmed", q)]
            if refusal in ("estimate_change", "not_stationary"):     # the window holds more than one rail: forget it
                event = self._publish(s, "unconfirmed" if ends else "correction", q)
                self._restart(s)
                self.restarts += 1
                return [event]
        return [self._publish(s, "unconfirmed" if ends else "correction", q)]

    def _unattributable(self, s: Sample, q: np.ndarray) -> str | None:
        """Why a confirmation due now cannot be attributed to one rail (module docstring), or None: in closed loop,
        ``estimate_change``: the TCU's peak estimate dates a change of rail after the window's first sample;
        ``too_short``: the window spans fewer than ``stationary_blocks`` of the stationarity test's blocks;
        ``not_stationary``: the stationarity test; ``estimate_disagrees``: the published intervals and the
        estimate's share no peak mu or no peak creep."""
        if not (self._dates_changes and self.opts["one_rail"]):
            return None
        o, est = self.opts, self.rail_estimate
        first = self.samples_seen[self._n0]
        if est is not None and o["estimate_changes"] and est.since_step > first.step:
            return "estimate_change"
        if (len(self._v) - self._n0 - self._lag) // STATIONARY_BLOCK < int(o["stationary_blocks"]):
            return "too_short"
        if self._drift_sigmas(self._interval_half_width_mu(q)) > float(o["stationary_sigmas"]):
            return "not_stationary"
        if est is not None and o["estimate_agrees"]:
            (mu_lo, creep_lo), (mu_hi, creep_hi) = self._published_bounds(q)
            (e_mu_lo, e_mu_hi), (e_v_lo, e_v_hi) = est.peak_mu_ci, est.peak_creep_ci
            if mu_hi < e_mu_lo or mu_lo > e_mu_hi or creep_hi < e_v_lo or creep_lo > e_v_hi:
                return "estimate_disagrees"
        return None

    def _published_bounds(self, q: np.ndarray, peak_open: bool = False
                          ) -> tuple[tuple[float, float], tuple[float, float]]:
        """((peak mu lo, peak creep lo), (hi, hi)) of the intervals ``_publish`` states from ``q``: in closed loop
        never narrower than the floors (module docstring), but an open interval's upper ends stay the range's."""
        (mu_lo, creep_lo), (mu_mid, creep_mid), (mu_hi, creep_hi) = q[1], q[2], q[3]
        if self.closed_loop and not peak_open:
            f_mu, f_creep = float(self.opts["floor_peak_mu"]), float(self.opts["floor_peak_creep_kmh"])
            mu_lo, mu_hi = min(mu_lo, mu_mid - f_mu), max(mu_hi, mu_mid + f_mu)
            creep_lo, creep_hi = min(creep_lo, creep_mid - f_creep), max(creep_hi, creep_mid + f_creep)
        return (float(mu_lo), float(creep_lo)), (float(mu_hi), float(creep_hi))

    def _interval_half_width_mu(self, q: np.ndarray) -> float:
        """The published peak-mu interval's least half-width about its median: how far the rail's mu may move
        across the window and the interval still hold it."""
        (lo, _), (hi, _) = self._published_bounds(q)
        mid = float(q[2][0])
        return max(min(mid - lo, hi - mid), 0.0)

    def _drift_sigmas(self, allowed_mu: float) -> float:
        """The stationarity test (module docstring): r = mu^ - m^(v) over the window's samples (v the creep ``lag``
        samples earlier, m^ the posterior mean); d = mean(r, second half) - mean(r, first half) with its standard
        error from block means (``STATIONARY_BLOCK`` samples); returns (|d| - ``allowed_mu``) / se (0 when too
        few blocks)."""
        lag, end = self._lag, len(self._v)       # _v, _mu: every sample's creep and mu^ (Strategy)
        n_blocks = (end - self._n0 - lag) // STATIONARY_BLOCK
        if n_blocks < 4:
            return 0.0
        n = n_blocks * STATIONARY_BLOCK
        v = np.array(self._v[end - lag - n:end - lag])
        mu = np.array(self._mu[end - n:end])
        m = np.interp(np.log(np.maximum(v, math.exp(self._log_x_list[0]))), self.log_x, self.z[1:])
        blocks = ((mu - m).reshape(n_blocks, STATIONARY_BLOCK).sum(axis=1) / STATIONARY_BLOCK).tolist()
        if not all(math.isfinite(b) for b in blocks):
            return 0.0
        h = n_blocks // 2
        first, second = blocks[:h], blocks[n_blocks - h:]
        m1, m2 = sum(first) / h, sum(second) / h
        d = m2 - m1
        var = (sum((b - m1) ** 2 for b in first) + sum((b - m2) ** 2 for b in second)) / max(2 * h - 2, 1)
        se = math.sqrt(var * 2.0 / h) if var > 0 else 0.0
        excess = abs(d) - allowed_mu
        if excess <= 0:
            return 0.0
        return excess / se if se > 0 else math.inf

    def _publish(self, s: Sample, kind: str, q: np.ndarray) -> IdentificationEvent:
        """The event of ``kind`` with the median peak and the intervals at ``report_level`` (rows 1-3
        of ``q``, the quantiles of ``_evaluate``; columns peak mu, peak creep)."""
        mu_mid, creep_mid = q[2]
        peak_open = self._open_beyond(float(self.opts["report_level"]))
        (mu_lo, creep_lo), (mu_hi, creep_hi) = self._published_bounds(q, peak_open)
        self.theta_peak = (float(mu_mid), float(creep_mid))
        mu0, a, r = self._shape
        theta = theta_from_phi_floats((float(mu_mid), float(creep_mid), min(mu0, 0.5 * float(mu_mid)), a, r))
        return self.event(s, kind, theta, (float(mu_lo), float(mu_hi)), (float(creep_lo), float(creep_hi)),
                          peak_open=peak_open, samples_from_s=self.samples_seen[self._n0].t_s)

    def fit_shape(self, peak_mu: float, peak_creep_kmh: float) -> tuple[float, float, float]:
        """(mu(0), a, r) of identifier/prior.py's form, on SHAPE_GRID, whose curve through the peak
        (peak_creep_kmh, peak_mu) is nearest in least squares to the posterior mean at up to
        SHAPE_FIT_POINTS of the grid's creeps seen so far: the shape of the published curve."""
        i0, i1 = self._seen()
        pick = np.arange(i0, i1 + 1, max(1, (i1 - i0) // (SHAPE_FIT_POINTS - 1)))
        v, m = np.exp(self.log_x[pick]), self.z[1 + pick]
        mu0, a, r = SHAPE_GRID
        mu0 = np.minimum(mu0, 0.5 * peak_mu)
        if self._compiled:
            i = load_kernels().exp_shape_fit(*SHAPE_AXES, peak_mu, peak_creep_kmh, v, m, np.empty(5))
        else:
            phi = np.stack([np.full(a.size, peak_mu), np.full(a.size, peak_creep_kmh), mu0, a, r], axis=1)
            l0, l1, l2, t1, t2 = (col[:, None] for col in theta_from_phi(phi).T)
            i = int(np.argmin(np.sum((l0 + l1 * np.exp(t1 * v) + l2 * np.exp(t2 * v) - m) ** 2, axis=1)))
        return float(mu0[i]), float(a[i]), float(r[i])
