"""The cue axle's speed for the filter's wheel cue (runtime/filter.py): the axle that does not drive."""

from __future__ import annotations

import math

import numpy as np

from prml2_edge import schema

_SIG = schema.SIGNAL_BY_NAME
_RL, _RR = _SIG["wheel_speed_rl_mps"].index, _SIG["wheel_speed_rr_mps"].index
_FL, _FR = _SIG["wheel_speed_fl_mps"].index, _SIG["wheel_speed_fr_mps"].index
_STEER = _SIG["steering_wheel_angle_rad"].index


def rear_speed(values: np.ndarray, valid: np.ndarray) -> float | None:
    """Mean rear-axle wheel speed [m/s] (``np.mean`` of the two: their sum over 2), None unless both are valid.
    On Python floats: the filter asks for it twice a step, and NumPy's call cost on 2 elements dominated."""
    if not (valid[_RL] and valid[_RR]):
        return None
    return (float(values[_RL]) + float(values[_RR])) / 2


def front_speed(values: np.ndarray, valid: np.ndarray, steering_ratio: float) -> float | None:
    """Mean front-axle wheel speed as v_x [m/s], None unless both wheels and the steering angle are valid. The
    steered wheels roll along their own heading, v_x / cos(delta) on a kinematic single track, so the mean is
    multiplied by cos(delta), delta = steering wheel angle / ``steering_ratio``."""
    if not (valid[_FL] and valid[_FR] and valid[_STEER]):
        return None
    return (float(values[_FL]) + float(values[_FR])) / 2 * math.cos(float(values[_STEER]) / steering_ratio)
