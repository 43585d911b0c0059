"""A car's earlier drives, as its calibration file would have seen them: the evidence on its gyro's gain, and the
wheel scale its GNSS baselines taught.

The benchmark's drives each draw their own yaw-rate gain error; a real sensor keeps its gain from drive to drive
(within temperature and ageing). The runtime learns the gain from GNSS heading over many drives
(:mod:`prml2_edge.runtime.yaw_gain`) and keeps it in the calibration file, as it keeps the yaw-rate offset a
standstill taught. The evaluation gives each simulated drive that history: ``drives`` more drives of the same car,
``minutes`` in all, ``mixed`` family, dry, each with the drive's own gain plus a per-drive variation
(``variation``, one sigma: temperature), every other sensor error drawn anew, and consumer GNSS fixes
(:mod:`~prml2_edge.evaluation.consumer_gnss`, course over ground with its heading noise while moving). None of it
is the drive itself; everything is seeded by the drive's name. A gyro the runtime measures coarser than
``LocalizerConfig.yaw_gain_max_resolution_radps`` learns nothing (the runtime does not learn its gain either).

The history drives keep the drive's tyres (its per-wheel rolling-radius errors): a car's wheels read the same few
tenths of a percent fast or slow from one drive to the next, and the runtime keeps the wheel scale it learned
from GNSS distance in the same file. :func:`wheel_scale_evidence` runs the runtime's rule on the history (wheel
distance of the cue axle against the distance between two fixes over 5 s baselines above 5 m/s, the scale a random
walk between them) and hands back what the file would hold. Before, every window began from the scale's 1 % prior,
which on the simulator's cars (0.3 % spread) let 30 s of noisy baselines move the scale further than the truth.

The history drives also keep the drive's accelerometer and steering offsets (the unit's mounting and the steering's
alignment), each with a per-drive variation (``CUE_VARIATION``: temperature, the column's play). The runtime's cue
estimator (:mod:`prml2_edge.runtime.cue_offset`) runs over them, each drive starting the gyro's offset from its
prior, and :func:`cue_evidence` hands back the cues' own offsets the file would hold.

The drive is itself one draw about its car (``DRIVE_DRAW``, the default): the car's gain and cue offsets are the
drive's plus one per-drive variation, and the history drives vary about the car's. Before (``DRIVE_DRAW = False``)
the history varied about the drive's own values, so the drive sat at the car's mean and a file that averages its
drives knew the drive's gain and offsets about twice as well as a real one can.
"""

from __future__ import annotations

import math
import zlib

import numpy as np

from prml2_edge import schema
from prml2_edge.evaluation.consumer_gnss import (
    GNSS_HEADING_MIN_SPEED_MPS,
    GNSS_HEADING_STD_DEG,
    GNSS_POS_STD_M,
    GNSS_RATE_HZ,
)
from prml2_edge.runtime.yaw_gain import YawGainEstimator
from prml2_edge.runtime.yaw_resolution import YawResolution

HISTORY_MINUTES = 20.0
HISTORY_DRIVES = 4
GAIN_VARIATION = 0.002  # per-drive spread of a sensor's gain around its own (temperature), one sigma
# per-drive spread of the accelerometer's offset [m/s^2] and the steering's [rad] around the car's, one sigma
CUE_VARIATION = (0.03, 0.1 * schema.DEG_TO_RAD)
DRIVE_DRAW = True  # the drive one draw about its car's gain and cue offsets (module docstring); a benchmark's switch
_CACHE: dict[tuple, dict] = {}
_YAW = schema.SIGNAL_BY_NAME["yaw_rate_radps"].index


def gain_evidence(drive, minutes: float = HISTORY_MINUTES, drives: int = HISTORY_DRIVES,
                  variation: float = GAIN_VARIATION) -> tuple[float, float] | None:
    """``(info, info_c)`` the runtime's gain estimator gathers over the drive's simulated history, or None (not a
    simulated drive of the fleet, no history asked for, or a gyro too coarse to learn a gain from)."""
    hist = _history(drive, minutes, drives, variation)
    return None if hist is None else hist["gain"]


def wheel_scale_evidence(drive, minutes: float = HISTORY_MINUTES, drives: int = HISTORY_DRIVES,
                         variation: float = GAIN_VARIATION) -> tuple[float, float] | None:
    """``(scale, variance)`` of the cue axle's wheel scale the history's GNSS baselines taught (the calibration
    file's, before its restore floor), or None (not a simulated drive of the fleet, or no history asked for)."""
    hist = _history(drive, minutes, drives, variation)
    return None if hist is None else hist["scale"]


def cue_evidence(drive, minutes: float = HISTORY_MINUTES, drives: int = HISTORY_DRIVES,
                 variation: float = GAIN_VARIATION) -> tuple[np.ndarray, np.ndarray] | None:
    """``(values (3,), cov (3, 3))``: the cues' own offsets the runtime's cue estimator learned over the history
    (:meth:`~prml2_edge.runtime.cue_offset.CueOffset.nuisance`, before the restore floor); None (not a simulated
    drive of the fleet, or no history asked for)."""
    hist = _history(drive, minutes, drives, variation)
    return None if hist is None else hist["cues"]


