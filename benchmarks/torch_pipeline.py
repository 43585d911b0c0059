"""The reference for the runtime: the same per-step work as a plain PyTorch eager pipeline.

Decode and 50 Hz assembly are the runtime's own stages (cantools; there is no torch version of
them), then per step: the same sliding window (zero-copy into a tensor), the torch model in
eager mode under ``inference_mode``, the torch physics guard, and one predict + update of the
torch EKF (float64, batch of one) with the newest decoder output — what
:class:`~prml2_edge.runtime.localizer.StreamingLocalizer` does with onnxruntime and NumPy.
"""

from __future__ import annotations

import inspect
import time
from dataclasses import dataclass

import numpy as np
import torch

from prml2_edge import schema
from prml2_edge.can.signal_map import load_map_and_dbc, resolve_map
from prml2_edge.runtime.assembler import Assembler
from prml2_edge.runtime.decode import FrameDecoder
from prml2_edge.runtime.initial_pose import InitialPose, initial_state
from prml2_edge.runtime.latency import LatencyRecorder
from prml2_edge.runtime.pipeline import Pipeline
from prml2_edge.runtime.stats import FrameStats
from prml2_edge.runtime.window import Window
from prml2_edge.training import ekf_torch
from prml2_edge.training.guard_torch import PhysicsGuard
from prml2_edge.training.model import Prml2Model


@dataclass
class TorchStep:
    """What the torch localiser returns per step (what the pipeline keeps as ``last``)."""

    t_s: float
    x: np.ndarray
    inferred: bool
    bus_silent: bool = False
    # what the pipeline reads off a step (runtime/pipeline.py ``_row``): it records the stage times itself
    infer_ns: int = 0
    guard_ns: int = 0
    filter_ns: int = 0
    degraded: bool = False
    reasons: dict | None = None
    substituted: np.ndarray | None = None


class TorchEagerLocalizer:
    """Window -> torch model -> torch guard -> torch EKF, one 50 Hz row per :meth:`step` (stride 1)."""

    def __init__(self, model: Prml2Model, initial_pose: InitialPose, latency: LatencyRecorder, mu: float = 1.0,
                 dtype: torch.dtype = torch.float32) -> None:
        self.model = model.eval()
        self.dtype = dtype
        self.guard = PhysicsGuard(mu)
        self.window = Window(model.cfg.window_len)
        self.latency = latency
        self.initial_pose = initial_pose
        self.Q = ekf_torch.default_process_noise(schema.DT_S, dtype=torch.float64)
        self.x: torch.Tensor | None = None
        self.P: torch.Tensor | None = None

    def close(self) -> None:
        """Nothing to release (the runtime localiser's interface)."""

    def step(self, values: np.ndarray, valid: np.ndarray, t_s: float, gnss=None,
             discontinuity: bool = False, bus_silent: bool = False, substituted=None,
             substitute_std=None) -> TorchStep:
        """The runtime localiser's call (``StreamingLocalizer.step``); GNSS and substituted cues are not used."""
        all_valid = bool(np.all(valid))
        self.window.step(values, all_valid)
        z = z_var = None
        inferred = False
        infer_ns = guard_ns = 0
        if self.window.full:
            t0 = time.perf_counter_ns()
            with torch.inference_mode():
                onboard = torch.from_numpy(self.window.view())
                # rows=1: the newest decoder step only, the same work as the runtime's streaming graph
                if self.dtype is torch.float32:
                    mean, var = self.model(onboard, rows=1)
                else:
                    with torch.autocast("cpu", dtype=self.dtype):
                        mean, var = self.model(onboard, rows=1)
                    mean, var = mean.float(), var.float()
            t1 = time.perf_counter_ns()
            with torch.inference_mode():
                mean, var = self.guard(mean, var)  # (1, 1, 5): the newest step, as the runtime guards it
                z, z_var = mean[:, -1].double(), var[:, -1].double()  # (1, 5)
            infer_ns, guard_ns = t1 - t0, time.perf_counter_ns() - t1
            inferred = True
        t_filter = time.perf_counter_ns()
        with torch.inference_mode():
            if self.x is None:
                x0, p0 = initial_state(self.initial_pose, values, valid)
                self.x = torch.as_tensor(x0)[None]
                self.P = torch.as_tensor(p0)[None]
            else:
                self.x, self.P = ekf_torch.predict(self.x, self.P, self.Q, schema.DT_S)
                if z is not None and all_valid:
                    self.x, self.P = ekf_torch.update(self.x, self.P, z, z_var)
            x = self.x[0].numpy().copy()
        return TorchStep(t_s, x, inferred, bus_silent, infer_ns, guard_ns, time.perf_counter_ns() - t_filter)


def torch_pipeline(model: Prml2Model, initial_pose: InitialPose, signal_map: str = "prml2_onboard",
                   dtype: torch.dtype = torch.float32) -> Pipeline:
    """A :class:`Pipeline` with the runtime's decoder and assembler and the torch-eager localiser."""
    smap, db, dbc_path = load_map_and_dbc(resolve_map(signal_map), None)
    stats = FrameStats()
    latency = LatencyRecorder()
    decoder = FrameDecoder(smap, db)
    stale = inspect.signature(Pipeline.build).parameters["stale_periods"].default  # the runtime's default
    assembler = Assembler.for_map(smap, stale_periods=stale)
    localizer = TorchEagerLocalizer(model, initial_pose, latency, dtype=dtype)
    return Pipeline(smap, decoder, assembler, localizer, (), stats, latency, dbc_path)
