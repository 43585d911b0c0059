"""Offline replay of a recorded CAN log: the streaming path's numbers on a batch schedule.

``prml2 replay --batch`` and ``prml2 fleet`` run a recorded log in three stages instead of one
frame at a time through a virtual bus, a piece of the log (``chunk_frames`` frames) at a time:

1. **frames -> rows.** ``can.LogReader`` straight into a list (no virtual bus, no feeder thread);
   every frame through the streaming :class:`FrameDecoder` and :class:`Assembler` (their rules:
   checksums, counters, late frames, clock jumps, gaps, stuck sensors, have one code path) and
   counted with :meth:`FrameStats.add_frame` as :meth:`Pipeline.step` does.
2. **windows -> model.** :meth:`~prml2_edge.runtime.estimator.Estimator.schedule` names every row at which the streaming
   estimator runs the model (it depends on the rows' discontinuity flags only); worker threads run
   those windows through the ONNX session (``session.run`` releases the GIL) while the main thread
   goes on with stages 1 and 3.
3. **rows -> filter.** The rows go through :meth:`Pipeline._row` as in streaming, with a
   :class:`PrecomputedModel` in the model's place: the estimator (window, invalid fraction, stride),
   the physics guard, the EKF, GNSS, sinks and every counter run unchanged. The filter lags one
   piece behind stage 1, so the workers are ahead of it.

With ``batch=1`` (the default) every window is its own ``session.run`` call on the same session, so
the model outputs, and with them the trajectory, are bitwise those of the streaming path (the test
suite checks it on a log with faults). ``batch > 1`` needs a graph with a free batch dimension and
changes outputs in the last float32 bits (onnxruntime blocks a batched GEMM differently); on this
CPU it is not faster for the edge model (``docs/benchmarks.md``); on a GPU it would be.
Decoding in bulk (frames grouped by ID, bits extracted with NumPy) was tried and measured no faster
than cantools frame by frame: the time of stage 1 is in the per-frame checks and the assembler.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import can
import numpy as np

from prml2_edge import schema
from prml2_edge.errors import ModelError, first_line
from prml2_edge.runtime.offline_workers import Inline, Processes, free_batch
from prml2_edge.runtime.rows import AssembledRow
from prml2_edge.runtime.source import check_log
from prml2_edge.runtime.status import InferenceStatus

log = logging.getLogger(__name__)

CHUNK_FRAMES = 10_000  # frames per piece (~25 s of driving on the project DBC): bounds memory, keeps stages overlapped
WINDOWS_PER_TASK = 128  # windows one worker task runs


def default_workers() -> int:
    """Inference worker threads: the CPUs this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def read_chunks(path: str | Path, chunk: int = CHUNK_FRAMES) -> Iterator[tuple[list[can.Message], str | None]]:
    """The log's frames in file order, ``chunk`` at a time; the last piece carries the read problem (or None).

    A log that breaks midway yields the frames before the break with its one-line problem, like
    :attr:`~prml2_edge.runtime.source.LogReplay.error`.
    """
    path = check_log(path)
    frames: list[can.Message] = []
    n = 0
    try:
        with can.LogReader(str(path)) as reader:
            for msg in reader:
                frames.append(msg)
                n += 1
                if len(frames) >= chunk:
                    yield frames, None
                    frames = []
    except Exception as exc:  # a malformed log: deliver what came before, report it at the end
        yield frames, f"{path}: cannot read CAN log after {n} frames ({first_line(exc, 200)})"
        return
    yield frames, None


@dataclass
class RowBlock:
    """Assembled rows of one piece of the log, from row index ``start`` on."""

    start: int
    rows: list[AssembledRow] = field(default_factory=list)


class _Values:
    """Every row's values as float32 (what the window holds), growing; a task gets a copy of the slice it needs."""

    def __init__(self) -> None:
        self.array = np.zeros((4096, schema.NUM_SIGNALS), dtype=np.float32)
        self.n = 0

    def extend(self, rows: list[AssembledRow]) -> None:
        need = self.n + len(rows)
        if need > len(self.array):
            grown = np.zeros((max(need, 2 * len(self.array)), schema.NUM_SIGNALS), dtype=np.float32)
            grown[:self.n] = self.array[:self.n]
            self.array = grown
        for j, row in enumerate(rows):
            self.array[self.n + j] = row.values
        self.n = need


