"""Simulated drives with their lateral acceleration and steering-wheel angle less the car's own offsets (issue 26).

A model trained on such drives (``ModelConfig.cue_debiased_inputs``) never has to tell the accelerometer's and the
steering's offsets from the yaw rate they bias; the runtime feeds it each CAN row less the offsets its cue estimator
has learned (``runtime.cue_offset.CueOffset.debiased``). That estimator knows them to about 0.015 m/s² and 0.2°
once the car's earlier drives or a few minutes of this one taught it (docs/ablation.md), so each drive here keeps a
residual of that size, drawn once per drive: the model learns to live with what the runtime leaves.

The offsets are the simulator's own (``meta["sensor_errors"]``); a recorded drive has none, and asking for it there
is an error, not a silent pass-through.
"""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np

from prml2_edge import schema
from prml2_edge.errors import ConfigError

_AY = schema.SIGNAL_BY_NAME["lat_accel_mps2"].index
_STEER = schema.SIGNAL_BY_NAME["steering_wheel_angle_rad"].index
# one sigma of what the runtime's cue estimator leaves of each offset (docs/ablation.md, "the model reading a_y and
# steering less their learned offsets"): a_y [m/s^2], steering-wheel angle [rad]
AY_RESIDUAL_STD_MPS2 = 0.02
STEER_RESIDUAL_STD_RAD = 0.25 * schema.DEG_TO_RAD


def drive_offsets(drive) -> tuple[float, float]:
    """``(a_y offset [m/s^2], steering-wheel offset [rad])`` the simulator gave ``drive``; ConfigError without them."""
    errors = (drive.meta or {}).get("sensor_errors") or {}
    try:
        return float(errors["lat_offset_mps2"]), float(errors["steer_offset_rad"])
    except KeyError:
        raise ConfigError(f"{drive.name}: no simulated a_y and steering offsets (meta 'sensor_errors'); a model "
                          "with cue-debiased inputs trains and is measured on simulated drives only") from None


def debiased_drive(drive, rng: np.random.Generator | None = None):
    """A copy of ``drive`` whose a_y and steering-wheel angle are less its offsets, less a residual drawn from
    ``rng`` (None: the exact offsets)."""
    ay, steer = drive_offsets(drive)
    if rng is not None:
        ay += float(rng.normal(0.0, AY_RESIDUAL_STD_MPS2))
        steer += float(rng.normal(0.0, STEER_RESIDUAL_STD_RAD))
    onboard = np.array(drive.onboard, copy=True)
    onboard[:, _AY] -= ay
    onboard[:, _STEER] -= steer
    return replace(drive, onboard=onboard, meta=copy.deepcopy(drive.meta))


def debiased_dataset(dataset, seed: int | None = 0):
    """``dataset`` (``data.datasets.Dataset``) with every drive debiased, each with its own residual from ``seed``
    (None: exact); splits are built afresh from the new drives."""
    drives = [debiased_drive(d, None if seed is None else np.random.default_rng([seed, 26, k]))
              for k, d in enumerate(dataset.drives)]
    return replace(dataset, drives=drives, _splits={})
