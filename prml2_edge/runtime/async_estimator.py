"""The estimator with the model on a worker thread: the 50 Hz step never waits for an inference.

At stride k the model has k steps (k * 20 ms) between windows, but :class:`~prml2_edge.runtime.estimator.Estimator`
runs it inside the step that is due, so that step takes as long as the model (the paper-size model: ~35 ms on a CPU
core, past the 20 ms step). Here the due step hands a copy of the window to one worker thread (onnxruntime releases
the GIL while it runs) and returns at once; each later step checks whether the result is in, guards it, and from
then on gives it to the filter, which meanwhile carries on with the raw cues and the previous output. The cost: an
output is consumed one or more steps after its window ended (``summary()['async']`` gives the lag in steps).

Rules, so that nothing is lost or used out of place:

* at most one window in flight; a window that falls due while one is in flight waits for it (the stride counts from
  the window actually sent);
* an output is used from the step it arrives until ``2 * stride`` steps later (the next one is due ``stride`` steps
  after its window was sent; one more stride is the grace for a slow inference), never after;
* a discontinuity or :meth:`reset` forgets the window in flight: its output, when it comes, is dropped;
* a failed inference counts as one, as in the synchronous estimator.

Opt-in (``[model] async_inference``, ``--async-inference``); the evaluation and the offline replay stay synchronous
(their schedule is :meth:`Estimator.schedule`).
"""

from __future__ import annotations

import time
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from prml2_edge.runtime.estimator import Estimate, Estimator, Model
from prml2_edge.runtime.status import InferenceStatus


class AsyncEstimator(Estimator):
    """:class:`Estimator` whose inference runs on one worker thread (module docstring)."""

    def __init__(self, model: Model, stride: int, max_invalid_fraction: float, a_max_mps2: float) -> None:
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="prml2-infer")
        self._future: Future | None = None
        super().__init__(model, stride, max_invalid_fraction, a_max_mps2)

    def reset(self) -> None:
        super().reset()
        self._future = None  # a window in flight is forgotten; its result is dropped when it comes
        self._arrived = -1  # window.count when the output in use arrived; -1: none
        # steps from a consumed output's window end to its first use: count, sum, min, max (bounded on a long drive)
        self._lag = [0, 0, 0, 0]

    def _run(self, window: np.ndarray, invalid_fraction: float) -> tuple[InferenceStatus, np.ndarray, np.ndarray,
                                                                         float, int]:
        """Worker thread: the model on ``window``; ``(status, mean row, var row, invalid fraction, infer_ns)``."""
        t0 = time.perf_counter_ns()
        status = self.model.step(window)
        infer_ns = time.perf_counter_ns() - t0
        if status is not InferenceStatus.SUCCESS:
            return status, None, None, invalid_fraction, infer_ns
        return status, self.model.mean[-1].copy(), self.model.var[-1].copy(), invalid_fraction, infer_ns

    def _collect(self) -> tuple[bool, int, int]:
        """Take the finished inference, if any: ``(arrived, infer_ns, guard_ns)``."""
        fut = self._future
        if fut is None or not fut.done():
            return False, 0, 0
        self._future = None
        status, mean, var, invalid_fraction, infer_ns = fut.result()
        t0 = time.perf_counter_ns()
        self._accept(status, mean, var, invalid_fraction)
        if status is InferenceStatus.SUCCESS:
            self._arrived = self.window.count
            lag = self.window.count - self._inf_count
            n, total, low, high = self._lag
            self._lag = [n + 1, total + lag, lag if n == 0 else min(low, lag), max(high, lag)]
        return True, infer_ns, time.perf_counter_ns() - t0

    def step(self, values: np.ndarray, all_valid: bool, discontinuity: bool = False) -> Estimate:
        """One row into the window; sends a due window to the worker; the newest arrived output, if any."""
        if discontinuity:
            self._break()
            self._future = None
            self._arrived = -1
        self.window.step(values, all_valid)
        arrived, infer_ns, guard_ns = self._collect()
        if self._future is None and self._due():
            self._inf_count = self.window.count
            self._future = self._pool.submit(self._run, self.window.view().copy(), self.window.invalid_fraction)
        fresh = 0 <= self._arrived and self.window.count - self._arrived < 2 * self.stride
        if self._output_ok and all_valid and fresh:
            return Estimate(arrived, self._z_mean, self._z_var, self._fired, infer_ns, guard_ns)
        return Estimate(arrived, infer_ns=infer_ns, guard_ns=guard_ns)

    def close(self) -> None:
        """Stop the worker thread (after the window in flight)."""
        self._pool.shutdown(wait=True)

    def summary(self) -> dict:
        n, total, low, high = self._lag
        lag = {"lag_steps_mean": total / n, "lag_steps_min": low, "lag_steps_max": high} if n else \
            {"lag_steps_mean": None, "lag_steps_min": None, "lag_steps_max": None}
        return {**super().summary(), "async": lag}