class PrecomputedModel:
    """Stands in for an :class:`~prml2_edge.runtime.inference.OnnxModel` in the estimator: the outputs of the
    windows :meth:`~prml2_edge.runtime.estimator.Estimator.schedule` names, run ahead of the filter
    (``workers`` >= 2: worker processes; 1: in this thread when the filter needs them).

    :meth:`submit` queues windows (by row index, in schedule order); :meth:`step` hands their outputs out
    in that order and checks that it is called for the scheduled row (the runner sets :attr:`row`): a
    schedule out of step with the estimator's is a bug and raises, it never silently feeds one window's
    output to another row. ``verify=True`` also compares every window the estimator passes with the one
    run (tests). :attr:`mean`/:attr:`var` hold the newest decoder row only (1, 5).
    """

    def __init__(self, model, batch: int = 1, workers: int = 1, verify: bool = False) -> None:
        if batch < 1 or workers < 1:
            raise ModelError(f"batch size and workers must be >= 1, got {batch}, {workers}")
        if batch > 1 and not free_batch(model.session):
            raise ModelError(f"{model.path}: the graph's batch dimension is fixed at 1, so it runs one window per "
                             "call; use --batch-size 1 or a model exported with a free batch dimension")
        self.base = model
        self.metadata = model.metadata
        self.window_len = model.window_len
        self.output_rows = 1
        self.batch = int(batch)
        self.workers = int(workers)
        self.verify = verify
        self.mean = np.zeros((1, schema.NUM_STATES))
        self.var = np.ones((1, schema.NUM_STATES))
        self.row = -1
        self.scheduled: list[int] = []
        self._task: list[tuple[int, int]] = []  # per scheduled window: its task and its place in it
        self._ptr = 0
        self._values: _Values | None = None
        self._current: tuple[int, tuple] | None = None
        self._n_tasks = 0
        self.n_runs = 0
        self.n_invalid = 0
        self.n_errors = 0
        self.last_error = ""
        self.wait_s = 0.0  # time the filter waited for an inference [s]
        self.runner = Inline(model, self.batch) if self.workers == 1 else Processes(model, self.batch, self.workers)

    @property
    def worker_s(self) -> float:
        """Inference time summed over the workers [s]."""
        return self.runner.busy_s

    @property
    def consumed(self) -> int:
        return self._ptr

    def submit(self, values: _Values, rows: np.ndarray) -> None:
        """Queue the windows ending at ``rows`` (ascending, after every row queued before)."""
        self._values = values
        for s in range(0, len(rows), WINDOWS_PER_TASK):
            part = rows[s:s + WINDOWS_PER_TASK]
            self.runner.submit(self._n_tasks, values.array, part)
            self._task += [(self._n_tasks, j) for j in range(len(part))]
            self.scheduled += part.tolist()
            self._n_tasks += 1

    def step(self, window: np.ndarray) -> InferenceStatus:
        j = self._ptr
        if j >= len(self.scheduled) or self.scheduled[j] != self.row:
            want = self.scheduled[j] if j < len(self.scheduled) else None
            raise RuntimeError(f"offline inference schedule out of step with the estimator: inference at row "
                               f"{self.row}, scheduled {want}")
        if self.verify:
            L = self.window_len
            if not np.array_equal(window[0], self._values.array[self.row - L + 1:self.row + 1]):
                raise RuntimeError(f"offline window of row {self.row} differs from the estimator's")
        task_id, i = self._task[j]
        self._ptr += 1
        if self._current is None or self._current[0] != task_id:
            t0 = time.perf_counter()
            self._current = (task_id, self.runner.result(task_id))
            self.wait_s += time.perf_counter() - t0
        status, mean, var, error = self._current[1]
        self.n_runs += 1
        st = InferenceStatus(int(status[i]))
        if st is InferenceStatus.ERROR:
            self.n_errors += 1
            self.last_error = error
        elif st is InferenceStatus.INVALID_OUTPUT:
            self.n_invalid += 1
        else:
            self.mean[0] = mean[i]
            self.var[0] = var[i]
        return st

    def describe(self) -> str:
        where = "in the filter's thread" if self.workers == 1 else f"{self.workers} worker processes"
        return f"{self.base.describe()}; offline: inference {where}, {self.batch} window(s) per call"

    def close(self) -> None:
        self.runner.close()


