"""What the calibrated filter starts a benchmark window from: the standstill's yaw-rate offset and how well it is
known.

The OSD baseline subtracts the standstill bias of the drive before the window (else of the whole drive); the
calibrated filter starts from the same offset. How well it knows it depends on where the standstill was:

* ``"runtime"``: the standstill came before the window, in the same drive. The runtime's filter would have stood
  through it (every wheel at 0: :meth:`~prml2_edge.ekf.numpy_ekf.Ekf.update_standstill` beside the CAN yaw-rate cue),
  so it knows the offset as that update leaves it, widened by the offset's random walk since
  (:func:`standstill_offset`: a scalar Kalman filter over the standstill episodes with the runtime's own settings).
* ``"file"`` (and always when the standstill is only after the window): the car's calibration file holds it from an
  earlier drive, floored at :data:`~prml2_edge.runtime.calibration.RESTORE_STD_FLOOR` (offsets drift between drives).
"""

from __future__ import annotations

import math

import numpy as np

from prml2_edge import schema
from prml2_edge.evaluation.osd import MIN_STANDSTILL_SAMPLES, StandstillBias

STANDSTILL_RESTORES = ("runtime", "file")


def standstill_offset(bias: StandstillBias, cfg) -> tuple[float, float] | None:
    """``(offset [rad/s], variance [rad^2/s^2])``: the CAN yaw-rate offset a runtime with ``cfg`` (a
    :class:`~prml2_edge.runtime.localizer_config.LocalizerConfig`) would hold at the end of the segment ``bias`` was
    measured on, having stood through its standstill episodes from the offset's prior; None when ``bias`` has no
    episodes (measured on the whole drive, or no standstill).

    Each standstill row after ``standstill_hold_s`` measures the offset with variance ``yaw cue variance +
    standstill yaw variance`` (the cue's at the segment's measured resolution, as the runtime's); between and after
    the episodes the offset's random walk (``cal_yaw_offset_psd``) widens it, so a recent stop weighs more than an
    old one (the OSD baseline's mean weighs them alike)."""
    from prml2_edge.runtime.filter import yaw_cue_var

    if not bias.episodes or bias.n_samples < MIN_STANDSTILL_SAMPLES:
        return None
    resolution = bias.yaw_resolution_radps or cfg.yaw_cue_resolution_radps
    r = yaw_cue_var(cfg, resolution) + cfg.standstill_yaw_std_radps ** 2
    hold = int(math.ceil(cfg.standstill_hold_s / schema.DT_S - 1e-9))
    mean, var, t = 0.0, cfg.cal_yaw_offset_prior_std_radps ** 2, None
    for age_s, n, yaw_mean in bias.episodes:
        start = -age_s - n * schema.DT_S
        var += cfg.cal_yaw_offset_psd * ((-age_s - start) + (start - t if t is not None else 0.0))
        info = max(n - hold, 0) / r
        mean = (mean / var + info * yaw_mean) / (1.0 / var + info)
        var = 1.0 / (1.0 / var + info)
        t = -age_s
    return mean, var + cfg.cal_yaw_offset_psd * (0.0 - t)


def restore_standstill_calibration(loc, bias: StandstillBias, wheel_scale: tuple[float, float] | None = None,
                                   how: str = "file") -> bool:
    """Start the calibrated filter ``loc`` from the yaw-rate offset the OSD baseline uses, when it has one, and from
    the wheel scale the car's earlier drives taught (``wheel_scale``: (scale, variance)), when it has one.

    The offset: ``how`` (module docstring), ``"runtime"`` as the runtime's own standstill update leaves it when the
    standstill came before the window, else the baseline's mean with the calibration file's restore floor. The wheel
    scale with at least the file's floor; what it does not know (and the model bias) from the priors. True when
    anything was restored.
    """
    from prml2_edge.runtime.calibration import RESTORE_STD_FLOOR

    if how not in STANDSTILL_RESTORES:
        raise ValueError(f"standstill restore must be one of {STANDSTILL_RESTORES}, got {how!r}")
    offset = bias.n_samples >= MIN_STANDSTILL_SAMPLES
    if not offset and wheel_scale is None:
        return False
    cfg = loc.config
    k, k_std = (wheel_scale[0], max(math.sqrt(wheel_scale[1]), RESTORE_STD_FLOOR[1])) if wheel_scale is not None \
        else (0.0, cfg.cal_wheel_scale_prior_std)
    b, b_std = 0.0, cfg.cal_yaw_offset_prior_std_radps
    if offset:
        stood = standstill_offset(bias, cfg) if how == "runtime" else None
        b, b_std = (stood[0], math.sqrt(stood[1])) if stood is not None else (bias.yaw_rate_radps,
                                                                               RESTORE_STD_FLOOR[0])
    std = np.array([b_std, k_std, cfg.cal_model_bias_std_radps])
    loc.restore_calibration(np.array([b, k, 0.0]), np.diag(std**2))
    return True
