"""The CAN yaw rate's offset from the other yaw-rate cues while driving, with no stop and no GNSS (issue 26).

A model that reads the gyro passes its offset through, so the gyro against the model says nothing of it next to a fine
gyro (``benchmarks/offset_learning.py``). Three cues in the CAN signals do not contain the gyro, each with a slow
error of its own that has its own shape in speed (``benchmarks/offset_observability.py``):

* ``a_y / v`` (lateral acceleration over the rear-axle speed): an accelerometer offset ``c`` gives ``c / v``;
* the rear wheels' difference over the track: a rolling-radius difference gives ``k v``;
* the kinematic single-track steering rate: a steering-wheel offset gives about ``d v``.

The gyro's offset ``b`` is a constant, so over minutes of driving at varying speed it separates from the rest.
:class:`CueOffset` is a linear Kalman filter over ``θ = (b, c, k, d)``: per block of ``block_s`` seconds of
near-straight moving rows (every row above ``min_speed_mps`` with ``|a_y|`` under ``max_lat_accel_mps2``; the
steering rate's understeer and the geometry's unknowns vanish there), the block means of gyro − cue are three
measurements::

    gyro − a_y / v      = b − c · mean(1 / v)
    gyro − rear wheels  = b − k · mean(v)
    gyro − steering     = b − d · mean(v)

Track and wheelbase need not be known: off the straights their error scales the yaw rate, which is near 0 there, and
the offsets' slopes ``k`` and ``d`` [rad/m] are learned as they are. :meth:`CueOffset.export` hands what it has
learned of ``b`` since the last export to the pose filter as one measurement (the information it gained, so that
nothing is counted twice), where it meets the CAN yaw-rate offset state.

A coarse gyro (the ReV-StED car's 1.28 deg/s) reads 0 on a straight whatever its offset within half a step, so its
block means measure the rounding of the road's gentle curves, not ``b``, and the blocks grow surer without growing
righter (docs/ablation.md). With ``coarse_min_step_radps`` at or under its resolution, the intervals its readings
allow build a likelihood over a grid of ``b`` alongside (:mod:`~prml2_edge.runtime.coarse_offset`). Once the grid
tells an offset beyond ``coarse_min_offset_radps`` plus two of its sigmas it takes over for the drive: ``b`` is the
grid's, the blocks give only the cues' differences (which the gyro cancels out of, so ``c, k, d`` still learn), and
:attr:`CueOffset.handed_over` tells the pose filter to forget what the blocks told it and take the grid's whole
estimate. A small offset is left to the blocks: there the filter's cue wants the rounding's mean, which the blocks
and the fixes learn, not the offset (docs/ablation.md).

The cues' own offsets belong to the car (the accelerometer's mounting, the tyres, the steering's alignment), not to
the drive, so the calibration file keeps them (:meth:`CueOffset.nuisance`) and the next drive starts from them
(:meth:`CueOffset.restore`): in a minute of driving at one speed ``b`` does not separate from them, and a cold start
has only their priors. The gyro's offset starts each drive from its prior; it moves between drives. What a drive
hands on is its own estimate (the next drive's prior is it widened by ``restore_std_floor``, so the last drive
dominates). A car's mean over its drives and a release of the kept offsets at the drive's first stop were tried on
validation and removed (docs/ablation.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from prml2_edge import schema
from prml2_edge.ekf.numpy_ekf import checked_gaussian
from prml2_edge.runtime.axle_speed import rear_speed
from prml2_edge.runtime.coarse_offset import CoarseOffset

_SIG = schema.SIGNAL_BY_NAME
_YAW, _AY, _STEER = (_SIG[n].index for n in ("yaw_rate_radps", "lat_accel_mps2", "steering_wheel_angle_rad"))
_RL, _RR = _SIG["wheel_speed_rl_mps"].index, _SIG["wheel_speed_rr_mps"].index
_NEEDED = (_YAW, _AY, _STEER, _RL, _RR)
NOMINAL_TRACK_M = 1.55
NOMINAL_WHEELBASE_M = 2.7
_GYRO_FREE = np.array([[1.0, -1.0, 0.0], [1.0, 0.0, -1.0]])  # the cues' differences: a_y/v − wheels, a_y/v − steering
NUISANCE_NAMES = ("lat_accel_offset_mps2", "rear_radius_diff_radpm", "steering_offset_radpm")


def steering_offset(deg: float) -> float:
    """A steering-wheel angle offset [deg] as the steering cue's offset state ``d`` [rad/m] (nominal ratio 15 and
    wheelbase)."""
    return deg * schema.DEG_TO_RAD / (15.0 * NOMINAL_WHEELBASE_M)


# one-sigma floor of restored cue offsets: they move between drives (the accelerometer with temperature, tyre
# pressure, the column's play), so a restored estimate is a strong prior, not a certainty. a_y and steering at
# sqrt(2) x a drive's spread about its car (0.03 m/s^2, 0.1 deg): the kept offsets are the last drive's, which
# differs from this one by two draws. Chosen on validation (docs/ablation.md; 0.03 / 0.1 before). The runtime's
# LocalizerConfig.cue_ay_restore_floor_mps2 / cue_steer_restore_floor_deg default to these
AY_RESTORE_FLOOR_MPS2 = 0.042
STEER_RESTORE_FLOOR_DEG = 0.14
RESTORE_STD_FLOOR = (AY_RESTORE_FLOOR_MPS2, 0.001 / NOMINAL_TRACK_M, steering_offset(STEER_RESTORE_FLOOR_DEG))


def checked_nuisance(values, cov) -> tuple[np.ndarray, np.ndarray]:
    """The cues' own offsets ``(values (3,), cov (3, 3))`` as float arrays, the covariance made symmetric; ValueError
    on a wrong shape, a non-finite value or a covariance that is not positive (semi-)definite."""
    return checked_gaussian(values, cov, len(NUISANCE_NAMES))


@dataclass(frozen=True)
class CueOffsetConfig:
    """The estimator's settings, SI units; chosen on the validation drives (docs/evaluation.md)."""

    block_s: float = 2.0
    min_speed_mps: float = 5.0
    max_lat_accel_mps2: float = 0.5
    # one block's mean of gyro − cue about the cue's offset term (slip, sideslip, understeer, road and sensor
    # noise), per cue: a_y / v, rear wheels, steering. The rows' scatter on val's straights (0.1 / 0.5 / 0.4 °/s)
    # lasts longer than a block, so it is not divided down
    block_std_radps: tuple[float, float, float] = (0.15 * schema.DEG_TO_RAD, 0.5 * schema.DEG_TO_RAD,
                                                   0.5 * schema.DEG_TO_RAD)
    # the cues' own offsets, one sigma: a_y [m/s^2], rear radius difference over the track [rad/m], steering [rad/m]
    prior_std: tuple[float, float, float] = (0.3, 0.015 / NOMINAL_TRACK_M,
                                             steering_offset(4.0))
    # random walks: each state's variance grows by this per second (b: the filter's offset drift, 0.0066 deg/s in
    # 10 min; c: the accelerometer's with temperature; k, d: tyres warming, the column's play)
    psd: tuple[float, float, float, float] = (2.2e-11, 1e-8, 1e-12, 1e-12)
    min_gain: float = 0.5  # an export needs this much information on b, in units of its prior's
    # a gyro whose resolution is at least this [rad/s] tells its offset through the intervals its readings allow
    # (module docstring, "A coarse gyro"); inf: never, every gyro's block means are taken as they are
    coarse_min_step_radps: float = 1.0 * schema.DEG_TO_RAD
    # ... once the grid's |b| less two of its sigmas reaches this [rad/s]; before, the gyro's blocks as they are (the
    # grid listens alongside). 0: the grid from the first run
    coarse_min_offset_radps: float = 0.1 * schema.DEG_TO_RAD
    # a floor under what the cues can tell of b [rad/s], one sigma: their errors that do not average out (a van's
    # steering geometry against the nominal, the history's offsets); the exports never add up to more information
    # than 1 / floor^2. 0: none
    systematic_std_radps: float = 0.0
    # the least uncertainty a restored offset keeps, one sigma, per cue (c, k, d): what can change between drives
    restore_std_floor: tuple[float, float, float] = RESTORE_STD_FLOOR

    @classmethod
    def from_localizer(cls, config) -> CueOffsetConfig:
        """The settings a :class:`~prml2_edge.runtime.localizer_config.LocalizerConfig` gives (its floor under what
        the cues tell, its coarse-gyro threshold, on a low-friction road none: a sliding car's a_y / v does not tell
        its yaw rate; its a_y and steering restore floors); the rest default."""
        dry = float(getattr(config, "mu", 1.0)) > schema.LOW_MU_THRESHOLD
        return cls(systematic_std_radps=float(config.cue_offset_floor_radps),
                   coarse_min_step_radps=float(config.cue_offset_coarse_min_step_radps) if dry else math.inf,
                   coarse_min_offset_radps=float(config.cue_offset_coarse_min_offset_radps),
                   restore_std_floor=(float(config.cue_ay_restore_floor_mps2), RESTORE_STD_FLOOR[1],
                                      steering_offset(float(config.cue_steer_restore_floor_deg))))


