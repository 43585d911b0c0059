"""The OSD-Baseline (paper Eq. obd; NumPy only): z from onboard signals with a kinematic model.

    v_x ~ (v_fl + v_fr + v_rl + v_rr) / 4,   a_y = a_y^osd - b_ay,   omega_z = omega^osd - b_omega

with ``b_ay`` and ``b_omega`` the standstill biases of the lateral-acceleration and yaw-rate
sensors: the mean of each over the samples where the car stands still (every wheel speed
below :data:`STANDSTILL_SPEED_MPS`). The baseline cannot estimate v_y and a_x (the paper's
Table 1 dashes); they are NaN here.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from prml2_edge import schema
from prml2_edge.schema import Z

STANDSTILL_SPEED_MPS = 0.05  # every wheel slower than this counts as standing still
MIN_STANDSTILL_SAMPLES = 25  # 0.5 s at 50 Hz: fewer give no usable bias estimate

_WHEELS = [schema.SIGNAL_BY_NAME[n].index for n in schema.WHEEL_SPEED_NAMES]
_YAW = schema.SIGNAL_BY_NAME["yaw_rate_radps"].index
_LAT = schema.SIGNAL_BY_NAME["lat_accel_mps2"].index


@dataclass(frozen=True)
class StandstillBias:
    """Sensor biases measured at standstill: ``lat_accel_mps2`` [m/s^2], ``yaw_rate_radps`` [rad/s]."""

    lat_accel_mps2: float = 0.0
    yaw_rate_radps: float = 0.0
    n_samples: int = 0  # standstill samples they were estimated from (0: none, biases are 0)
    # where those samples were, for a filter that stood through them (evaluation.standstill_restore): per standstill
    # episode (seconds from its last sample to the end of the segment measured, samples, mean yaw rate [rad/s]),
    # oldest first; empty when the biases come from the whole drive (samples after the window too)
    episodes: tuple[tuple[float, int, float], ...] = ()
    yaw_resolution_radps: float = 0.0  # the yaw rate's step over the segment, as the runtime measures it (0: none)


def standstill_mask(onboard: np.ndarray) -> np.ndarray:
    """(N,) bool: every wheel speed below :data:`STANDSTILL_SPEED_MPS`; ``onboard`` (N, 9) SI."""
    onboard = np.asarray(onboard, dtype=np.float64)
    return np.all(np.abs(onboard[:, _WHEELS]) < STANDSTILL_SPEED_MPS, axis=1)


def standstill_episodes(still: np.ndarray, yaw: np.ndarray) -> tuple[tuple[float, int, float], ...]:
    """``(seconds from the episode's last sample to the end of still, samples, mean of yaw over them)`` per run of
    True in ``still`` (N,) bool, oldest first; ``yaw`` (N,)."""
    edges = np.flatnonzero(np.diff(np.concatenate(([0], np.asarray(still, dtype=np.int8), [0]))))
    n = len(still)
    return tuple((float((n - end) * schema.DT_S), int(end - start), float(np.mean(yaw[start:end])))
                 for start, end in zip(edges[::2], edges[1::2], strict=True))


def yaw_resolution(yaw: np.ndarray) -> float:
    """The yaw rate's resolution [rad/s] as the runtime's filter measures it: the 10th percentile of the steps
    between successive distinct readings (0 when the signal never changes)."""
    steps = np.abs(np.diff(np.asarray(yaw, dtype=np.float64)))
    steps = steps[steps > 0.0]
    return float(np.percentile(steps, 10)) if len(steps) else 0.0


def standstill_bias(onboard: np.ndarray, min_samples: int = MIN_STANDSTILL_SAMPLES) -> StandstillBias:
    """Standstill biases from the standstill samples of ``onboard`` (N, 9) SI; zeros if too few."""
    onboard = np.asarray(onboard, dtype=np.float64)
    still = standstill_mask(onboard)
    n = int(still.sum())
    if n < min_samples:
        return StandstillBias(n_samples=n)
    return StandstillBias(float(onboard[still, _LAT].mean()), float(onboard[still, _YAW].mean()), n,
                          standstill_episodes(still, onboard[:, _YAW]), yaw_resolution(onboard[:, _YAW]))


def osd_baseline_z(onboard: np.ndarray, bias: StandstillBias | None = None) -> np.ndarray:
    """Baseline z (N, 5) [SI, schema z order] from ``onboard`` (N, 9) [SI]; v_y and a_x are NaN."""
    onboard = np.asarray(onboard, dtype=np.float64)
    if onboard.ndim != 2 or onboard.shape[1] != schema.NUM_SIGNALS:
        raise ValueError(f"onboard must be (N, {schema.NUM_SIGNALS}), got {onboard.shape}")
    bias = bias or StandstillBias()
    z = np.full((len(onboard), schema.NUM_STATES), np.nan)
    z[:, Z.V_X] = onboard[:, _WHEELS].mean(axis=1)
    z[:, Z.A_Y] = onboard[:, _LAT] - bias.lat_accel_mps2
    z[:, Z.OMEGA_Z] = onboard[:, _YAW] - bias.yaw_rate_radps
    return z


def drive_bias(onboard_segment: np.ndarray, onboard_full: np.ndarray | None = None,
               fallback: StandstillBias | None = None) -> StandstillBias:
    """Bias for a drive segment: from the segment's standstill, else the whole drive's, else ``fallback``."""
    bias = standstill_bias(onboard_segment)
    if bias.n_samples >= MIN_STANDSTILL_SAMPLES:
        return bias
    if onboard_full is not None:
        full = standstill_bias(onboard_full)
        if full.n_samples >= MIN_STANDSTILL_SAMPLES:
            return replace(full, episodes=())  # samples after the segment too: no filter stood through them
    return fallback or StandstillBias()