def _history(drive, minutes: float, drives: int, variation: float) -> dict | None:
    from prml2_edge.data.simulate.fleet import CARS

    meta = drive.meta or {}
    gain = (meta.get("sensor_errors") or {}).get("yaw_scale_error")
    if minutes <= 0.0 or drives < 1 or gain is None or str(meta.get("vehicle")) not in CARS:
        return None
    key = (drive.name, str(meta["vehicle"]), float(gain), minutes, drives, variation, DRIVE_DRAW)
    if key not in _CACHE:  # split_tasks asks once per protocol
        _CACHE[key] = _simulate_history(drive, float(gain), minutes, drives, variation)
    return _CACHE[key]


def _coarse(drive) -> bool:
    """Whether the drive's CAN yaw rate is too coarse to learn a gain from, measured as the runtime measures it
    (the 10th percentile of the steps between distinct readings)."""
    from prml2_edge.runtime.localizer import LocalizerConfig

    yaw = drive.onboard[:, schema.SIGNAL_BY_NAME["yaw_rate_radps"].index]
    steps = np.abs(np.diff(yaw[np.isfinite(yaw)]))
    steps = steps[steps > 0.0]
    return steps.size > 0 and float(np.percentile(steps[:200], 10)) >= LocalizerConfig().yaw_gain_max_resolution_radps


def _simulate_history(drive, gain: float, minutes: float, drives: int, variation: float) -> dict:
    from prml2_edge.data.simulate import simulate_drive
    from prml2_edge.data.simulate.fleet import CARS

    meta = drive.meta
    coarse = _coarse(drive)
    tyres = (meta.get("sensor_errors") or {}).get("wheel_radius_error")
    rng = np.random.default_rng([zlib.crc32(drive.name.encode()), 0x6741494E])  # "gAIN"
    est = YawGainEstimator(math.radians(GNSS_HEADING_STD_DEG))
    settings = CARS[str(meta["vehicle"])].filter_settings()  # (_history: a car of the fleet)
    scale = WheelScaleHistory(**settings)
    cues, runtime = _cue_estimator(settings["steering_ratio"])
    cue_rng = np.random.default_rng([zlib.crc32(drive.name.encode()), 0x43554553])  # "CUES": the gain's draws stay
    # the car's gain and cue offsets: the drive's, or (DRIVE_DRAW) the drive's plus one per-drive variation
    car_rng = np.random.default_rng([zlib.crc32(drive.name.encode()), 0x43415253])  # "CARS"
    car = _car_cue_errors(meta, car_rng) if DRIVE_DRAW else meta.get("sensor_errors") or {}
    gain = gain + float(car_rng.normal(0.0, variation)) if DRIVE_DRAW else gain
    for j in range(drives):
        g = gain + float(rng.normal(0.0, variation))
        errors = {"yaw_scale_error": g} | ({"wheel_radius_error": tuple(tyres)} if tyres is not None else {}) \
            | _car_cue_errors({"sensor_errors": car}, cue_rng)
        hist = simulate_drive(minutes / drives, 1.0, int(rng.integers(1 << 31)), "mixed", f"{drive.name}_history{j}",
                              sensor_errors=errors, vehicle=str(meta["vehicle"]))
        if not coarse:
            feed(est, hist, rng)
        scale.feed(hist, rng)
        if j:
            cues.new_drive()
        cues.rows(hist.onboard, 1.0, YawResolution.of(hist.onboard[:, _YAW], runtime))  # as the runtime
    return {"gain": None if coarse else (est.info, est.info_c), "scale": (scale.k, scale.var),
            "cues": cues.nuisance()}


def _cue_estimator(steering_ratio: float):
    from prml2_edge.runtime.cue_offset import CueOffset, CueOffsetConfig
    from prml2_edge.runtime.localizer import LocalizerConfig

    cfg = LocalizerConfig()
    return (CueOffset(cfg.cal_yaw_offset_prior_std_radps, steering_ratio, CueOffsetConfig.from_localizer(cfg)),
            cfg)


def _car_cue_errors(meta: dict, rng: np.random.Generator) -> dict:
    """The drive's accelerometer and steering offsets with this history drive's variation (``CUE_VARIATION``); {}
    for a drive whose metadata does not have them."""
    errors = meta.get("sensor_errors") or {}
    out = {}
    for name, spread in zip(("lat_offset_mps2", "steer_offset_rad"), CUE_VARIATION, strict=True):
        if errors.get(name) is not None:
            out[name] = float(errors[name]) + float(rng.normal(0.0, spread))
    return out


