"""Filter stage: the EKF with its calibration states, the raw cues, standstill, GNSS gate and fusion.

Per 50 Hz step, in this order:

1. predict;
2. the model's z (from :mod:`prml2_edge.runtime.estimator`) as a pseudo-measurement, when there is one;
3. with ``calibration`` on, the raw cues as measurements of their own, through the calibration
   states (:class:`prml2_edge.schema.CalState`): the CAN yaw rate (``omega_z + offset``) and the
   non-driven axle's wheel speed (``(1 + scale) v_x``, only above ``cue_min_speed_mps``: ABS sensors read 0
   near standstill): the rear axle, or the front one of a rear-driven car (``driven_axle``), whose driven wheels
   spin up with the traction on a slippery road. The model's learned variance against the cues' fixed noise decides the
   weighting step by step; the model's omega_z carries a bias state of its own, so over seconds the
   heading follows the calibrated yaw rate and within them the model;
4. standstill (every valid wheel speed 0 and the speedometer 0 for ``standstill_hold_s``): a
   zero-velocity / zero-rotation update, which with the yaw-rate cue reveals its offset without GNSS;
5. the slide monitor (:mod:`prml2_edge.runtime.slide`): while the lateral acceleration and v_x times the yaw rate
   disagree (a skid, a spin), the position's uncertainty grows by what the odometry missed;
6. GNSS fixes: position, and heading while moving, behind an innovation gate; a fused heading is also evidence
   on the CAN yaw rate's gain (:mod:`prml2_edge.runtime.yaw_gain`), which divides the yaw-rate cue.

On a low-friction road (``config.mu`` <= 0.5) the model's variance is multiplied by ``low_mu_model_var_scale``, and
the position's along-track uncertainty grows with the braking asked of the road (``low_mu_slip_gain``; with any
traction when the cue axle also drives).

The filter starts from a given pose, or from a GNSS fix, never before a wheel speed or the
speedometer is valid (the velocity is initialised from the wheels, not from nothing). A GNSS start
is provisional until two consecutive fixes agree with each other and with the wheel speeds; a fix
that disagrees restarts the filter from it, so a single stray or spoofed first frame is replaced at
the next fix.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from prml2_edge import schema
from prml2_edge.ekf.numpy_ekf import CalibrationNoise, CalibrationStd, Ekf, StepStatus
from prml2_edge.runtime.axle_speed import front_speed, rear_speed
from prml2_edge.runtime.cue_offset import CueOffset, CueOffsetConfig
from prml2_edge.runtime.estimator import Estimate
from prml2_edge.runtime.filter_gnss import GnssFusion
from prml2_edge.runtime.gnss_check import FixNoise, GnssCheck, GnssCheckConfig
from prml2_edge.runtime.initial_pose import InitialPose, initial_state
from prml2_edge.runtime.rows import GnssFix
from prml2_edge.runtime.slide import SlideMonitor
from prml2_edge.runtime.yaw_gain import YawGainEstimator
from prml2_edge.runtime.yaw_resolution import YawResolution
from prml2_edge.schema import CalState, EkfState

_SIG = schema.SIGNAL_BY_NAME
_YAW_RATE = _SIG["yaw_rate_radps"].index
_SPEEDO = _SIG["speedometer_mps"].index
_LAT_ACCEL = _SIG["lat_accel_mps2"].index
_WHEELS = np.array(schema.WHEEL_SPEED_INDICES)
_WHEEL_LIST = [int(i) for i in _WHEELS]
_YAW, _OMEGA, _VX = EkfState.YAW.start, EkfState.OMEGA_Z.start, EkfState.VEL.start
_AX = EkfState.ACC.start
_B_YAW = CalState.YAW_RATE_OFFSET.start


def yaw_cue_var(config, resolution_radps: float) -> float:
    """The CAN yaw-rate cue's variance [rad^2/s^2]: white noise plus ``yaw_cue_quant_gain`` times the signal's
    resolution ``resolution_radps``; ``config`` a :class:`~prml2_edge.runtime.localizer_config.LocalizerConfig`."""
    return config.yaw_cue_std_radps ** 2 + (config.yaw_cue_quant_gain * resolution_radps) ** 2


@dataclass(frozen=True)
class FilterStep:
    """What the filter did at one step."""

    ekf_status: StepStatus | None  # None: not started
    model_used: bool
    gnss_fused: bool
    cues_used: bool = False
    standstill: bool = False


class PoseFilter(GnssFusion):
    """The EKF and everything fused into it; ``config`` is a
    :class:`~prml2_edge.runtime.localizer_config.LocalizerConfig`."""

    def __init__(self, config, process_noise: np.ndarray, initial_pose: InitialPose | None = None,
                 dt_s: float = schema.DT_S) -> None:
        self.config = config
        self.process_noise = np.asarray(process_noise, dtype=np.float64)
        self.initial_pose = initial_pose
        self.dt_s = float(dt_s)
        # a restored calibration (cal (3,), cov (3, 3)) that every start begins from; None: the prior
        self.calibration0: tuple[np.ndarray, np.ndarray] | None = None
        self.omega_var_inflation = 1.0  # on the model's omega_z variance when the raw cues are fused (localizer.py)
        self.omega_var_inflation_coarse = 1.0  # the same next to a coarse CAN yaw rate, once measured coarse
        # the CAN yaw rate's gain: evidence over drives (the calibration file), so not reset with the EKF
        self.yaw_gain = YawGainEstimator(math.radians(config.gnss_heading_std_deg))
        self._gain_on = self.calibrated and bool(config.yaw_gain_calibration)
        # on a low-friction road (config.mu <= schema.LOW_MU_THRESHOLD) the model's variance times this
        low_mu = float(getattr(config, "mu", 1.0)) <= schema.LOW_MU_THRESHOLD
        self._low_mu_scale = float(getattr(config, "low_mu_model_var_scale", 1.0)) if low_mu else 1.0
        # ... and the position's along-track sigma grows by this times the speed times |a_x| / (mu g) per second
        self._slip_k = float(getattr(config, "low_mu_slip_gain", 0.0)) / (config.mu * schema.G_MPS2) if low_mu else 0.0
        self._row_yaw: float | None = None  # this row's raw CAN yaw rate, for the gain
        self._row: tuple[np.ndarray, np.ndarray] | None = None  # this row's values and validity (its speed)
        # slides over the whole run (runtime/slide.py): kept across restarts, so the summary counts every one
        self.slide = SlideMonitor(getattr(config, "slide_accel_mps2", None), self.dt_s)
        # the wheel cue's speed (values, valid) -> m/s or None: the axle that does not drive (an AWD car keeps the
        # rear: all four slip); LocalizerConfig checks driven_axle
        axle = getattr(config, "driven_axle", "front")
        self._axle_speed = rear_speed
        self._cue_axle_drives = axle == "all"
        if axle == "rear":
            self._axle_speed = functools.partial(front_speed, steering_ratio=float(config.steering_ratio))
        # the gyro's offset from the other cues (runtime/cue_offset.py): over drives' minutes, so kept across restarts
        cue_cfg = CueOffsetConfig.from_localizer(config)
        self.cue_offset = CueOffset(config.cal_yaw_offset_prior_std_radps, config.steering_ratio, cue_cfg, self.dt_s) \
            if self.calibrated and getattr(config, "cue_offset", False) else None
        self.reset()

    def reset(self) -> None:
        self.ekf: Ekf | None = None
        self._last_abs_t: float | None = None  # last GNSS fix or the start
        self._last_fix_t: float | None = None
        self._gnss_rejects_in_row = 0
        self._prev_fix: tuple[GnssFix, float] | None = None  # the last fix and the wheel speed then
        self._confirmed = True  # a GNSS start is provisional until two consecutive fixes agree
        self._heading_provisional = False  # the start's heading came from no course while driving
        self._last_seen_fix: GnssFix | None = None  # the last fix offered to the filter (_follows_last_fix)
        self._still_since: float | None = None
        self._odo_anchor: tuple[float, np.ndarray] | None = None  # (t, fix position) the wheel distance is from
        self._odo = np.zeros(2)  # wheel displacement since the anchor, world frame, along the filter's heading
        self.n_scale_updates = 0
        # the CAN yaw rate's resolution and whether it is coarse, measured from its steps (runtime/yaw_resolution.py)
        self.resolution = YawResolution.from_config(self.config)
        self._yaw_cue_var = self._yaw_var()
        self.n_gnss_rejected = 0  # fixes refused by the innovation gate
        self.n_gnss_suspect = 0  # fixes not fused because the odometry contradicts the fix stream
        self.n_gnss_init_rejected = 0  # first fixes that the next fix or the wheels contradicted
        self.n_standstill_updates = 0
        self.gnss_check = GnssCheck(GnssCheckConfig(enabled=bool(getattr(self.config, "gnss_consistency", True))))
        self.slide.reset()
        self.fix_noise = FixNoise()

    @property
    def gnss_std_m(self) -> float:
        """The GNSS noise per axis the gate, the fusion and the checks use [m]: the configured one, or the fix
        stream's own when that is larger (a consumer receiver behind a configuration for a better one)."""
        est = self.fix_noise.std_m
        if est is None:  # the first fixes: not known yet
            return FixNoise.UNKNOWN_FACTOR * self.config.gnss_pos_std_m
        return max(self.config.gnss_pos_std_m, est)

    def _yaw_rate_std(self) -> tuple[float, bool]:
        """``(std, converged)``: how well the filter knows the CAN yaw-rate offset [rad/s]. Without the calibration
        states nothing learns it: the prior stands, and the checks arm anyway (they would never arm)."""
        cfg = self.config
        if not self.calibrated or self.ekf is None:
            return cfg.cal_yaw_offset_prior_std_radps, True
        std = math.sqrt(max(float(self.ekf.cal_cov[0, 0]), 0.0))
        return std, std <= math.radians(self.gnss_check.config.arm_rate_std_dps)

    @property
    def calibrated(self) -> bool:
        return bool(self.config.calibration)

    def start(self, x0: np.ndarray, P0: np.ndarray, t_s: float) -> None:
        """Start (or restart) the EKF at ``x0`` (8,), ``P0`` (8, 8) at ``t_s`` [s], with the calibration prior."""
        cfg = self.config
        self.ekf = Ekf(x0, P0, Q=self.process_noise, dt_s=self.dt_s, calibration=self.calibrated,
                       cal_noise=CalibrationNoise(cfg.cal_yaw_offset_psd, cfg.cal_wheel_scale_psd,
                                                  cfg.cal_model_bias_std_radps, cfg.cal_model_bias_tau_s,
                                                  cfg.model_offset_share)
                       if self.calibrated else None,
                       cal_std=CalibrationStd(cfg.cal_yaw_offset_prior_std_radps, cfg.cal_wheel_scale_prior_std,
                                              cfg.cal_model_bias_std_radps) if self.calibrated else None)
        if self.calibrated and self.calibration0 is not None:
            self.ekf.set_calibration(*self.calibration0)
        if self.cue_offset is not None:
            self.cue_offset.restart_export()  # the new EKF has heard nothing of it yet: all it knows goes over now
            self._export_cues()
        self._last_abs_t = t_s
        self.gnss_check.reset()

    # ---- one step -----------------------------------------------------------------------------------

    def step(self, values: np.ndarray, valid: np.ndarray, t_s: float, est: Estimate,
             fix: GnssFix | None, substituted: np.ndarray | None = None,
             substitute_std: np.ndarray | None = None) -> FilterStep:
        if self.ekf is None or (fix is not None and not self._confirmed and not self._plausible(fix, values, valid)):
            return self._try_start(values, valid, t_s, fix)
        still = self.calibrated and self._still(values, valid, t_s)
        # parked, the zero-velocity update replaces the model: its omega_z at rest is not its error while driving,
        # and the yaw-rate offset it shares with the CAN yaw rate would learn the wrong value
        skip_model = still and self.config.standstill_skips_model
        z_var = est.z_var
        infl = self.omega_var_inflation
        coarse = self.resolution.coarse
        if coarse:
            infl = self.omega_var_inflation_coarse
        if self.calibrated and z_var is not None and infl != 1.0:
            z_var = z_var.copy()
            z_var[schema.Z.OMEGA_Z] *= infl
        if z_var is not None and self._low_mu_scale != 1.0:
            z_var = z_var * self._low_mu_scale
        z, z_var = (None, None) if skip_model else (est.z, z_var)
        if coarse and self.calibrated and z is not None and self.config.coarse_model_clamp_sigma is not None \
                and valid[_YAW_RATE] and (substituted is None or not substituted[_YAW_RATE]):
            z = self._held_to_reading(z, float(values[_YAW_RATE]) * self.yaw_gain_factor)
        cues = standstill = False
        if self._gain_on:
            self._gain_row(values, valid, substituted)
        if self.calibrated:
            # the model's z and the raw cues in one update (Ekf.step_with_cues)
            ekf_status, cues = self.ekf.step_with_cues(z, z_var, *self._cue_values(values, valid, substituted,
                                                                                  substitute_std))
            standstill = still and self._zero_velocity()
            self._odometry(values, valid)
            if self.cue_offset is not None and (substituted is None or not substituted[_YAW_RATE]):
                self._cue_offset_row(values, valid)
        else:
            ekf_status = self.ekf.step(z, z_var)
        model_used = ekf_status is StepStatus.SUCCESS
        self._watch_slide(values, valid)
        if self._slip_k:
            self._widen_along_track()
        pos = self.ekf.x[EkfState.POS]
        self.gnss_check.step(float(pos[0]), float(pos[1]))
        gnss_fused = fix is not None and self._fuse(fix, t_s)
        pos = self.ekf.x[EkfState.POS]
        self.gnss_check.settle(float(pos[0]), float(pos[1]))
        if gnss_fused and self.calibrated:
            self._scale_from_gnss(fix, t_s)
        return FilterStep(ekf_status, model_used, gnss_fused, cues, standstill)

    def _watch_slide(self, values: np.ndarray, valid: np.ndarray) -> None:
        """The slide monitor on this row (:mod:`~prml2_edge.runtime.slide`): while the car slides, the position's
        uncertainty grows by what the odometry missed, and a new slide starts the GNSS check's baseline again."""
        x = self.ekf.x  # type: ignore[union-attr]
        omega = None
        if valid[_YAW_RATE]:
            omega = float(values[_YAW_RATE]) * self.yaw_gain_factor
            if self.calibrated:
                omega -= float(x[CalState.YAW_RATE_OFFSET.start])
        grow = self.slide.step(float(values[_LAT_ACCEL]) if valid[_LAT_ACCEL] else None, float(x[_VX]), omega)
        if self.slide.started:
            self.gnss_check.restart()
        if grow > 0.0:
            p = self.ekf.P  # type: ignore[union-attr]
            for i in (0, 1):  # the diagonal only: P stays positive semi-definite
                p[i, i] = (math.sqrt(max(float(p[i, i]), 0.0)) + grow) ** 2

    def _widen_along_track(self) -> None:
        """On a low-friction road the cue axle's tyres slip with the force asked of them, and the model and the
        wheels read the same too-high (or too-low) speed: their fusion cannot show it. The position's standard
        deviation along the track grows by ``low_mu_slip_gain * |v_x| * a / (mu g) * dt`` per step (a slip ratio
        that grows with the share of the friction used), the way a correlated speed error moves the position;
        ``a`` is the braking deceleration, or ``|a_x|`` when the cue axle also drives (AWD)."""
        x = self.ekf.x  # type: ignore[union-attr]
        ax = float(x[_AX])
        grow = self._slip_k * abs(float(x[_VX])) * (abs(ax) if self._cue_axle_drives else -ax) * self.dt_s
        if grow <= 0.0:
            return
        c, s = math.cos(float(x[_YAW])), math.sin(float(x[_YAW]))
        p = self.ekf.P  # type: ignore[union-attr]
        along = math.sqrt(max(c * c * p[0, 0] + 2.0 * c * s * p[0, 1] + s * s * p[1, 1], 0.0))
        add = (along + grow) ** 2 - along * along  # a rank-one term along the heading: P stays positive semi-definite
        p[0, 0] += add * c * c
        p[0, 1] += add * c * s
        p[1, 0] += add * c * s
        p[1, 1] += add * s * s

    @property
    def gain_learned(self) -> bool:
        """Whether this filter learns and applies the CAN yaw rate's gain (calibrated, and the option on)."""
        return self._gain_on

    @property
    def yaw_gain_factor(self) -> float:
        """What the CAN yaw rate is multiplied by before it is a cue: ``1 / (1 + gain)`` (1 with the gain off)."""
        return 1.0 / (1.0 + self.yaw_gain.gain) if self._gain_on else 1.0

    def _gain_row(self, values: np.ndarray, valid: np.ndarray, substituted: np.ndarray | None) -> None:
        """This row's raw yaw rate into the gain estimator (a missing or substituted one ends its chunk)."""
        ok = valid[_YAW_RATE] and (substituted is None or not substituted[_YAW_RATE])
        self._row_yaw = float(values[_YAW_RATE]) if ok else None
        self._row = (values, valid)
        self.yaw_gain.yaw_rate(self._row_yaw, self.dt_s)

    def _gain_heading(self, t_s: float, psi: float) -> None:
        """A fused GNSS heading as gain evidence, when the gyro is fine enough to learn from (quantisation without
        dither leaves an error that follows the turn) and the row had a yaw rate and a cue-axle speed."""
        fine = self.resolution.measured and self.yaw_resolution_radps < self.config.yaw_gain_max_resolution_radps
        speed = self._axle_speed(*self._row) if fine and self._row_yaw is not None and self._row is not None else None
        if speed is not None and speed >= self.config.gnss_heading_min_speed_mps:
            self.yaw_gain.heading(t_s, psi, self._row_yaw, speed)

    def _held_to_reading(self, z: np.ndarray, yaw_rate: float) -> np.ndarray:
        """``z`` with its omega_z inside the interval a coarse CAN reading ``yaw_rate`` allows: the reading less the
        offset estimate, +- half the measured resolution + ``coarse_model_clamp_sigma`` white-noise sigmas."""
        cfg = self.config
        half = 0.5 * self.yaw_resolution_radps + cfg.coarse_model_clamp_sigma * cfg.yaw_cue_std_radps
        centre = yaw_rate - float(self.ekf.x[CalState.YAW_RATE_OFFSET.start])
        w = float(z[schema.Z.OMEGA_Z])
        held = min(max(w, centre - half), centre + half)
        if held == w:
            return z
        z = z.copy()
        z[schema.Z.OMEGA_Z] = held
        return z

    def _try_start(self, values: np.ndarray, valid: np.ndarray, t_s: float, fix: GnssFix | None) -> FilterStep:
        pose = self.initial_pose if self.ekf is None else None
        if pose is None and fix is not None and self._wheels_known(valid):
            self.fix_noise.add(fix.t_s, fix.x_m, fix.y_m)
            pose = InitialPose.from_gnss(fix, self.gnss_std_m, self.config.gnss_heading_std_deg)
            # parked, a receiver's course is the last one it saw or noise: taken for now, replaced by the first
            # course while driving (_reseat_heading)
            moving = self._wheel_speed(values, valid) >= self.config.gnss_heading_min_speed_mps
            self._heading_provisional = not (moving and fix.heading_deg is not None)
            self._confirmed = not self.config.gnss_init_check
            self._prev_fix = (fix, self._wheel_speed(values, valid))
        if pose is None:
            return FilterStep(None, False, False)
        x0, p0 = initial_state(pose, values, valid)
        self.start(x0, p0, t_s)
        gnss = pose.source == "gnss"
        if gnss:
            self._last_fix_t = t_s
        return FilterStep(None, False, gnss)

    @staticmethod
    def _wheels_known(valid: np.ndarray) -> bool:
        return bool(np.any(valid[_WHEELS]) or valid[_SPEEDO])

    @staticmethod
    def _wheel_speed(values: np.ndarray, valid: np.ndarray) -> float:
        wheels = [i for i in _WHEELS if valid[i]]
        return float(np.mean(values[wheels])) if wheels else float(values[_SPEEDO]) if valid[_SPEEDO] else 0.0

    def _plausible(self, fix: GnssFix, values: np.ndarray, valid: np.ndarray) -> bool:
        """While the GNSS start is provisional: does ``fix`` agree with the previous fix and the wheel speeds?

        Agreeing confirms the start; disagreeing (counted) restarts the filter from ``fix``, so one stray or
        spoofed first frame is replaced at the next fix instead of winning the gate after 20 refusals.
        """
        cfg = self.config
        speed = self._wheel_speed(values, valid)
        prev, self._prev_fix = self._prev_fix, (fix, speed)
        if prev is None:
            return True
        last, last_speed = prev
        dt = fix.t_s - last.t_s
        if not 0.0 < dt <= cfg.gnss_init_max_gap_s:
            return True  # nothing to compare with: keep the provisional start, check the next pair
        self.fix_noise.add(fix.t_s, fix.x_m, fix.y_m)
        if self._follows(last, fix, 0.5 * (speed + last_speed)):
            self._confirmed = True
            return True
        self.n_gnss_init_rejected += 1
        self.ekf = None
        return False

    def _yaw_var(self) -> float:
        return yaw_cue_var(self.config, self.yaw_resolution_radps)

    @property
    def yaw_resolution_radps(self) -> float:
        """The CAN yaw rate's resolution as measured so far [rad/s] (the configured one before any step)."""
        return self.resolution.radps

    def _track_resolution(self, yaw: float) -> None:
        if self.resolution.reading(yaw):
            self._yaw_cue_var = self._yaw_var()

    def correct_yaw_cue(self, offset: float, std: float, t_from: float, t_now: float) -> None:
        """The CAN yaw rate read ``offset`` [rad/s] too much from ``t_from`` on (an offset jump the plausibility
        stage measured at its step, ``std`` its uncertainty): the heading and yaw rate integrated from it since
        are taken back, times :attr:`LocalizerConfig.offset_retro_gain` (the cue's share of the yaw rate)."""
        if self.ekf is None or not self.calibrated:
            return
        g = self.config.offset_retro_gain
        dt = max(t_now - t_from, 0.0)
        x = self.ekf.x.copy()
        x[EkfState.YAW] -= g * offset * dt
        x[EkfState.OMEGA_Z] -= g * offset
        self.ekf.x = x
        p = self.ekf.P.copy()
        p[EkfState.YAW, EkfState.YAW] += (std * dt) ** 2
        self.ekf.P = p

    def _cue_values(self, values: np.ndarray, valid: np.ndarray, substituted: np.ndarray | None = None,
                    substitute_std: np.ndarray | None = None) -> tuple[float | None, float, float | None, float]:
        """The raw cues of this row for :meth:`Ekf.step_with_cues`: ``(yaw rate or None, its variance, the cue
        axle's wheel speed or None, its variance)``; tracks the yaw rate's resolution on the way."""
        cfg = self.config
        yaw = float(values[_YAW_RATE]) if valid[_YAW_RATE] else None
        yaw_var = self._yaw_cue_var
        if yaw is not None:
            self._track_resolution(yaw)
            if self._gain_on:
                yaw *= self.yaw_gain_factor
        elif cfg.substitute_yaw_cue and substituted is not None and substituted[_YAW_RATE] \
                and substitute_std is not None and math.isfinite(substitute_std[_YAW_RATE]):
            # the plausibility stage's substitute (the gyro less an offset jump, or the others' rotation), with
            # its own uncertainty on top
            yaw = float(values[_YAW_RATE])
            yaw_var = yaw_var + float(substitute_std[_YAW_RATE]) ** 2
        wheel = None
        w = self._axle_speed(values, valid)
        if w is not None and w >= cfg.cue_min_speed_mps:
            wheel = w
        return yaw, yaw_var, wheel, cfg.wheel_cue_std_mps ** 2

    def _cue_offset_row(self, values: np.ndarray, valid: np.ndarray) -> None:
        """This row to the cues' offset estimate; what it learned, when it closes a block, to the offset state."""
        if self.cue_offset.row(values, valid, self.yaw_gain_factor, self.yaw_resolution_radps):  # type: ignore
            self._export_cues()

    def _export_cues(self) -> None:
        """What the cue estimator learned of the gyro's offset since its last export, to the EKF's offset state."""
        cues = self.cue_offset
        if cues.handed_over:  # type: ignore[union-attr]
            # a coarse gyro's grid took over from its blocks (runtime/cue_offset.py): what they told the offset state
            # is forgotten (its variance grows by the prior's) and the grid's whole estimate goes over instead
            self.ekf.P[_B_YAW, _B_YAW] += self.config.cal_yaw_offset_prior_std_radps ** 2  # type: ignore[union-attr]
            cues.restart_export()  # type: ignore[union-attr]
        measured = cues.export()  # type: ignore[union-attr]
        if measured is not None:
            self.ekf.update_yaw_offset(*measured)  # type: ignore[union-attr]

    def _still(self, values: np.ndarray, valid: np.ndarray, t_s: float) -> bool:
        """Standstill: every valid wheel speed 0 (and the speedometer) for ``standstill_hold_s``."""
        seen = [float(values[i]) for i in _WHEEL_LIST if valid[i]]  # (Python floats: NumPy's call cost on 4 values)
        still = bool(seen) and all(v <= 0.0 for v in seen) and (not valid[_SPEEDO] or values[_SPEEDO] <= 0.0)
        if not still:
            self._still_since = None
            return False
        if self._still_since is None:
            self._still_since = t_s
        return t_s - self._still_since + 1e-9 >= self.config.standstill_hold_s

    def _zero_velocity(self) -> bool:
        cfg = self.config
        status = self.ekf.update_standstill(cfg.standstill_std_mps ** 2,  # type: ignore[union-attr]
                                            cfg.standstill_yaw_std_radps ** 2)
        self.n_standstill_updates += int(status is StepStatus.SUCCESS)
        return status is StepStatus.SUCCESS

    # ---- GNSS: runtime/filter_gnss.py (GnssFusion) ---------------------------------------------------

    # ---- reporting ----------------------------------------------------------------------------------

    def gnss_recent(self, t_s: float) -> bool:
        return self._last_fix_t is not None and t_s - self._last_fix_t <= self.config.gnss_timeout_s + 1e-9

    def outage_s(self, t_s: float) -> float:
        return t_s - self._last_abs_t if self._last_abs_t is not None else math.nan

    def had_fix(self) -> bool:
        return self._last_fix_t is not None

    def calibration(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The current calibration estimate ``(cal (3,), cov (3, 3))``, or None (off, or not started)."""
        if self.ekf is None or not self.calibrated:
            return None
        return self.ekf.cal, self.ekf.cal_cov

    def summary(self) -> dict:
        out = {"gnss_rejected": self.n_gnss_rejected, "gnss_init_rejected": self.n_gnss_init_rejected,
               "gnss_suspect": self.gnss_check.summary(),
               "gnss_std_m": {"configured": self.config.gnss_pos_std_m, "measured": self.fix_noise.std_m,
                              "used": self.gnss_std_m if self.fix_noise.std_m is not None else None},
               "ekf_resets": self.ekf.n_resets if self.ekf is not None else 0, "slides": self.slide.episodes}
        cal = self.calibration()
        if cal is not None:
            est, cov = cal
            std = np.sqrt(np.maximum(np.diag(cov), 0.0))
            out["calibration"] = {
                "yaw_rate_offset_dps": math.degrees(est[0]), "yaw_rate_offset_std_dps": math.degrees(std[0]),
                "wheel_scale_pct": 100.0 * est[1], "wheel_scale_std_pct": 100.0 * std[1],
                "model_omega_bias_dps": math.degrees(est[2]), "standstill_updates": self.n_standstill_updates,
                "yaw_rate_resolution_dps": math.degrees(self.yaw_resolution_radps)}
            if self._gain_on:
                out["calibration"].update(self.yaw_gain.summary())
            if self.cue_offset is not None:
                out["calibration"]["cue_offset"] = self.cue_offset.summary()
        return out