@dataclass
class OfflineResult:
    """What :func:`run_offline` did: the log's read problem (or None), rows, inferences, where the time went [s]."""

    problem: str | None
    frames: int
    rows: int
    inferences: int
    timing_s: dict[str, float]


def run_offline(pipeline, path: str | Path, batch: int = 1, workers: int | None = None, progress=None,
                verify: bool = False, chunk_frames: int = CHUNK_FRAMES,
                on_rows: Callable[[int], None] | None = None,
                on_row: Callable[[AssembledRow, object], None] | None = None) -> OfflineResult:
    """Replay the log ``path`` through ``pipeline`` on the offline schedule (module docstring).

    ``pipeline`` is a fresh :class:`~prml2_edge.runtime.pipeline.Pipeline`; afterwards its sinks, summary and
    frame accounting are as after :func:`~prml2_edge.runtime.pipeline.run_source` on the same log (only the
    per-stage latencies are not measured: stages do not run per frame; see the
    time per stage in ``pipeline.offline``). ``progress`` is advanced per frame, ``on_rows(n)`` per piece filtered;
    ``on_row(row, out)`` sees every assembled row with its :class:`StepOutput` (``prml2 fleet``'s GNSS drift).
    """
    if (reason := windows_wait_for_filter(pipeline)) is not None:
        if batch > 1 or (workers or 1) > 1:
            log.warning("offline: %s, so every window runs in the filter's step, one at a time (--batch-size and "
                        "--workers do not apply)", reason)
        return _run_in_step(pipeline, path, reason, progress, chunk_frames, on_rows, on_row)
    t_start = time.perf_counter()
    loc = pipeline.localizer
    est = loc.estimator
    model = est.model
    pre = PrecomputedModel(model, batch=batch, workers=workers or default_workers(), verify=verify)
    values = _Values()
    state = [0, -1]
    pending: list[RowBlock] = []
    t_assemble = t_filter = 0.0
    n_frames = 0
    problem = None

    def add_rows(rows: list[AssembledRow]) -> None:
        if not rows:
            return
        block = RowBlock(values.n, rows)
        values.extend(rows)
        pre.submit(values, est.schedule([r.discontinuity for r in rows], model.window_len, est.stride, state,
                                        offset=block.start))
        pending.append(block)

    def filter_block(block: RowBlock) -> None:
        for j, row in enumerate(block.rows):
            pre.row = block.start + j
            out = pipeline._row(row)
            if on_row is not None:
                on_row(row, out)
        if on_rows is not None:
            on_rows(len(block.rows))

    loc.model = est.model = pre
    try:
        for frames, piece_problem in read_chunks(path, chunk_frames):
            problem = problem or piece_problem
            t0 = time.perf_counter()
            add_rows(_decode_chunk(pipeline, frames))
            n_frames += len(frames)
            t1 = time.perf_counter()
            t_assemble += t1 - t0
            if progress is not None:
                progress.update(len(frames))
            while len(pending) > 1:  # the filter lags one piece behind, so the workers are ahead of it
                filter_block(pending.pop(0))
            t_filter += time.perf_counter() - t1
        t0 = time.perf_counter()
        add_rows([pipeline.check(r) for r in pipeline.assembler.flush()])
        t1 = time.perf_counter()
        while pending:
            filter_block(pending.pop(0))
        t_filter += time.perf_counter() - t1
        t_assemble += t1 - t0
        if pre.consumed != len(pre.scheduled):
            raise RuntimeError(f"offline inference schedule out of step: {len(pre.scheduled)} windows run, "
                               f"{pre.consumed} consumed")
    finally:
        loc.model = est.model = model
        pre.close()
    timing = {"decode_assemble": t_assemble, "filter": t_filter - pre.wait_s, "inference_workers": pre.worker_s,
              "filter_waited_for_inference": pre.wait_s, "total": time.perf_counter() - t_start}
    _record_schedule(pipeline, pre, timing)
    return OfflineResult(problem, n_frames, values.n, len(pre.scheduled), timing)