class WheelScaleHistory:
    """The runtime's wheel-scale rule (``runtime/filter.py``: ``_odometry``, ``_scale_from_gnss``) over whole simulated
    drives: the cue axle's wheel distance along the heading against the displacement between two consumer-GNSS
    fixes ``baseline_s`` apart while the cue speed stays above ``min_speed_mps`` and the cue axle rolls free, each a
    measurement of the scale with variance ``2 sigma^2 / d^2 + floor^2`` (``d`` the wheels' distance), fused into a
    random walk (the EKF's wheel-scale state, alone). The heading is the drive's true one: a GNSS-aided filter's is
    within a degree, which moves a baseline by < 0.02 %."""

    def __init__(self, driven_axle: str = "front", steering_ratio: float = 15.0) -> None:
        from prml2_edge.ekf.numpy_ekf import CalibrationNoise, CalibrationStd
        from prml2_edge.runtime.localizer import LocalizerConfig

        cfg = LocalizerConfig()
        self.driven_axle, self.steering_ratio = driven_axle, float(steering_ratio)
        self.baseline_s, self.min_speed_mps, self.floor = cfg.scale_baseline_s, cfg.scale_min_speed_mps, \
            cfg.scale_meas_floor
        self.max_accel = cfg.scale_max_accel_mps2  # (the true a_x stands for the GNSS-aided filter's)
        self.psd = CalibrationNoise.wheel_scale_psd_ps
        self.k, self.var = 0.0, CalibrationStd.wheel_scale ** 2
        self.n_baselines = 0

    def cue_speed(self, onboard: np.ndarray) -> np.ndarray:
        """The filter's wheel cue per row [m/s]: the axle that does not drive (a RWD car's front, steer-corrected)."""
        fl, fr, rl, rr = (onboard[:, i] for i in schema.WHEEL_SPEED_INDICES)
        if self.driven_axle == "rear":
            steer = onboard[:, schema.SIGNAL_BY_NAME["steering_wheel_angle_rad"].index]
            return (fl + fr) / 2 * np.cos(steer / self.steering_ratio)
        return (rl + rr) / 2

    def feed(self, drive, rng: np.random.Generator) -> None:
        """One drive's baselines, in order (the walk's variance grows with the time between them)."""
        w = self.cue_speed(drive.onboard)
        psi = drive.pose_gt[:, 2]
        dt = schema.DT_S
        step = np.where(np.isfinite(w), w, 0.0) * dt
        odo = np.stack([np.cumsum(step * np.cos(psi)), np.cumsum(step * np.sin(psi))], axis=1)
        ax = drive.z_gt[:, schema.Z.A_X]
        rolling = (ax >= -self.max_accel) & ((ax <= self.max_accel) | (self.driven_axle != "all"))
        fast = np.isfinite(w) & (w >= self.min_speed_mps) & rolling
        every = int(round(schema.SAMPLE_RATE_HZ / GNSS_RATE_HZ))
        span = int(round(self.baseline_s / dt))
        fixes = drive.pose_gt[:, :2] + rng.normal(0.0, GNSS_POS_STD_M, (len(w), 2))
        i, last = every, 0
        while i + span < len(w):
            j = i + span
            if not fast[i + 1: j + 1].all():  # a slow or slipping row restarts the baseline at the next fix
                i += every
                continue
            d = fixes[j] - fixes[i]
            dist2 = float(d @ d)
            if dist2 > 1.0:
                wheel = odo[j] - odo[i]
                var = 2.0 * GNSS_POS_STD_M ** 2 / max(float(wheel @ wheel), 1.0) + self.floor ** 2
                self._update(float(wheel @ d) / dist2 - 1.0, var, (j - last) * dt)
                last = j
            i = j

    def _update(self, scale: float, var: float, dt_s: float) -> None:
        self.var += self.psd * dt_s
        gain = self.var / (self.var + var)
        self.k += gain * (scale - self.k)
        self.var *= 1.0 - gain
        self.n_baselines += 1


def feed(est: YawGainEstimator, drive, rng: np.random.Generator) -> None:
    """Run ``est`` over ``drive``: its CAN yaw rate every row, a GNSS course-over-ground fix at the protocol's rate
    while moving."""
    yaw = drive.onboard[:, schema.SIGNAL_BY_NAME["yaw_rate_radps"].index].tolist()
    every = int(round(schema.SAMPLE_RATE_HZ / GNSS_RATE_HZ))
    vx, vy = drive.z_gt[:, 0], drive.z_gt[:, 1]
    course = (drive.pose_gt[:, 2] + np.arctan2(vy, vx)).tolist()
    speed = np.hypot(vx, vy)
    moving = (speed >= GNSS_HEADING_MIN_SPEED_MPS).tolist()
    wheels = drive.onboard[:, [schema.SIGNAL_BY_NAME[n].index for n in schema.WHEEL_SPEED_NAMES[2:]]].mean(axis=1)
    wheels = np.maximum(wheels, 0.1).tolist()
    noise = rng.normal(0.0, math.sqrt(est.heading_var), len(yaw)).tolist()
    dt = schema.DT_S
    for i, w in enumerate(yaw):
        est.yaw_rate(w if math.isfinite(w) else None, dt)
        if i % every == 0 and moving[i]:
            est.heading(i * dt, course[i] + noise[i], w, wheels[i])
    est.close_chunk()
