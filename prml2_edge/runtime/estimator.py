"""Estimator stage: window -> model -> physics guard -> the dynamic state z for this step.

method.md "Streaming inference": a new window every ``stride`` 50 Hz steps; each window's
decoder outputs cover its last L - H steps; at every step the filter consumes the newest
available output for that step (with stride 1: the last decoder output of the newest window),
after the physics guard. While no valid output is available (the first L - 1 steps, a failed
inference, a window with too many invalid rows, an invalid current row) it gives none.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from prml2_edge import schema
from prml2_edge.guard import GuardStats, physics_guard_row
from prml2_edge.runtime.status import InferenceStatus
from prml2_edge.runtime.window import Window


class Model(Protocol):
    """What the estimator needs from a model (:class:`prml2_edge.runtime.inference.OnnxModel`)."""

    window_len: int
    mean: np.ndarray  # (R, 5) after a successful step, the newest R decoder steps; the last row is used
    var: np.ndarray  # (R, 5)

    def step(self, window: np.ndarray) -> InferenceStatus: ...


@dataclass(frozen=True)
class Estimate:
    """The estimator's result for one step: the guarded z (5,) and its variances, or none."""

    inferred: bool  # a window was run through the model at this step
    z: np.ndarray | None = None
    z_var: np.ndarray | None = None
    guard_fired: bool = False
    infer_ns: int = 0  # time spent in the model and in the guard at this step (the pipeline records them)
    guard_ns: int = 0


class Estimator:
    """Window, inference when due, physics guard; :meth:`step` once per 50 Hz row."""

    def __init__(self, model: Model, stride: int, max_invalid_fraction: float, a_max_mps2: float) -> None:
        self.model = model
        self.stride = int(stride)
        self.max_invalid_fraction = float(max_invalid_fraction)
        self.a_max_mps2 = float(a_max_mps2)
        self.guard_stats = GuardStats()
        self.window = Window(model.window_len)
        # the newest window's newest decoder output, guarded: the only one ever consumed (see step)
        self._z_mean = np.zeros(schema.NUM_STATES)
        self._z_var = np.ones(schema.NUM_STATES)
        self._fired = False
        self.reset()

    def reset(self) -> None:
        """Back to the state before the first row: window, inference schedule and guard statistics."""
        self.window.clear()
        self.guard_stats.reset()
        self._inf_count = -1  # window.count at the last inference; -1: none yet
        self._output_ok = False
        self.n_inferences = 0
        self.n_inference_failures = 0

    def _infer(self) -> tuple[int, int]:
        """Run the model on the window; ``(infer_ns, guard_ns)``."""
        t0 = time.perf_counter_ns()
        status = self.model.step(self.window.view())
        t1 = time.perf_counter_ns()
        self._inf_count = self.window.count
        self._accept(status, self.model.mean[-1], self.model.var[-1], self.window.invalid_fraction)
        return t1 - t0, time.perf_counter_ns() - t1

    def _accept(self, status: InferenceStatus, mean: np.ndarray | None, var: np.ndarray | None,
                invalid_fraction: float) -> None:
        """Count one inference and make its newest decoder row (``mean``, ``var`` (5,)) the held output."""
        self.n_inferences += 1
        if status is not InferenceStatus.SUCCESS:
            self._output_ok = False
            self.n_inference_failures += 1
        else:
            # Only the newest decoder step is ever consumed (held until the next window), so only it is
            # guarded and counted: the guard statistics are over used predictions.
            self._z_mean, self._z_var, self._fired = physics_guard_row(mean, var, self.a_max_mps2)
            self.guard_stats.add(self._fired)
            self._output_ok = invalid_fraction <= self.max_invalid_fraction

    def _break(self) -> None:
        """A discontinuity: the window and the held output belong before it."""
        self.window.clear()
        self._inf_count = -1
        self._output_ok = False

    def _due(self) -> bool:
        """The window is full and ``stride`` rows have passed since the last inference (:meth:`schedule`)."""
        return self.window.full and (self._inf_count < 0 or self.window.count - self._inf_count >= self.stride)

    def close(self) -> None:
        """Nothing to release (the asynchronous estimator stops its worker thread)."""

    @staticmethod
    def schedule(discontinuity, window_len: int, stride: int, state: list[int] | None = None,
                 offset: int = 0) -> np.ndarray:
        """Row indices at which :meth:`step` runs the model, for rows with these ``discontinuity`` flags.

        The inference rule of :meth:`step` (the window is full, and ``stride`` rows have passed since the
        last inference, counted from the last discontinuity) depends on nothing else, so an offline run can
        compute every window before its rows are filtered (:mod:`prml2_edge.runtime.offline`). The window of
        row ``i`` is rows ``i - window_len + 1 .. i``, all after the last discontinuity. For a stream in
        pieces pass the same ``state`` list (rows since the last discontinuity, that count at the last
        inference) each time and the index of the piece's first row as ``offset``.
        """
        if state is None:
            state = [0, -1]
        count, inf_count = state
        out = []
        for i, disc in enumerate(np.asarray(discontinuity, dtype=bool).tolist()):
            if disc:
                count, inf_count = 0, -1
            count += 1
            if count >= window_len and (inf_count < 0 or count - inf_count >= stride):
                out.append(offset + i)
                inf_count = count
        state[:] = [count, inf_count]
        return np.asarray(out, dtype=np.int64)

    def step(self, values: np.ndarray, all_valid: bool, discontinuity: bool = False) -> Estimate:
        """One row ``values`` (9,) into the window; the z to use at this step, if any."""
        if discontinuity:
            self._break()
        self.window.step(values, all_valid)
        inferred = False
        infer_ns = guard_ns = 0
        if self._due():
            infer_ns, guard_ns = self._infer()
            inferred = True
        if self._output_ok and all_valid and self._inf_count >= 0:
            # Causal streaming: between windows (stride > 1) the newest window's newest output, the estimate
            # for step k - offset, is held; older decoder rows describe older steps and are never used.
            if self.window.count - self._inf_count < self.stride:
                return Estimate(inferred, self._z_mean, self._z_var, self._fired, infer_ns, guard_ns)
        return Estimate(inferred, infer_ns=infer_ns, guard_ns=guard_ns)

    def summary(self) -> dict:
        g = self.guard_stats
        return {"inferences": self.n_inferences, "inference_failures": self.n_inference_failures,
                "guard": {"predictions": g.n_predictions, "fired": g.n_fired, "fire_rate": g.fire_rate}}