def windows_wait_for_filter(pipeline) -> str | None:
    """Why this pipeline's model windows cannot run ahead of its filter (None: they can). A model that reads each
    row less the cue offsets the filter's estimator has learned by then (``StreamingLocalizer.model_reads_cues``)
    needs the filter to have run up to that row: run ahead on raw rows, it would be fed what it never saw."""
    loc = pipeline.localizer
    if loc.model_reads_cues and loc.filter.cue_offset is not None:
        return "the model reads each row less the cue offsets the filter has learned by then"
    return None


def _run_in_step(pipeline, path: str | Path, reason: str, progress, chunk_frames: int,
                 on_rows: Callable[[int], None] | None,
                 on_row: Callable[[AssembledRow, object], None] | None) -> OfflineResult:
    """:func:`run_offline` for a model whose windows wait for the filter (``reason``): the frames are read and
    decoded a piece at a time, and every row goes through :meth:`Pipeline._row` with the model run in the
    estimator's step, as streaming runs it (the same poses, bitwise)."""
    t_start = time.perf_counter()
    est = pipeline.localizer.estimator
    runs0 = est.n_inferences
    t_assemble = t_filter = 0.0
    n_frames = n_rows = 0
    problem = None

    def filter_rows(rows: list[AssembledRow]) -> None:
        for row in rows:
            out = pipeline._row(row)
            if on_row is not None:
                on_row(row, out)
        if on_rows is not None and rows:
            on_rows(len(rows))

    for frames, piece_problem in [*read_chunks(path, chunk_frames), (None, None)]:
        problem = problem or piece_problem
        t0 = time.perf_counter()
        if frames is None:  # the end of the log: what the assembler still holds
            rows = [pipeline.check(r) for r in pipeline.assembler.flush()]
        else:
            rows = _decode_chunk(pipeline, frames)
            n_frames += len(frames)
            if progress is not None:
                progress.update(len(frames))
        t1 = time.perf_counter()
        filter_rows(rows)
        n_rows += len(rows)
        t_assemble, t_filter = t_assemble + t1 - t0, t_filter + time.perf_counter() - t1
    windows = est.n_inferences - runs0
    timing = {"decode_assemble": t_assemble, "filter": t_filter, "inference_workers": 0.0,
              "filter_waited_for_inference": 0.0, "total": time.perf_counter() - t_start}
    pipeline.offline = {"model": f"{est.model.describe()}; offline: inference in the filter's step ({reason})",
                        "windows": windows, "workers": 0, "batch": 1, "timing_s": timing, "in_step": reason}
    return OfflineResult(problem, n_frames, n_rows, windows, timing)


def _decode_chunk(pipeline, frames: list) -> list[AssembledRow]:
    """Decode and assemble one chunk of frames (frame accounting in the pipeline's stats); its checked rows."""
    decoder, assembler, stats = pipeline.decoder, pipeline.assembler, pipeline.stats
    rows: list[AssembledRow] = []
    for msg in frames:
        frame = decoder.step(msg)
        status, new_rows = assembler.step(frame, 0)
        stats.add_frame(status, frame)
        if new_rows:
            rows += [pipeline.check(r) for r in new_rows]
    return rows


def _record_schedule(pipeline, pre: PrecomputedModel, timing: dict[str, float]) -> None:
    """What the offline schedule did, in ``pipeline.offline``; the per-step inference latency dropped."""
    pipeline.latency.clear("infer")  # it timed handing out precomputed outputs, not the model
    pipeline.offline = {"model": pre.describe(), "windows": len(pre.scheduled), "workers": pre.workers,
                        "batch": pre.batch, "timing_s": timing}


__all__ = ["OfflineResult", "PrecomputedModel", "default_workers", "read_chunks", "run_offline",
           "windows_wait_for_filter"]
