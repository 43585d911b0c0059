"""The streaming localiser's tunables (:class:`LocalizerConfig`), apart from the loop that uses them
(:mod:`prml2_edge.runtime.localizer`): each field says what it does and, where it was chosen, on what."""

from __future__ import annotations

import math
from dataclasses import dataclass

from prml2_edge import schema
from prml2_edge.config import DEFAULT_STRIDE, DRIVEN_AXLES
from prml2_edge.ekf.numpy_ekf import CalibrationNoise, CalibrationStd
from prml2_edge.runtime.cue_offset import AY_RESTORE_FLOOR_MPS2, STEER_RESTORE_FLOOR_DEG

__all__ = ["LocalizerConfig"]


@dataclass(frozen=True)
class LocalizerConfig:
    """Tunables of :class:`~prml2_edge.runtime.localizer.StreamingLocalizer` (SI units unless named otherwise)."""

    stride: int = DEFAULT_STRIDE  # a new window every `stride` 50 Hz steps (config.py says how it was chosen)
    async_inference: bool = False  # the model on a worker thread: no step waits for it (runtime/async_estimator.py)
    mu: float = 1.0  # road friction for the physics guard (<= 0.5: low-mu limits)
    # On such a low-mu road the model's whole variance times this: it was trained on dry roads only, so on snow the
    # raw cues carry more. Chosen on the snow_val split (1, 2, 4, 10, 30; docs/evaluation.md, issue 26).
    low_mu_model_var_scale: float = 10.0
    # ... and the wheel cue's tyres slip with the braking asked of them (a driving axle: with |a_x|), which the model
    # and the wheels read alike: the position's along-track sigma grows by this times |v_x| a / (mu g) per second
    # (0: off). Chosen on snow_val over 0, 0.01, 0.02, 0.04, 0.08: 2-sigma / 3-sigma coverage in 75-95 / >= 95 % in the
    # paper protocol, and the deployment protocol's closest to it (docs/evaluation.md, issue 26).
    low_mu_slip_gain: float = 0.01
    # Outputs of a window whose rows had an invalid signal in more than this fraction are not used:
    # a dropout of d rows costs the model until at most fraction * L of them are left in the window.
    max_invalid_fraction: float = 0.2
    gnss_pos_std_m: float = 0.5  # one-sigma GNSS position noise per axis
    gnss_heading_std_deg: float = 2.0  # one-sigma GNSS heading noise
    gnss_heading_min_speed_mps: float = 2.0  # below this speed a GNSS heading is not fused
    # A fix's angle is the course over ground (NMEA RMC, gpsd's track, the bus), fused as psi + atan2(v_y, v_x),
    # the sideslip taken out; False fuses it as the car's yaw (an INS; [gnss] course = false).
    gnss_course_sideslip: bool = True
    gnss_timeout_s: float = 0.5  # no fix for longer: GNSS outage (dead reckoning)
    fuse_gnss: bool = True
    # Innovation gate: a fix whose position is further from the prediction than this squared
    # Mahalanobis distance (2 dof; 16 ~ 4 sigma, p ~ 3e-4) is not fused, nor a heading beyond the same
    # bound (1 dof). CAN has no authentication and GNSS_FIX no checksum: one stray frame must not
    # teleport the pose. After this many fixes rejected in a row (2 s at 10 Hz) the next one is fused
    # anyway, so a filter that really is off is pulled back.
    gnss_gate_chi2: float = 16.0
    # GNSS against the wheels and the gyro (runtime/gnss_check.py): a fix stream the odometry contradicts is
    # suspect and not fused (a spoofer walking the position away passes the gate at every fix)
    gnss_consistency: bool = True
    gnss_gate_max_rejects: int = 20
    # The car sliding (runtime/slide.py): the 0.1 s mean of |a_y - v_x omega_z| above this [m/s^2] widens the
    # position by the lateral speed nobody measured and restarts the GNSS check's baseline (None: off).
    slide_accel_mps2: float | None = 3.0
    # GNSS start-up: the first fix becomes the pose only when the next one (within gnss_init_max_gap_s)
    # agrees with it and with the wheel speeds: |distance - mean wheel speed * dt| within
    # gnss_gate_sigma * sqrt(2) * gnss_pos_std_m + gnss_init_speed_tol_mps * dt.
    gnss_init_check: bool = True
    gnss_init_max_gap_s: float = 1.0
    gnss_init_speed_tol_mps: float = 2.0
    gnss_gate_sigma: float = 4.0
    # Self-calibration (runtime/filter.py): calibration states, raw cues, standstill updates.
    calibration: bool = True
    # CAN yaw-rate cue noise: white noise plus yaw_cue_quant_gain times the signal's resolution, measured
    # online (the 10th percentile of the steps between successive distinct readings; until measured,
    # yaw_cue_resolution_radps, or the smallest step seen if smaller: resolution_from_steps). Quantisation error
    # is not white: it stays while the yaw rate stays in one step, so a coarse sensor (ReV-StED: 1.28 deg/s) is
    # down-weighted far more than step / sqrt(12).
    # The gain was chosen on the validation splits with course-over-ground fixes (docs/evaluation.md): 3, where
    # the cue's variance matches its measured error on the coarse sensors (12 stated it 7-20 x too large).
    yaw_cue_std_radps: float = 0.1 * schema.DEG_TO_RAD
    yaw_cue_quant_gain: float = 3.0
    yaw_cue_resolution_radps: float = 1.28 * schema.DEG_TO_RAD
    substitute_yaw_cue: bool = True  # a substituted yaw rate (plausibility stage) is a cue, with its uncertainty
    offset_retro_gain: float = 0.6  # share of an offset jump's heading taken back when it is found (filter.py)
    wheel_cue_std_mps: float = 0.05  # cue axle's mean speed: 0.05 km/h quantisation, slip, v_y and lever arms
    # The car's driven axle: "front" (FWD) or "all" (AWD) take the wheel cue from the rear axle, "rear" (RWD) from
    # the front one, so that the cue does not read the driven wheels' slip (+3.6 % under traction on snow_val's RWD
    # drives, against +0.1 % for the free-rolling front axle). The front wheels' mean is steer-corrected with
    # ``steering_ratio`` (steering wheel angle over road wheel angle).
    driven_axle: str = "front"
    steering_ratio: float = 15.0
    cue_min_speed_mps: float = 1.0  # below this the ABS sensors read 0: no wheel-speed cue
    # wheel scale from GNSS: wheel distance over GNSS distance on baselines this long, above this speed
    scale_baseline_s: float = 5.0
    scale_min_speed_mps: float = 5.0
    # ... and with the filter's |a_x| under this (braking; accelerating too where the cue axle drives): the cue axle
    # rolls free there, so the scale is the tyres' (a 5-minute mixed drive: -0.13 % with braking, 0.000 % without)
    scale_max_accel_mps2: float = 0.3
    scale_meas_floor: float = 0.003  # slip and heading error per baseline
    standstill_hold_s: float = 0.5  # every wheel at 0 (and the speedometer) for this long: standstill
    standstill_skips_model: bool = True  # parked: zero-velocity update instead of the model's z
    standstill_std_mps: float = 0.02
    standstill_yaw_std_radps: float = 0.001
    # the calibration states' prior without a saved calibration, and their process noise
    # (ekf.numpy_ekf.CalibrationStd / CalibrationNoise document the values)
    cal_yaw_offset_prior_std_radps: float = CalibrationStd.yaw_offset_radps
    cal_wheel_scale_prior_std: float = CalibrationStd.wheel_scale
    cal_yaw_offset_psd: float = CalibrationNoise.yaw_offset_psd_rad2ps3
    cal_wheel_scale_psd: float = CalibrationNoise.wheel_scale_psd_ps
    cal_model_bias_std_radps: float = CalibrationNoise.model_bias_std_radps  # the model's omega_z error: Gauss-Markov
    cal_model_bias_tau_s: float = CalibrationNoise.model_bias_tau_s
    model_offset_share: float = CalibrationNoise.model_offset_share  # of the CAN yaw-rate offset, in model omega_z
    # With the raw cues: the model's omega_z variance times this. Its slow error is the Gauss-Markov state above
    # (0.3 deg/s, 60 s); what is left of each step's variance is inflated so far that, step by step, the gyro
    # carries the yaw rate and the model only tells the offset over minutes, weighed against the offset's own
    # uncertainty (chosen on the validation split, issue 26: benchmarks/filter_ablation.py). None: the model's
    # metadata (error_model, the 5 s mean-error ratio measured at export), else 1.
    model_omega_var_inflation: float | None = 5.0e4
    # ... except next to a coarse CAN yaw rate (its resolution, measured online, at least coarse_yaw_resolution):
    # quantisation error is slow, so there the model's omega_z carries the yaw rate step by step, its variance
    # times this (None: the metadata's 5 s factor). Until the resolution is measured: coarse_until_fine_step.
    # Chosen on validation (issue 26, docs/evaluation.md); inf as the threshold turns it off.
    model_omega_var_inflation_coarse: float | None = None
    coarse_yaw_resolution_radps: float = 0.2 * schema.DEG_TO_RAD
    # True (the default): until the resolution is measured (200 distinct readings: a 1.28 deg/s gyro on mild roads
    # often not in a minute) the gyro counts as coarse while yaw_cue_resolution_radps and every step it has taken
    # are at least coarse_yaw_resolution (a fine one shows a small step within a few samples). False (before):
    # fine until measured, so the model is inflated 5e4 and a coarse gyro's cue is weak: nothing carries the yaw
    # rate. Chosen on validation (issue 26, docs/evaluation.md).
    coarse_until_fine_step: bool = True
    # True (the default): until measured, the resolution (the cue's variance, the hold's interval) is the smaller of
    # yaw_cue_resolution_radps and the smallest step between distinct readings so far, which bounds it from above.
    # False (before): yaw_cue_resolution_radps (1.28 deg/s) until measured, even for a 0.24 deg/s gyro. Chosen on
    # validation (issue 26, docs/evaluation.md).
    resolution_from_steps: bool = True
    # ... and there the model's omega_z is held inside what the CAN reading allows: the reading less the offset
    # estimate, +- half a resolution step + this many times yaw_cue_std_radps (None: not held). A model wrong on
    # a road it never saw (snow) can then be no further from the truth than the coarse reading's interval. 3: the
    # usual gate, not tuned (on validation 1, 3 and 6 changed the 60 s RMSE by at most 0.04 m; issue 26).
    coarse_model_clamp_sigma: float | None = 3.0
    # The CAN yaw rate's gain, learned from GNSS heading in turns over drives (runtime/yaw_gain.py; kept in the
    # calibration file): the yaw-rate cue is divided by 1 + gain. Learned only from a gyro finer than
    # yaw_gain_max_resolution (the 1.28 deg/s ReV-StED sensor's quantisation follows the turn: its fit left ~1 %).
    yaw_gain_calibration: bool = True
    yaw_gain_max_resolution_radps: float = 1.0 * schema.DEG_TO_RAD
    # The CAN yaw rate's offset from the cues that do not contain the gyro (a_y / v, the rear wheels, the steering,
    # each with an offset of its own: runtime/cue_offset.py), while driving straight, fused into the offset state:
    # learned over minutes with no stop and no GNSS, where a model that reads the gyro passes its offset through.
    # Chosen on validation (issue 26, docs/evaluation.md): a fine gyro's +0.4 deg/s learned to 0.07 deg/s rms in
    # 5 min (0.34 without), and no validation split worse beyond its interval.
    cue_offset: bool = True
    # ... starting from the cues' own offsets the calibration file kept from earlier drives (the car's, not the
    # drive's); off: every drive starts them from their priors (an ablation: a cold start's minute cannot separate
    # the gyro's offset from them).
    cue_offset_restore: bool = True
    # ... and what the cues tell of the offset never more certain than this [rad/s], one sigma (their errors that do
    # not average out); 0: as certain as the blocks make it (CueOffsetConfig.systematic_std_radps)
    cue_offset_floor_radps: float = 0.0
    # ... a gyro this coarse [rad/s] or coarser tells its offset through the intervals its readings allow (a grid
    # likelihood, runtime/coarse_offset.py), its blocks only the cues' differences: on a straight it reads 0 whatever
    # its offset within half a step (the ReV-StED-like 1.28 deg/s gyro; the 0.5 deg/s one's grid is wrong: docs/
    # ablation.md); inf: every gyro's block means as they are
    cue_offset_coarse_min_step_radps: float = 1.0 * schema.DEG_TO_RAD
    # ... and only once the grid tells an offset at least this large [rad/s] beyond two of its sigmas; until then the
    # gyro's blocks as on a fine one. 0: from the first run. A small offset is as large as the rounding's window-to-
    # window mean (docs/ablation.md), where the compromise the fixes and blocks learn serves the cue as well. Chosen on
    # validation: the benchmark's splits as before to the centimetre, the real-car-like offsets' drift down a third
    cue_offset_coarse_min_offset_radps: float = 0.1 * schema.DEG_TO_RAD
    # ... the steering's offset restored with at least this uncertainty [deg of steering-wheel angle], one sigma: its
    # error follows the drive's mean yaw rate (wheelbase, understeer, lag), not a constant. 0.3 and 1 tried on
    # validation: van_fwd's dry_val loss does not move, snow_val's deployment a little worse. 0.14 (sqrt(2) x a
    # drive's spread about its car: the kept offsets are the last drive's) with a_y's 0.042: dry_val better beyond
    # the interval, no split worse (docs/ablation.md); 0.1 before. Back at 0.1 with a_y at 0.042: within 0.02 m on
    # every validation split but the real-car drives' +0.2 m: the a_y floor does the work
    cue_steer_restore_floor_deg: float = STEER_RESTORE_FLOOR_DEG
    # ... the lateral accelerometer's offset restored with at least this uncertainty [m/s^2], one sigma (its prior is
    # 0.3). 0.12 and 0.3 tried on validation: the van's dry_val windows 3.74 -> 3.08 m, but val's real-car drives
    # +5.7 m worse: the kept a_y offset is most of what the kept cues give them (docs/ablation.md). 0.042 with the
    # steering's 0.14 chosen on validation; 0.03 before
    cue_ay_restore_floor_mps2: float = AY_RESTORE_FLOOR_MPS2
    # The model reads the lateral acceleration and the steering-wheel angle less the offsets the cue estimator has
    # learned of them (the calibration file's and the drive so far's; runtime/cue_offset.py), as it reads the gyro
    # through its gain: a model passes part of a cue's offset into its omega_z (on validation's ReV-StED-like car
    # the true offsets taken out of its inputs took its window-mean omega_z error from 0.12 to 0.03 deg/s). Needs
    # calibration and cue_offset. Off (the raw CAN values): on validation it helped the fleet's calibrated drives
    # (dry_val -0.14 m) and lost on the real-car drives (+0.82 m), where an unknown gyro offset's share is left
    # without the a_y share that cancelled it (docs/ablation.md)
    model_inputs_from_cues: bool = False

    def __post_init__(self) -> None:
        if self.stride < 1:
            raise ValueError(f"stride must be >= 1, got {self.stride}")
        if not self.mu > 0:
            raise ValueError(f"mu must be > 0, got {self.mu}")
        if not 0.0 <= self.max_invalid_fraction <= 1.0:
            raise ValueError(f"max_invalid_fraction must be in [0, 1], got {self.max_invalid_fraction}")
        if self.driven_axle not in DRIVEN_AXLES:
            raise ValueError(f"driven_axle must be 'front' (FWD), 'rear' (RWD) or 'all' (AWD), "
                             f"got {self.driven_axle!r}")
        if not self.steering_ratio > 0:
            raise ValueError(f"steering_ratio must be > 0, got {self.steering_ratio}")
        if not (math.isfinite(self.cue_offset_floor_radps) and self.cue_offset_floor_radps >= 0.0):
            raise ValueError(f"cue_offset_floor_radps must be >= 0 (0: no floor), got {self.cue_offset_floor_radps}")
        gate = self.cue_offset_coarse_min_offset_radps
        if not (math.isfinite(gate) and gate >= 0.0):
            raise ValueError("cue_offset_coarse_min_offset_radps must be >= 0 [rad/s] (0: from the first run), got "
                             f"{self.cue_offset_coarse_min_offset_radps}")
        if not self.cue_offset_coarse_min_step_radps > 0.0:  # NaN too
            raise ValueError("cue_offset_coarse_min_step_radps must be > 0 [rad/s] (inf: off), got "
                             f"{self.cue_offset_coarse_min_step_radps}")
        for name in ("cal_yaw_offset_psd", "cal_wheel_scale_psd", "cue_steer_restore_floor_deg",
                     "cue_ay_restore_floor_mps2"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value}")
