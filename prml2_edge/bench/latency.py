"""End-to-end latency per 50 Hz step of the real runtime :class:`~prml2_edge.runtime.pipeline.Pipeline`.

Each CAN frame goes through :meth:`Pipeline.step` exactly as a live bus delivers it (decode ->
assemble -> window -> ONNX inference -> physics guard -> EKF -> sinks); the pipeline's own
:class:`~prml2_edge.runtime.latency.LatencyRecorder` times every 50 Hz row from the moment
the frame that completed it was received to the moment the sinks had the result
(``end_to_end``) and the ONNX call alone (``infer``). Only rows with an inference count (at the
runtime's default stride 5, every fifth row once the window is full: the worst steps);
``overhead = end_to_end - infer`` per row is everything outside the model. The first ``warmup_steps``
such rows are not counted.
"""

from __future__ import annotations

import gc
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import can
import numpy as np

from prml2_edge.config import DEFAULT_STRIDE
from prml2_edge.runtime.initial_pose import InitialPose
from prml2_edge.runtime.pipeline import Pipeline

QUANTILES = (50, 95, 99)
# every stage outside the model, in pipeline order; decode and assemble run per frame, the others per row
OUTSIDE_STAGES = ("decode", "assemble", "plausibility", "guard", "filter", "sinks")
OUTSIDE_TARGET_MS = {"p50": 0.25, "p99": 0.5}  # issue 29: everything per 50 Hz step outside the model


def summarize(ms: np.ndarray) -> dict:
    """``{"p50", "p95", "p99", "max", "mean", "count"}`` of durations [ms] (NaN-free; empty -> count 0)."""
    ms = np.asarray(ms, dtype=np.float64)
    if ms.size == 0:
        return {"count": 0}
    p = np.percentile(ms, QUANTILES)
    out = {f"p{q}": float(v) for q, v in zip(QUANTILES, p, strict=True)}
    out.update(max=float(ms.max()), mean=float(ms.mean()), count=int(ms.size))
    return out


@dataclass
class StepSamples:
    """Per 50 Hz row with an inference: end-to-end, model-only and overhead durations [ms]."""

    e2e_ms: list[float] = field(default_factory=list)
    model_ms: list[float] = field(default_factory=list)
    # CPU time per row outside the model: decode + assemble of every frame since the previous row, plus the
    # row's plausibility, guard, filter and sinks [ms]; per stage in outside_stage_ms
    outside_ms: list[float] = field(default_factory=list)
    outside_stage_ms: dict[str, list[float]] = field(default_factory=lambda: {s: [] for s in OUTSIDE_STAGES})
    wall_s: float = 0.0  # wall time of the frames fed, rows without inference included
    rows: int = 0  # every 50 Hz row produced

    def extend(self, other: StepSamples) -> None:
        self.e2e_ms.extend(other.e2e_ms)
        self.model_ms.extend(other.model_ms)
        self.outside_ms.extend(other.outside_ms)
        for stage, ms in other.outside_stage_ms.items():
            self.outside_stage_ms[stage].extend(ms)
        self.wall_s += other.wall_s
        self.rows += other.rows

    def summary(self) -> dict:
        e2e = np.asarray(self.e2e_ms)
        model = np.asarray(self.model_ms)
        return {"e2e_ms": summarize(e2e), "model_ms": summarize(model), "overhead_ms": summarize(e2e - model),
                "outside_ms": summarize(np.asarray(self.outside_ms)),
                "outside_stage_ms": {k: summarize(np.asarray(v)) for k, v in self.outside_stage_ms.items()}}


def open_session_model(path: str | Path, threads: int = 1, spinning: bool | None = None,
                       providers: Sequence[str] = ("cpu",), fixed_threads: bool = False):
    """The runtime's :class:`OnnxModel` for ``path`` (``providers`` as the runtime takes them: ``tensorrt``,
    ``cuda``, ``cpu``); ``spinning`` True turns onnxruntime's worker-thread spinning on, as the runtime's
    ``[model] spinning`` option does (default off); ``threads`` >= 2 is an upper bound as in the runtime, unless
    ``fixed_threads``."""
    from prml2_edge.runtime.inference import OnnxModel

    return OnnxModel(path, threads=threads, providers=providers, spinning=bool(spinning), fixed_threads=fixed_threads)


def build_pipeline(model, initial_pose: InitialPose, signal_map: str = "prml2_onboard",
                   stride: int = DEFAULT_STRIDE, async_inference: bool = False) -> Pipeline:
    """A runtime pipeline (no sinks) around an already-open model (``OnnxModel`` or a stand-in), the model every
    ``stride``-th step (the runtime's default), on a worker thread with ``async_inference``."""
    return Pipeline.build(map=signal_map, model=model, initial_pose=initial_pose, stride=stride,
                          async_inference=async_inference)


