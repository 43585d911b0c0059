"""GNSS against the car's own odometry: a fix stream that the wheels and the gyro contradict is not fused.

The innovation gate of :mod:`~prml2_edge.runtime.filter` refuses a fix that jumps; a spoofer that walks
the position away slowly passes it at every fix (each fix is only centimetres from the last), and the
filter follows. :class:`GnssCheck` compares what the fixes say the car did over the last
:attr:`~GnssCheckConfig.baseline_s` with what the car measured itself over the same time: the
filter's own dead reckoning (its prediction from the model, the wheels and the gyro, step by step),
with every GNSS correction left out. A fix changes that track only through the states it corrects
(velocity, heading rate), so a walk of the fixes in any direction shows up as a displacement the
car did not make. (A track from the CAN gyro alone drifts metres in 8 s on a car with 1.28 deg/s
steps.)

When the discrepancy exceeds the tolerance the fixes are *suspect*: none is fused (the pose
dead-reckons and its status says why), and the filter's position is moved back to where the
odometry puts it from the start of the baseline (what it fused since then was the spoofer's).

The tolerance is what the check does not know, added up (issue 28: a real car's uncalibrated gyro
must not make genuine fixes look like a spoof):

* the noise of the baseline's two ends, each the mean of its fixes over ``average_s`` (1 s: 10 fixes),
  ``gnss_sigmas * sigma_fix * sqrt(1 / n_old + 1 / n_new)`` (a 2-D distance: 4.3 such sigmas are passed once
  in 10^4 comparisons), where ``sigma_fix`` is the
  larger of the configured GNSS noise and the one the fix stream shows (:class:`FixNoise`);
* the odometry's own floor ``tol_m``, and ``tol_per_m`` (wheel scale) per metre driven;
* the filter's heading uncertainty at the baseline's start, ``heading_sigmas * psi_std * distance``;
* the yaw-rate error the filter has not calibrated yet: a rate error ``b`` turns the track by ``b t``,
  which moves its end sideways by ``b T / 2`` per metre over a baseline of ``T`` seconds, so
  ``rate_sigmas * rate_std * T / 2 * distance``, with ``rate_std`` the filter's yaw-offset uncertainty.

The check arms only after :attr:`~GnssCheckConfig.arm_fixes` trusted fixes *and* once that yaw-rate
uncertainty is below :attr:`~GnssCheckConfig.arm_rate_std_dps` (the filter has learned the gyro):
until then a disagreement teaches the calibration instead of refusing the fixes (without the
calibration states nothing learns the offset: the prior widens the tolerance and the check arms
on the fix count alone).

While suspect, the fixes must move like the car over a whole baseline of suspect fixes *and* pass
the filter's innovation gate, :attr:`~GnssCheckConfig.clear_fixes` times in a row: real
GNSS that returns is fused again; a walk is never consistent over a full baseline, and a spoofer
that stops and holds its false position stays outside the gate while the filter is confident (once
its dead-reckoning uncertainty covers the false position, the two cannot be told apart).
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class GnssCheckConfig:
    enabled: bool = True
    baseline_s: float = 8.0  # compare displacements over this long
    min_baseline_s: float = 3.0  # ... at least this long (after a restart)
    tol_m: float = 0.6  # the odometry's own error over a baseline ...
    # ... plus this many sigmas of the difference of the two ends' mean fixes: a 2-D distance is Rayleigh, so k
    # sigmas are exceeded with probability exp(-k^2 / 2): 4.3 is 1e-4 per comparison (2 single fixes were 14 %:
    # at 10 Hz with 1.5 m fixes genuine streams were refused within seconds)
    gnss_sigmas: float = 4.3
    average_s: float = 1.0  # each end of a baseline is the mean of its fixes over this long (10 at 10 Hz)
    tol_per_m: float = 0.01  # scale and gyro error per metre driven ...
    heading_sigmas: float = 1.0  # ... plus this many of the filter's heading sigmas at the baseline's start
    rate_sigmas: float = 1.0  # ... plus this many of its yaw-rate offset sigmas, integrated over the baseline
    clear_fixes: int = 20  # consecutive agreeing fixes (2 s at 10 Hz) end a suspicion
    fused_gap_s: float = 0.5  # a suspicion moves the pose back only when fixes were being fused up to then
    arm_fixes: int = 100  # the check arms after this many trusted fixes (10 s at 10 Hz: the filter has converged)
    arm_rate_std_dps: float = 0.1  # ... and once the filter's yaw-rate offset is known this well


class FixNoise:
    """The fix stream's own noise per axis [m], from its second differences (model-free).

    At a steady fix rate, ``p[k+1] - 2 p[k] + p[k-1]`` is white noise of variance ``6 sigma^2`` plus
    the car's acceleration times ``dt^2`` (centimetres at 10 Hz). A robust scale (the median of the
    squares over the last :attr:`WINDOW` triples, both axes) gives ``sigma`` from seven fixes on; a
    consumer receiver's 1.5 m shows as 1.5 m where the configuration says 0.5 m. Slow, correlated
    errors (multipath) do not show here, and need no wider gate: the filter follows them. Until five
    triples are in (the first half second at 10 Hz) the noise is not known: :attr:`std_m` is None
    (the filter then assumes :data:`UNKNOWN_FACTOR` times its setting).
    """

    WINDOW = 100  # triples kept
    MIN_TRIPLES = 5
    MAX_STD_M = 5.0  # a fix stream noisier than this is not made trustworthy by a wider gate
    UNKNOWN_FACTOR = 3.0
    _MEDIAN_CHI2_1 = 0.4549364  # median of a chi-square with one degree of freedom

    def __init__(self) -> None:
        self._fixes: collections.deque[tuple[float, float, float]] = collections.deque(maxlen=3)
        self._d2: collections.deque[float] = collections.deque(maxlen=2 * self.WINDOW)
        self.std_m: float | None = None

    def add(self, t: float, x: float, y: float) -> None:
        """One fix (a fix already added, by its time, is not added again)."""
        if self._fixes and t <= self._fixes[-1][0]:
            return
        self._fixes.append((t, x, y))
        if len(self._fixes) < 3:
            return
        (t0, x0, y0), (t1, x1, y1), (t2, x2, y2) = self._fixes
        dt0, dt1 = t1 - t0, t2 - t1
        if not (dt0 > 0.0 and abs(dt1 - dt0) <= 0.2 * dt0 and dt0 <= 0.5):
            return  # uneven or sparse fixes: their second difference mixes noise and motion
        self._d2.extend((x2 - 2 * x1 + x0, y2 - 2 * y1 + y0))
        if len(self._d2) >= 2 * self.MIN_TRIPLES:
            var = float(np.median(np.square(self._d2))) / (6.0 * self._MEDIAN_CHI2_1)
            self.std_m = min(math.sqrt(var), self.MAX_STD_M)


@dataclass
class _Entry:
    t: float
    fix: tuple[float, float]
    odo: tuple[float, float]
    pose: tuple[float, float]  # the filter's position then
    psi_std: float = 0.0  # the filter's heading uncertainty then [rad]
    rate_std: float = 0.0  # the filter's yaw-rate offset uncertainty then [rad/s]


def _offset_sum(entries, t_anchor: float, within_s: float, at_most: int,
                start: tuple[float, float] | None = None) -> tuple[float, float, int]:
    """Sum of ``fix - odometry`` over ``start`` (one offset already in, counted) and the leading ``entries``
    within ``within_s`` of ``t_anchor`` (at most ``at_most`` of them), and the count: one end of a baseline."""
    sx, sy = start or (0.0, 0.0)
    n = 0 if start is None else 1
    for e in entries:
        if n >= at_most or abs(e.t - t_anchor) > within_s:
            break
        sx, sy, n = sx + e.fix[0] - e.odo[0], sy + e.fix[1] - e.odo[1], n + 1
    return sx, sy, n


class GnssCheck:
    """Fix-stream displacement against wheel/gyro odometry (module docstring)."""

    def __init__(self, config: GnssCheckConfig | None = None) -> None:
        self.config = config or GnssCheckConfig()
        self.episodes = 0
        self.fixes_refused = 0
        self.first_reason: str | None = None
        self.restarts = 0  # baselines started again because the odometry broke (a slide)
        self.reset()

    def reset(self) -> None:
        self._last: tuple[float, float] | None = None
        self.odo = [0.0, 0.0]  # the filter's own displacement, GNSS corrections left out [m]
        self._new_baseline()
        self._psi_std0 = 0.0  # the filter's heading uncertainty when the suspicion began [rad]
        self._rate_std0 = 0.0  # ... and its yaw-rate offset uncertainty [rad/s]
        self.fix_std_m = 0.5  # the GNSS noise per axis the tolerance assumes (the filter sets it before every fix)
        self.last_discrepancy_m = 0.0
        self._now = 0.0

    def restart(self) -> None:
        """The odometry broke (the car slid: :mod:`~prml2_edge.runtime.slide`): what it says over a baseline that
        holds the break is no evidence against the fixes. The baseline starts again, and a suspicion ends; the check
        arms again after :attr:`~GnssCheckConfig.arm_fixes` trusted fixes."""
        self._new_baseline()
        self.restarts += 1

    def _new_baseline(self) -> None:
        """No baseline, no suspicion, not armed (the odometry track itself goes on)."""
        self.history: collections.deque[_Entry] = collections.deque()
        self.suspect = False
        self.reason = ""
        self._agree = 0
        self._suspect_hist: collections.deque[_Entry] = collections.deque()
        self._trusted = 0  # fixes trusted since the start (the check arms after arm_fixes)

    def step(self, x_m: float, y_m: float) -> None:
        """The filter's position after this step's prediction and measurements, before any GNSS fix: the
        odometry advances by what the filter moved on its own since the last :meth:`settle`."""
        if self._last is not None:
            self.odo[0] += x_m - self._last[0]
            self.odo[1] += y_m - self._last[1]

    def settle(self, x_m: float, y_m: float) -> None:
        """The filter's position at the end of the step (after a GNSS fix, if one was fused)."""
        self._last = (x_m, y_m)

    def _disc(self, hist: collections.deque, fix_xy: tuple[float, float]) -> tuple[float, float, float]:
        """``(discrepancy, tolerance, baseline)`` of ``fix_xy`` against the oldest entry of ``hist``: how far the
        fixes' offset from the odometry (fix minus odometry position) moved between the baseline's two ends, each
        end the mean over :attr:`~GnssCheckConfig.average_s` of its fixes (the newest end: ``fix_xy`` and the
        entries before it), so that one noisy fix is not taken for a walk."""
        cfg = self.config
        old = hist[0]
        ox, oy, n_old = _offset_sum(hist, old.t, cfg.average_s, len(hist))
        nx, ny, n_new = _offset_sum(reversed(hist), self._now, cfg.average_s, len(hist) - n_old + 1,
                                    start=(fix_xy[0] - self.odo[0], fix_xy[1] - self.odo[1]))
        o = (self.odo[0] - old.odo[0], self.odo[1] - old.odo[1])
        dist = math.hypot(*o)
        baseline = max(self._now - old.t, 0.0)
        # the odometry's heading is the filter's from the baseline's start, and it turns with the yaw-rate error
        # the filter has not calibrated: both widen the tolerance, as the fixes' own noise does
        per_m = cfg.tol_per_m + cfg.heading_sigmas * old.psi_std + cfg.rate_sigmas * old.rate_std * baseline / 2.0
        noise = cfg.gnss_sigmas * self.fix_std_m * math.sqrt(1.0 / n_old + 1.0 / n_new)
        tol = cfg.tol_m + noise + per_m * dist
        return math.hypot(nx / n_new - ox / n_old, ny / n_new - oy / n_old), tol, old.t

    def check(self, t: float, fix_xy: tuple[float, float], pose_xy: tuple[float, float], in_gate: bool,
              psi_std: float = 0.0, rate_std: float = 0.0, converged: bool = True) -> tuple[bool, np.ndarray | None]:
        """One fix: ``(trusted, correction)``. ``correction`` (2,) is where to move the filter's position when a
        suspicion starts (the odometry's position from the baseline's start), else None. ``in_gate``: the fix
        passes the filter's innovation gate; ``psi_std`` the filter's heading uncertainty now [rad];
        ``rate_std`` its yaw-rate offset uncertainty [rad/s] (module docstring); ``converged``: False while the
        filter is still learning that offset (the check does not arm then)."""
        cfg = self.config
        if not cfg.enabled:
            return True, None
        self._now = t
        entry = _Entry(t, fix_xy, (self.odo[0], self.odo[1]), pose_xy, min(psi_std, 0.1), min(rate_std, 0.05))
        if self.suspect:
            return self._while_suspect(t, entry, in_gate), None
        hist = self.history
        if hist and t - hist[-1].t > 2.0 * cfg.baseline_s:
            hist.clear()  # after an outage the baseline starts again
            self._trusted = 0
        recent = bool(hist) and t - hist[-1].t <= cfg.fused_gap_s  # the filter was following the fixes
        while len(hist) > 1 and t - hist[1].t >= cfg.baseline_s:
            hist.popleft()
        armed = self._trusted >= cfg.arm_fixes and converged
        if hist and t - hist[0].t >= cfg.min_baseline_s and armed:
            disc, tol, t_old = self._disc(hist, fix_xy)
            self.last_discrepancy_m = disc
            if disc > tol:
                old = hist[0]
                self.suspect = True
                self.episodes += 1
                self._agree = 0
                self.fixes_refused += 1
                self._suspect_hist.clear()
                self._suspect_hist.append(entry)
                self._psi_std0 = old.psi_std
                self._rate_std0 = old.rate_std
                self.reason = (f"GNSS suspect: the fixes moved {disc:.1f} m away from the wheels' and gyro's track "
                               f"over {t - t_old:.1f} s (allowed {tol:.1f} m); not fused while they disagree")
                if self.first_reason is None:
                    self.first_reason = self.reason
                if recent:
                    o = (self.odo[0] - old.odo[0], self.odo[1] - old.odo[1])
                    return False, np.array([old.pose[0] + o[0], old.pose[1] + o[1]])
                return False, None
        hist.append(entry)
        self._trusted += 1
        return True, None

    def _while_suspect(self, t: float, entry: _Entry, in_gate: bool) -> bool:
        """A fix while suspect: trusted again after ``clear_fixes`` in a row that move like the car over a whole
        baseline of suspect fixes *and* lie inside the filter's gate (a walk is never consistent over a full
        baseline; a spoofer holding a false position stays outside the gate while the filter is confident)."""
        cfg = self.config
        sh = self._suspect_hist
        while len(sh) > 1 and t - sh[1].t >= cfg.baseline_s:
            sh.popleft()
        agree = False
        # the heading uncertainty as it was when the suspicion began: dead-reckoning without GNSS grows it, and a
        # tolerance growing with it would let a steady walk through
        entry.psi_std = min(entry.psi_std, self._psi_std0)
        entry.rate_std = min(entry.rate_std, self._rate_std0)
        if t - sh[0].t >= cfg.baseline_s - 0.5:
            disc, tol, _ = self._disc(sh, entry.fix)
            self.last_discrepancy_m = disc
            agree = disc <= tol and in_gate
        sh.append(entry)
        self._agree = self._agree + 1 if agree else 0
        if self._agree >= cfg.clear_fixes:
            self.suspect = False
            self.reason = ""
            self.history.clear()
            self._trusted = cfg.arm_fixes  # armed at once: the car has been checked against these fixes
            return True
        self.fixes_refused += 1
        return False

    def summary(self) -> dict:
        return {"episodes": self.episodes, "fixes_refused": self.fixes_refused, "suspect_now": self.suspect,
                "restarts": self.restarts,
                "first_reason": self.first_reason, "last_discrepancy_m": self.last_discrepancy_m}
