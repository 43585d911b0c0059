"""A car's earlier drives, as its calibration file would have seen them: the evidence on its gyro's gain.

The benchmark's drives each draw their own yaw-rate gain error; a real sensor keeps its gain from drive to drive
(within temperature and ageing). The runtime learns the gain from GNSS heading over many drives
(:mod:`prml2_edge.runtime.yaw_gain`) and keeps it in the calibration file, as it keeps the yaw-rate offset a
standstill taught. The evaluation gives each simulated drive that history: ``drives`` more drives of the same car,
``minutes`` in all, ``mixed`` family, dry, each with the drive's own gain plus a per-drive variation
(``variation``, one sigma: temperature), every other sensor error drawn anew, and consumer GNSS fixes
(:mod:`~prml2_edge.evaluation.consumer_gnss`, course over ground with its heading noise while moving). None of it
is the drive itself; everything is seeded by the drive's name. A gyro the runtime measures coarser than
``LocalizerConfig.yaw_gain_max_resolution_radps`` learns nothing (the runtime does not learn its gain either).
"""

from __future__ import annotations

import math
import zlib

import numpy as np

from prml2_edge import schema
from prml2_edge.evaluation.consumer_gnss import GNSS_HEADING_MIN_SPEED_MPS, GNSS_HEADING_STD_DEG, GNSS_RATE_HZ
from prml2_edge.runtime.yaw_gain import YawGainEstimator

HISTORY_MINUTES = 20.0
HISTORY_DRIVES = 4
GAIN_VARIATION = 0.002  # per-drive spread of a sensor's gain around its own (temperature), one sigma
_CACHE: dict[tuple, tuple[float, float] | None] = {}


def gain_evidence(drive, minutes: float = HISTORY_MINUTES, drives: int = HISTORY_DRIVES,
                  variation: float = GAIN_VARIATION) -> tuple[float, float] | None:
    """``(info, info_c)`` the runtime's gain estimator gathers over the drive's simulated history, or None (not a
    simulated drive of the fleet, or no history asked for)."""
    from prml2_edge.data.simulate.fleet import CARS

    meta = drive.meta or {}
    gain = (meta.get("sensor_errors") or {}).get("yaw_scale_error")
    if minutes <= 0.0 or drives < 1 or gain is None or str(meta.get("vehicle")) not in CARS:
        return None
    key = (drive.name, str(meta["vehicle"]), float(gain), minutes, drives, variation)
    if key not in _CACHE:  # split_tasks asks once per protocol
        _CACHE[key] = None if _coarse(drive) else _simulate_history(drive, float(gain), minutes, drives, variation)
    return _CACHE[key]


def _coarse(drive) -> bool:
    """Whether the drive's CAN yaw rate is too coarse to learn a gain from, measured as the runtime measures it
    (the 10th percentile of the steps between distinct readings)."""
    from prml2_edge.runtime.localizer import LocalizerConfig

    yaw = drive.onboard[:, schema.SIGNAL_BY_NAME["yaw_rate_radps"].index]
    steps = np.abs(np.diff(yaw[np.isfinite(yaw)]))
    steps = steps[steps > 0.0]
    return steps.size > 0 and float(np.percentile(steps[:200], 10)) >= LocalizerConfig().yaw_gain_max_resolution_radps


def _simulate_history(drive, gain: float, minutes: float, drives: int, variation: float) -> tuple[float, float]:
    from prml2_edge.data.simulate import simulate_drive

    meta = drive.meta
    rng = np.random.default_rng([zlib.crc32(drive.name.encode()), 0x6741494E])  # "gAIN"
    est = YawGainEstimator(math.radians(GNSS_HEADING_STD_DEG))
    for j in range(drives):
        g = gain + float(rng.normal(0.0, variation))
        hist = simulate_drive(minutes / drives, 1.0, int(rng.integers(1 << 31)), "mixed", f"{drive.name}_history{j}",
                              sensor_errors={"yaw_scale_error": g}, vehicle=str(meta["vehicle"]))
        feed(est, hist, rng)
    return est.info, est.info_c


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