def split_frames(frames: Sequence[can.Message], warmup_rows: int, chunk_s: float):
    """(warm-up frames: the first ``warmup_rows`` 50 Hz rows' worth, then chunks of ``chunk_s`` seconds of frames),
    for measuring several pipelines on the same frames interleaved chunk by chunk (a change of machine load then
    hits all of them alike)."""
    from prml2_edge import schema

    t0 = frames[0].timestamp
    t_warm = t0 + warmup_rows * schema.DT_S
    warm = [f for f in frames if f.timestamp < t_warm]
    rest = frames[len(warm):]
    chunks: list[list[can.Message]] = []
    cur: list[can.Message] = []
    t_end = t_warm + chunk_s
    for f in rest:
        if f.timestamp >= t_end and cur:
            chunks.append(cur)
            cur, t_end = [], t_end + chunk_s
        cur.append(f)
    if cur:
        chunks.append(cur)
    return warm, chunks


def _outside_rows(lat, bounds: list[tuple[tuple[int, ...], tuple[int, ...]]], samples: StepSamples) -> None:
    """Per row (``bounds``: the :data:`OUTSIDE_STAGES` sample counts before and after its frames), the sum of
    each stage's samples in that range, into ``samples.outside_ms`` and ``samples.outside_stage_ms``."""
    if not bounds:
        return
    per_stage = []
    for j, stage in enumerate(OUTSIDE_STAGES):
        cum = np.concatenate(([0.0], np.cumsum(lat.samples_ms(stage))))
        lo = np.minimum([b[0][j] for b in bounds], cum.size - 1)
        hi = np.minimum([b[1][j] for b in bounds], cum.size - 1)
        ms = cum[hi] - cum[lo]
        samples.outside_stage_ms[stage].extend(ms.tolist())
        per_stage.append(ms)
    samples.outside_ms.extend(np.sum(per_stage, axis=0).tolist())


def measure_steps(pipeline: Pipeline, frames: Iterable[can.Message], skip: int = 0, paced: bool = False,
                  every_row: bool = False) -> StepSamples:
    """Feed ``frames`` to ``pipeline`` as fast as it takes them; per-row samples (first ``skip`` rows with an
    inference dropped). The pipeline may already have seen earlier frames of the same stream. Only the rows with
    an inference count (the worst ones), unless ``every_row`` (those without count with model time 0).

    ``paced``: each frame at its own time after the first (as a bus delivers them), and every row counts, its model
    time 0: the figure for a pipeline whose model runs on a worker thread (``async_inference``), where no row waits
    for an inference and the rows an output arrives at are not the ones that would have waited."""
    lat = pipeline.latency
    marks: list[tuple[int, int]] = []  # (end_to_end index, infer index) of rows with an inference
    bounds = []  # per counted row: OUTSIDE_STAGES sample counts before its first frame and after its last
    start = tuple(lat.count(s) for s in OUTSIDE_STAGES)
    rows = 0
    seen = 0
    gc.collect()
    t0 = time.perf_counter()
    ts0 = None
    for msg in frames:
        if paced:
            ts0 = msg.timestamp if ts0 is None else ts0
            wait = t0 + (msg.timestamp - ts0) - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
        n_e2e, n_inf = lat.count("end_to_end"), lat.count("infer")
        outs = pipeline.step(msg, time.perf_counter_ns())
        if not outs:
            continue
        rows += len(outs)
        counted = False
        for i, out in enumerate(outs):
            if paced:
                marks.append((n_e2e + i, -1))
                counted = True
            elif out.inferred:
                seen += 1
                if seen > skip:
                    marks.append((n_e2e + i, n_inf))
                    counted = True
                n_inf += 1
            elif every_row:
                marks.append((n_e2e + i, -1))
                counted = True
        end = tuple(lat.count(s) for s in OUTSIDE_STAGES)
        if counted:  # (two rows from one frame count as one step)
            bounds.append((start, end))
        start = end
    wall = time.perf_counter() - t0
    e2e_all = lat.samples_ms("end_to_end")
    inf_all = lat.samples_ms("infer")
    samples = StepSamples(wall_s=wall, rows=rows)
    for i_e2e, i_inf in marks:
        if i_e2e < e2e_all.size and i_inf < inf_all.size:
            samples.e2e_ms.append(float(e2e_all[i_e2e]))
            samples.model_ms.append(0.0 if i_inf < 0 else float(inf_all[i_inf]))
    _outside_rows(lat, bounds, samples)
    return samples
