"""GNSS against the car's own odometry: a fix stream that the wheels and the gyro contradict is not fused.

The innovation gate of :mod:`~prml2_edge.runtime.filter` refuses a fix that jumps; a spoofer that walks
the position away slowly passes it at every fix (each fix is only centimetres from the last), and the
filter follows. :class:`GnssCheck` compares what the fixes say the car did over the last
:attr:`~GnssCheckConfig.baseline_s` with what the car measured itself over the same time: a track
integrated from the rear-axle wheel speed (scaled by the filter's wheel-scale state) along a heading
integrated from the CAN yaw rate (less the filter's offset state). That heading follows the
filter's slowly (:attr:`~GnssCheckConfig.align_tau_s`) and only while GNSS is trusted, so a walk
of the fixes in any direction shows up as a displacement the odometry does not have.

When the discrepancy exceeds ``tol_m + tol_per_m * distance`` the fixes are *suspect*: none is
fused (the pose dead-reckons and its status says why), and the filter's position is moved back to
where the odometry puts it from the start of the baseline (what it fused since then was the
spoofer's). While suspect, each fix is compared with the odometry's track from that last trusted
position (same tolerance, over the distance since); the suspicion ends when
:attr:`~GnssCheckConfig.clear_fixes` consecutive fixes agree with it: real GNSS that returns after a
spoofer stops is fused again; a spoofer that keeps its false position is not.
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
    tol_m: float = 2.5  # GNSS noise of the two end fixes and the odometry's
    tol_per_m: float = 0.02  # heading (~1 deg) and scale error per metre driven
    align_tau_s: float = 60.0  # the odometry heading follows the filter's this slowly (trusted GNSS only)
    clear_fixes: int = 20  # consecutive agreeing fixes (2 s at 10 Hz) end a suspicion
    min_speed_mps: float = 1.0  # below: the odometry holds (ABS wheel speeds read 0)
    fused_gap_s: float = 0.5  # a suspicion moves the pose back only when fixes were being fused up to then


@dataclass
class _Entry:
    t: float
    fix: tuple[float, float]
    odo: tuple[float, float]
    pose: tuple[float, float]  # the filter's position then


class GnssCheck:
    """Fix-stream displacement against wheel/gyro odometry (module docstring)."""

    def __init__(self, config: GnssCheckConfig | None = None) -> None:
        self.config = config or GnssCheckConfig()
        self.episodes = 0
        self.fixes_refused = 0
        self.first_reason: str | None = None
        self.reset()

    def reset(self) -> None:
        self.psi: float | None = None  # odometry heading [rad]
        self.odo = [0.0, 0.0]
        self.history: collections.deque[_Entry] = collections.deque()
        self.suspect = False
        self.reason = ""
        self._agree = 0
        self._anchor: tuple | None = None  # (t, odometry, position) the suspect fixes are judged from
        self.last_discrepancy_m = 0.0

    def step(self, dt: float, yaw_rate: float | None, wheel_speed: float | None, filter_psi: float) -> None:
        """Integrate the odometry one step (``yaw_rate`` and ``wheel_speed`` already calibrated; None: invalid)."""
        cfg = self.config
        if self.psi is None:
            self.psi = filter_psi
        if yaw_rate is None or wheel_speed is None:
            self.history.clear()  # a hole in the odometry: start a new baseline
            self.psi = filter_psi if not self.suspect else self.psi
            return
        self.psi += yaw_rate * dt
        if not self.suspect:
            d = math.remainder(filter_psi - self.psi, 2.0 * math.pi)
            self.psi += d * dt / cfg.align_tau_s
        if wheel_speed >= cfg.min_speed_mps:
            self.odo[0] += wheel_speed * math.cos(self.psi) * dt
            self.odo[1] += wheel_speed * math.sin(self.psi) * dt

    def check(self, t: float, fix_xy: tuple[float, float], pose_xy: tuple[float, float]
              ) -> tuple[bool, np.ndarray | None]:
        """One fix: ``(trusted, correction)``. ``correction`` (2,) is where to move the filter's position when a
        suspicion starts (the odometry's position from the baseline's start), else None."""
        cfg = self.config
        if not cfg.enabled:
            return True, None
        hist = self.history
        if hist and t - hist[-1].t > 2.0 * cfg.baseline_s:
            hist.clear()  # after an outage the baseline starts again
        recent = bool(hist) and t - hist[-1].t <= cfg.fused_gap_s  # the filter was following the fixes
        entry = _Entry(t, fix_xy, (self.odo[0], self.odo[1]), pose_xy)
        while len(hist) > 1 and t - hist[1].t >= cfg.baseline_s:
            hist.popleft()
        correction = None
        if self.suspect:
            # judged against the odometry's track from the last trusted position, not against a fresh baseline of
            # the suspect fixes (a walk seen over a few seconds looks like driving)
            t_a, odo_a, pos_a = self._anchor  # type: ignore[misc]
            o = (self.odo[0] - odo_a[0], self.odo[1] - odo_a[1])
            pred = (pos_a[0] + o[0], pos_a[1] + o[1])
            disc = math.hypot(fix_xy[0] - pred[0], fix_xy[1] - pred[1])
            self.last_discrepancy_m = disc
            if disc <= cfg.tol_m + cfg.tol_per_m * math.hypot(*o):
                self._agree += 1
                if self._agree >= cfg.clear_fixes:
                    self.suspect = False
                    self.reason = ""
                    hist.clear()
            else:
                self._agree = 0
            if self.suspect:
                self.fixes_refused += 1
                return False, None
            hist.append(entry)
            return True, None
        if hist and t - hist[0].t >= cfg.min_baseline_s:
            old = hist[0]
            g = (fix_xy[0] - old.fix[0], fix_xy[1] - old.fix[1])
            o = (self.odo[0] - old.odo[0], self.odo[1] - old.odo[1])
            dist = math.hypot(*o)
            disc = math.hypot(g[0] - o[0], g[1] - o[1])
            self.last_discrepancy_m = disc
            tol = cfg.tol_m + cfg.tol_per_m * dist
            if disc > tol:
                self.suspect = True
                self.episodes += 1
                self._agree = 0
                self.fixes_refused += 1
                self.reason = (f"GNSS suspect: the fixes moved {disc:.1f} m away from the wheels' and gyro's track "
                               f"over {t - old.t:.1f} s (allowed {tol:.1f} m); not fused while they disagree")
                if self.first_reason is None:
                    self.first_reason = self.reason
                if recent:
                    correction = np.array([old.pose[0] + o[0], old.pose[1] + o[1]])
                    self._anchor = (old.t, old.odo, old.pose)
                else:
                    self._anchor = (t, (self.odo[0], self.odo[1]), pose_xy)
                return False, correction
        hist.append(entry)
        return True, None

    def summary(self) -> dict:
        return {"episodes": self.episodes, "fixes_refused": self.fixes_refused, "suspect_now": self.suspect,
                "first_reason": self.first_reason, "last_discrepancy_m": self.last_discrepancy_m}