class CueOffset:
    """The linear filter over ``(b, c, k, d)`` (module docstring); :meth:`row` once per 50 Hz step."""

    DIM = 4

    def __init__(self, b_prior_std_radps: float, steering_ratio: float, config: CueOffsetConfig | None = None,
                 dt_s: float = schema.DT_S) -> None:
        self.config = config or CueOffsetConfig()
        self.steering_ratio = float(steering_ratio)
        self.dt_s = float(dt_s)
        self._block_rows = max(1, int(round(self.config.block_s / self.dt_s)))
        self._prior = np.diag(np.square((float(b_prior_std_radps),) + tuple(self.config.prior_std)))
        self._R = np.diag(np.square(self.config.block_std_radps))
        self._start = (np.zeros(self.DIM), self._prior.copy())  # where :meth:`reset` begins (:meth:`restore`)
        self.coarse = CoarseOffset(float(b_prior_std_radps))
        self._finest = math.inf  # the finest resolution the gyro has shown (a filter that starts again re-measures)
        self.restored = False
        self.reset()

    def reset(self) -> None:
        self.theta = self._start[0].copy()
        self.P = self._start[1].copy()
        self._sums = np.zeros(5)  # gyro − a_y/v, gyro − rear, gyro − steering, 1/v, v
        self._n = 0
        self.blocks = 0
        self.coarse.reset()
        self._coarse_on = False  # the finest step the gyro has shown is coarse: the grid listens
        self._grid_on = False  # ... and tells a large enough offset (coarse_min_offset_radps): b is the grid's
        self._pending: list[tuple[float, float, float]] = []  # the coarse gyro's straight rows: reading, a_y, v
        self._step = 0.0
        self._nis_sum = np.zeros(3)  # per cue: innovation squared over its predicted variance, summed over blocks
        self._nis_n = 0  # ... that saw the gyro
        self.restart_export()  # (b, var) at the last export

    def restart_export(self) -> None:
        """The next :meth:`export` hands over everything learned (to a filter that starts again from its prior, or
        that has forgotten what the blocks told it when the grid took over: :attr:`handed_over`)."""
        self._exported = (0.0, float(self._prior[0, 0]) + self.config.systematic_std_radps ** 2)
        self.handed_over = False

    def nuisance(self) -> tuple[np.ndarray, np.ndarray]:
        """The cues' own offsets ``(c, k, d)`` (:data:`NUISANCE_NAMES`) and their covariance (3, 3): what the
        calibration file keeps for the next drive."""
        return self.theta[1:].copy(), self.P[1:, 1:].copy()

    def restore(self, values, cov) -> None:
        """Start from the cues' offsets an earlier drive learned (:meth:`nuisance`), their covariance floored at
        ``config.restore_std_floor`` (default :data:`RESTORE_STD_FLOOR`); ``b`` starts from its prior. Raises
        ValueError on a wrong shape, a non-finite value or a covariance that is not positive."""
        values, cov = checked_nuisance(values, cov)
        P = self._prior.copy()
        P[1:, 1:] = cov + np.diag(np.square(self.config.restore_std_floor))
        self._start = (np.concatenate([[0.0], values]), P)
        self.restored = True
        self.reset()

    def new_drive(self) -> None:
        """Between two drives of one car: what was learned of the cues' offsets stays, ``b`` back to its prior."""
        self.restore(*self.nuisance())

    def debiased(self, values: np.ndarray) -> np.ndarray:
        """A copy of one row ``values`` (9,) [SI, canonical order] with the lateral accelerometer's offset ``c`` and
        the steering wheel's (``d`` times the steering ratio and the nominal wheelbase: the steering cue's slope is
        that offset over them) taken out: what a model reads next to this estimator."""
        out = np.array(values, dtype=np.float64, copy=True)
        out[_AY] -= float(self.theta[1])
        out[_STEER] -= float(self.theta[3]) * self.steering_ratio * NOMINAL_WHEELBASE_M
        return out

    @property
    def offset(self) -> tuple[float, float]:
        """``(b, its standard deviation)`` [rad/s]: a coarse gyro's from the grid once it took over, else the
        filter's."""
        if self._grid_on:
            return self.coarse.offset
        return float(self.theta[0]), math.sqrt(max(float(self.P[0, 0]), 0.0))

    def row(self, values: np.ndarray, valid: np.ndarray, yaw_gain: float = 1.0,
            step_radps: float | None = None) -> bool:
        """One step's CAN signals (``step_radps``: the gyro's resolution as the filter knows it, None: unknown); True
        when it updated the estimate (closed a block). A row that does not qualify (slow, turning, a signal missing)
        ends the block it would have joined."""
        if step_radps is not None:
            self._finest = min(self._finest, float(step_radps))
        self._coarse_on = math.isfinite(self._finest) and self._finest >= self.config.coarse_min_step_radps
        if not self._coarse_on or self.config.coarse_min_offset_radps <= 0.0:
            if self._coarse_on and not self._grid_on and self._nis_n:
                self.handed_over = True  # the grid from its first run, after blocks that saw the gyro (step unknown)
            self._grid_on = self._coarse_on
        v = self._straight_speed(values, valid)
        if v is None:
            self._sums[:] = 0.0
            self._n = 0
            return self._flush_coarse() > 0
        gyro = float(values[_YAW]) * yaw_gain
        steer = v * math.tan(float(values[_STEER]) / self.steering_ratio) / NOMINAL_WHEELBASE_M
        rear = (float(values[_RR]) - float(values[_RL])) / NOMINAL_TRACK_M
        self._sums += (gyro - float(values[_AY]) / v, gyro - rear, gyro - steer, 1.0 / v, v)
        self._n += 1
        if self._coarse_on:
            self._pending.append((gyro, float(values[_AY]), v))
            self._step = self._finest * yaw_gain
        if self._n < self._block_rows:
            return False
        means = self._sums / self._n
        self._sums[:] = 0.0
        self._n = 0
        self._update(means, with_gyro=not self._grid_on)
        self._flush_coarse()
        return True

    def _flush_coarse(self) -> int:
        """The coarse gyro's pending straight rows to the grid, their rate from ``a_y / v`` less its offset ``c``
        as the filter knows it now; returns the runs of one reading it used."""
        if not self._pending:
            return 0
        rows = np.asarray(self._pending)
        self._pending = []
        inv_v = 1.0 / rows[:, 2]
        rate = (rows[:, 1] - self.theta[1]) * inv_v
        used = self.coarse.block(rows[:, 0], rate, self._step,
                                 math.sqrt(max(float(self.P[1, 1]), 0.0)) * float(np.mean(inv_v)))
        if used and not self._grid_on:  # the grid takes over once it tells a large enough offset
            b, std = self.coarse.offset
            self._grid_on = self.handed_over = abs(b) - 2.0 * std >= self.config.coarse_min_offset_radps
        return used

    def rows(self, onboard: np.ndarray, yaw_gain: float = 1.0, step_radps: float | None = None) -> int:
        """:meth:`row` over every row of ``onboard`` (N, 9) [SI, canonical order; NaN: a missing signal]: a drive's
        signals so far, as the runtime would have seen them. Returns the updates it made."""
        onboard = np.asarray(onboard, dtype=np.float64)
        closed = 0
        for values, valid in zip(onboard, np.isfinite(onboard), strict=True):
            closed += self.row(values, valid, yaw_gain, step_radps)
        return closed

    def _straight_speed(self, values: np.ndarray, valid: np.ndarray) -> float | None:
        cfg = self.config
        if not all(valid[i] for i in _NEEDED):
            return None
        v = rear_speed(values, valid)
        if not (v is not None and v >= cfg.min_speed_mps and abs(float(values[_AY])) <= cfg.max_lat_accel_mps2):
            return None
        return v

    def _update(self, means: np.ndarray, with_gyro: bool = True) -> None:
        """One block's means of gyro − cue per cue with mean(1/v), mean(v); ``with_gyro`` False: only the cues'
        differences, which the gyro (and its rounding) cancel out of."""
        dt = self._block_rows * self.dt_s
        self.P = self.P + np.diag(self.config.psd) * dt
        inv_v, v = means[3], means[4]
        H = np.array([[1.0, -inv_v, 0.0, 0.0], [1.0, 0.0, -v, 0.0], [1.0, 0.0, 0.0, -v]])
        y, R = means[:3] - H @ self.theta, self._R
        if not with_gyro:
            H, y, R = _GYRO_FREE @ H, _GYRO_FREE @ y, _GYRO_FREE @ R @ _GYRO_FREE.T
        S = H @ self.P @ H.T + R
        K = np.linalg.solve(S, H @ self.P).T
        if with_gyro:
            self._nis_sum += y * y / np.diag(S)
            self._nis_n += 1
        self.theta = self.theta + K @ y
        I_KH = np.eye(self.DIM) - K @ H
        self.P = I_KH @ self.P @ I_KH.T + K @ R @ K.T
        self.blocks += 1

    @property
    def nis(self) -> np.ndarray:
        """Per cue (a_y / v, rear wheels, steering): the mean normalised innovation squared over the blocks so far
        (about 1 where ``block_std_radps`` states the blocks' scatter rightly; NaN before the first block)."""
        return self._nis_sum / self._nis_n if self._nis_n else np.full(3, np.nan)

    def summary(self) -> dict:
        """For the run's summary: the blocks used, a coarse gyro's runs of one reading and whether its grid took
        over, the offset the cues tell with its sigma [deg/s] and the NIS (None before the first block: the summary
        is written as strict JSON, which has no NaN)."""
        b, std = self.offset
        return {"blocks": self.blocks, "coarse_runs": self.coarse.runs, "coarse_grid": self._grid_on,
                "restored": self.restored,
                "yaw_rate_offset_dps": math.degrees(b), "yaw_rate_offset_std_dps": math.degrees(std),
                "nis": [round(float(x), 3) for x in self.nis] if self._nis_n else None}

    def export(self) -> tuple[float, float] | None:
        """What was learned of ``b`` since the last export as one measurement ``(value, variance)`` [rad/s,
        rad^2/s^2]: the marginal's information gain and the value that carries it; None while the gain is under
        ``min_gain`` of the prior's information."""
        b, std = self.offset
        var = std ** 2 + self.config.systematic_std_radps ** 2
        b0, var0 = self._exported
        gain = 1.0 / var - 1.0 / var0
        if gain < self.config.min_gain / float(self._prior[0, 0]):
            if gain < 0.0 and not self._grid_on:
                self._exported = (b, var)  # drifted: what was exported is older than the estimate's memory
            # the grid forgets nothing: a wider posterior is a reshaped one, its information already handed over
            return None
        self._exported = (b, var)
        return (b / var - b0 / var0) / gain, 1.0 / gain
