"""The filter's GNSS side: fusing a fix (position, and its course over ground while moving) behind the innovation
gate and the odometry check, re-seating a parked start's heading, and the wheel scale from GNSS distance.

A mixin of :class:`prml2_edge.runtime.filter.PoseFilter`: it reads and updates the filter's EKF, configuration, GNSS
check and counters.
"""

from __future__ import annotations

import math

import numpy as np

from prml2_edge.ekf.numpy_ekf import StepStatus, course_measurement, wrap_angle
from prml2_edge.runtime.rows import GnssFix
from prml2_edge.schema import EkfState

_YAW, _OMEGA = EkfState.YAW.start, EkfState.OMEGA_Z.start
_AX = EkfState.ACC.start


class GnssFusion:
    """GNSS fusion and the wheel scale from GNSS, for :class:`~prml2_edge.runtime.filter.PoseFilter`."""

    def _odometry(self, values: np.ndarray, valid: np.ndarray) -> None:
        """Integrate the cue axle's wheel speed along the filter's heading; a gap, slow driving or a slipping cue
        axle (braking harder than ``scale_max_accel_mps2``, or accelerating so where the cue axle drives) restarts
        it: the scale is the tyres', and a brake's slip (the cue reads ~0.6 % slow while braking) is not."""
        if self._odo_anchor is None:
            return
        w = self._axle_speed(values, valid)
        cfg = self.config
        ax = float(self.ekf.x[_AX])  # type: ignore[union-attr]
        slipping = ax < -cfg.scale_max_accel_mps2 or (self._cue_axle_drives and ax > cfg.scale_max_accel_mps2)
        if w is None or not w >= cfg.scale_min_speed_mps or slipping:
            self._odo_anchor = None
            return
        psi = float(self.ekf.x[_YAW])  # type: ignore[union-attr]
        step = w * self.dt_s
        odo = self._odo
        odo[0] += step * math.cos(psi)
        odo[1] += step * math.sin(psi)

    def _scale_from_gnss(self, fix: GnssFix, t_s: float) -> None:
        """Wheel scale = wheel distance / GNSS distance - 1 over baselines of ``scale_baseline_s``, fed to the
        scale state with the GNSS noise of the two end fixes (``2 sigma^2 / distance^2``). The distance in the
        variance is the wheels', not the fixes': weighted by the noisy one, a baseline whose noise lengthened it
        (and so read the scale low) counted more, -0.16 % of bias at 75 m baselines and -0.37 % at 50 m."""
        cfg = self.config
        pos = np.array([fix.x_m, fix.y_m])
        anchor = self._odo_anchor
        if anchor is not None and t_s - anchor[0] >= cfg.scale_baseline_s:
            d = pos - anchor[1]
            dist2 = float(d @ d)
            if dist2 > 1.0:
                scale = float(self._odo @ d) / dist2 - 1.0
                var = 2.0 * self.gnss_std_m ** 2 / max(float(self._odo @ self._odo), 1.0) + cfg.scale_meas_floor ** 2
                status = self.ekf.update_wheel_scale(scale, var)  # type: ignore[union-attr]
                self.n_scale_updates += int(status is StepStatus.SUCCESS)
            anchor = None
        if anchor is None:
            self._odo_anchor = (t_s, pos)
            self._odo = np.zeros(2)

    def _follows(self, last: GnssFix, fix: GnssFix, speed: float) -> bool:
        """Whether ``fix`` lies where ``last`` and the car's mean ``speed`` [m/s] since put it, within the GNSS noise
        of both and ``gnss_init_speed_tol_mps`` (the start-up check's rule, and the heading re-seat's)."""
        cfg = self.config
        dt = fix.t_s - last.t_s
        moved = math.hypot(fix.x_m - last.x_m, fix.y_m - last.y_m)
        slack = cfg.gnss_gate_sigma * math.sqrt(2.0) * self.gnss_std_m + cfg.gnss_init_speed_tol_mps * dt
        return abs(moved - speed * dt) <= slack

    def _follows_last_fix(self, fix: GnssFix, speed: float) -> bool:
        """Whether ``fix`` lies where the fix before it (within ``gnss_init_max_gap_s``) and the car's speed put it:
        a stray or random frame does not. Remembers ``fix`` for the next call."""
        last, self._last_seen_fix = self._last_seen_fix, fix
        if last is None or not 0.0 < fix.t_s - last.t_s <= self.config.gnss_init_max_gap_s:
            return False
        return self._follows(last, fix, speed)

    def _reseat_heading(self, angle: float, var: float, course: bool) -> None:
        """The first course while driving (from a fix where the fix before it and the speed put it) after a start
        whose heading was a parked receiver's (stale, or noise) or none: the yaw is set from it (less the filter's
        sideslip) with the fix's variance, uncorrelated with the rest, instead of being gated against a heading
        nobody measured."""
        x, p = self.ekf.x, self.ekf.P  # type: ignore[union-attr]
        beta = course_measurement(x)[0] - float(x[_YAW]) if course else 0.0
        x[_YAW] = float(x[_YAW]) + float(wrap_angle(angle - beta - float(x[_YAW])))
        p[_YAW, :] = 0.0
        p[:, _YAW] = 0.0
        p[_YAW, _YAW] = var
        self._heading_provisional = False
        self.gnss_check.reset()  # its odometry since the start ran along the stale heading

    def _angle_plausible(self, angle: float, var: float, course: bool) -> bool:
        """A fix's heading (or course over ground) within the innovation gate of the filter's prediction of it."""
        x, p = self.ekf.x, self.ekf.P  # type: ignore[union-attr]
        if course:
            pred, h = course_measurement(x)
            pred_var = float(h @ p @ h)
        else:
            pred, pred_var = float(x[_YAW]), float(p[_YAW, _YAW])
        d = float(wrap_angle(angle - pred))
        return d * d <= self.config.gnss_gate_chi2 * (pred_var + var)

    def _fuse(self, fix: GnssFix, t_s: float) -> bool:
        cfg = self.config
        self.fix_noise.add(fix.t_s, fix.x_m, fix.y_m)
        self.gnss_check.fix_std_m = std_m = self.gnss_std_m
        x = self.ekf.x  # type: ignore[union-attr]
        # Move the fix from its frame time to this row's time along the current velocity (<= one period).
        lag_s = min(max(t_s - fix.t_s, 0.0), self.dt_s)
        c, s = math.cos(x[_YAW]), math.sin(x[_YAW])
        vx, vy = x[EkfState.VEL]
        pos = np.array([fix.x_m + (c * vx - s * vy) * lag_s, fix.y_m + (s * vx + c * vy) * lag_s])
        psi = fix.psi_rad
        yaw_var = None
        course = cfg.gnss_course_sideslip
        if psi is not None and math.hypot(vx, vy) >= cfg.gnss_heading_min_speed_mps:
            psi += x[_OMEGA] * lag_s
            yaw_var = math.radians(cfg.gnss_heading_std_deg) ** 2
        else:
            psi = None
        follows = self._follows_last_fix(fix, math.hypot(vx, vy))
        if psi is not None and yaw_var is not None and self._heading_provisional and follows:
            self._reseat_heading(psi, yaw_var, course)  # before the checks: they would judge it by a stale heading
            self.gnss_check.fix_std_m = std_m
        m2 = self._mahalanobis(pos)
        ekf = self.ekf
        rate_std, converged = self._yaw_rate_std()
        trusted, correction = self.gnss_check.check(t_s, (float(pos[0]), float(pos[1])),
                                                    (float(x[EkfState.POS][0]), float(x[EkfState.POS][1])),
                                                    m2 <= cfg.gnss_gate_chi2, float(ekf.pose_std[1]), rate_std,
                                                    converged)
        if correction is not None:
            # what was fused since the baseline's start was the spoofer's: back to the odometry's position
            ekf.x[EkfState.POS] = correction  # type: ignore[union-attr]
            ekf.P[EkfState.POS, EkfState.POS] += np.eye(2) * 2.0  # type: ignore[union-attr]  (the odometry's 8 s)
        if not trusted:
            self.n_gnss_suspect += 1
            return False
        if not self._gate(pos, m2):
            return False
        if psi is not None and yaw_var is not None and not self._angle_plausible(psi, yaw_var, course):
            psi = yaw_var = None  # position fine, heading implausible: fuse the position only
        status = self.ekf.fuse_pose(pos, std_m ** 2, psi, yaw_var, course)  # type: ignore[union-attr]
        if status is StepStatus.SUCCESS:
            if psi is not None and self._gain_on:
                self._gain_heading(t_s, float(psi))
            self._last_fix_t = t_s
            self._last_abs_t = t_s
            return True
        return False

    def _mahalanobis(self, pos: np.ndarray) -> float:
        """Squared Mahalanobis distance of a GNSS position (2,) [m] from the prediction."""
        p = self.ekf.P  # type: ignore[union-attr]
        d = pos - self.ekf.x[EkfState.POS]  # type: ignore[union-attr]
        s = p[EkfState.POS, EkfState.POS] + np.eye(2) * self.gnss_std_m ** 2
        with np.errstate(all="ignore"):
            try:
                return float(d @ np.linalg.solve(s, d))
            except np.linalg.LinAlgError:
                return math.inf

    def _gate(self, pos: np.ndarray, m2: float) -> bool:
        """Innovation gate of a GNSS position (2,) [m] at squared distance ``m2``; False (and counted) when it
        is refused. Fixes the odometry trusts (:mod:`~prml2_edge.runtime.gnss_check`) that the gate refused
        :attr:`gnss_gate_max_rejects` times in a row are fused anyway: then it is the filter that is off."""
        cfg = self.config
        if math.isfinite(m2) and m2 <= cfg.gnss_gate_chi2:
            self._gnss_rejects_in_row = 0
            return True
        self._gnss_rejects_in_row += 1
        if self._gnss_rejects_in_row > cfg.gnss_gate_max_rejects and math.isfinite(m2):
            self._gnss_rejects_in_row = 0
            return True
        self.n_gnss_rejected += 1
        return False
