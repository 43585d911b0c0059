"""Planar EKF for the edge runtime and evaluation (NumPy, float64; never imports torch).

The torch twin used in training is :mod:`prml2_edge.training.ekf_torch`.
"""

from prml2_edge.ekf.numpy_ekf import (
    Ekf,
    InitialStd,
    ProcessNoise,
    StepStatus,
    default_initial_covariance,
    default_process_noise,
    measurement_matrix,
    predict,
    process_jacobian,
    process_model,
    update,
    update_pose,
    wrap_angle,
)

__all__ = [
    "Ekf",
    "InitialStd",
    "ProcessNoise",
    "StepStatus",
    "default_initial_covariance",
    "default_process_noise",
    "measurement_matrix",
    "predict",
    "process_jacobian",
    "process_model",
    "update",
    "update_pose",
    "wrap_angle",
]
