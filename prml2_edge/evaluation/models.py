"""Runtime models for evaluation: the OSD baseline and the ablation/recording wrappers.

All implement the localiser's :class:`prml2_edge.runtime.localizer.Model` protocol, so every
method is scored through the same streaming path (window -> model -> guard -> NumPy EKF).
"""

from __future__ import annotations

import numpy as np

from prml2_edge import schema
from prml2_edge.evaluation.osd import StandstillBias, osd_baseline_z
from prml2_edge.runtime.status import InferenceStatus
from prml2_edge.schema import Z

# The OSD baseline cannot estimate v_y and a_x (paper Table 1 dashes). Its kinematic model (no side
# slip) feeds the EKF v_y = 0 with the tuned variance; a_x is reported as 0 with this variance, i.e. no
# information for the EKF [m^2/s^4].
UNOBSERVED_VAR = 1e6
OSD_MISSING = (Z.V_Y, Z.A_X)


class OsdModel:
    """OSD-Baseline (paper Eq. obd) as a streaming model: z from the newest rows of the window.

    Parameters
    ----------
    var:
        (5,) constant measurement variances [SI squared] (tuned on the validation split);
        v_y is the kinematic model's 0 with ``var[V_Y]``; the a_x entry is ignored (:data:`UNOBSERVED_VAR`).
    bias:
        Standstill biases of the lateral-acceleration and yaw-rate sensors.
    """

    def __init__(self, var: np.ndarray, bias: StandstillBias | None = None,
                 window_len: int = schema.WINDOW_LEN, decoder_len: int = schema.DECODER_LEN) -> None:
        self.window_len = int(window_len)
        self.decoder_len = int(decoder_len)
        self.bias = bias or StandstillBias()
        self._var = np.asarray(var, dtype=np.float64).copy()
        self._var[Z.A_X] = UNOBSERVED_VAR
        self.mean = np.zeros((self.decoder_len, schema.NUM_STATES))
        self.var = np.ones((self.decoder_len, schema.NUM_STATES))

    def step(self, window: np.ndarray) -> InferenceStatus:
        """``window`` (1, L, 9) float32 [SI]: fills :attr:`mean`/:attr:`var` (L - H, 5)."""
        z = osd_baseline_z(np.asarray(window[0, -self.decoder_len:], dtype=np.float64), self.bias)
        if not np.isfinite(np.delete(z, OSD_MISSING, axis=1)).all():
            return InferenceStatus.INVALID_OUTPUT
        self.mean[:] = np.nan_to_num(z, nan=0.0)
        self.var[:] = self._var
        return InferenceStatus.SUCCESS


class ConstantVarianceModel:
    """Ablation "uncertainty off": the inner model's means with constant variances ``var`` (5,) [SI^2]."""

    def __init__(self, inner, var: np.ndarray) -> None:
        self.inner = inner
        self.window_len = inner.window_len
        self.decoder_len = inner.decoder_len
        self.metadata = getattr(inner, "metadata", None)
        self._var = np.asarray(var, dtype=np.float64)
        if self._var.shape != (schema.NUM_STATES,) or not (self._var > 0).all():
            raise ValueError(f"var must be (5,) and positive, got {self._var}")
        self.var = np.ones((len(inner.mean), schema.NUM_STATES))  # as many rows as the inner model returns

    @property
    def mean(self) -> np.ndarray:
        return self.inner.mean

    def step(self, window: np.ndarray) -> InferenceStatus:
        status = self.inner.step(window)
        self.var[:] = self._var
        return status


class RecordingModel:
    """Wraps a model and keeps the newest decoder output (last row) of every successful call.

    ``records`` lists ``(call_index, mean (5,), var (5,))`` before the physics guard; with
    stride 1 call ``i`` of a run whose rows are all valid is the window ending at row ``L - 1 + i``.
    """

    def __init__(self, inner) -> None:
        self.inner = inner
        self.window_len = inner.window_len
        self.decoder_len = inner.decoder_len
        self.metadata = getattr(inner, "metadata", None)
        self.calls = 0
        self.records: list[tuple[int, np.ndarray, np.ndarray]] = []

    @property
    def mean(self) -> np.ndarray:
        return self.inner.mean

    @property
    def var(self) -> np.ndarray:
        return self.inner.var

    def clear(self) -> None:
        self.calls = 0
        self.records.clear()

    def step(self, window: np.ndarray) -> InferenceStatus:
        status = self.inner.step(window)
        if status is InferenceStatus.SUCCESS:
            self.records.append((self.calls, self.inner.mean[-1].copy(), self.inner.var[-1].copy()))
        self.calls += 1
        return status


class ReplayModel:
    """Gives back the outputs a :class:`RecordingModel` recorded, call by call: the model's z never depends on the
    filter, so filter variants of one window can share one run of the model (``benchmarks/filter_ablation.py``).
    A call that was not recorded (the model failed, or a row was invalid) is an invalid output again."""

    def __init__(self, records: list[tuple[int, np.ndarray, np.ndarray]], metadata=None,
                 window_len: int = schema.WINDOW_LEN, decoder_len: int = schema.DECODER_LEN) -> None:
        self.window_len, self.decoder_len, self.metadata = int(window_len), int(decoder_len), metadata
        self._records = {int(c): (m, v) for c, m, v in records}
        self.calls = 0
        self.mean = np.zeros((1, schema.NUM_STATES))
        self.var = np.ones((1, schema.NUM_STATES))

    def step(self, window: np.ndarray) -> InferenceStatus:
        rec = self._records.get(self.calls)
        self.calls += 1
        if rec is None:
            return InferenceStatus.INVALID_OUTPUT
        self.mean[0], self.var[0] = rec
        return InferenceStatus.SUCCESS
