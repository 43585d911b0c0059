"""The workers that run a recorded log's model windows ahead of its filter (:mod:`~prml2_edge.runtime.offline`):
in the filter's thread when it asks for them (:class:`Inline`), or in worker processes (:class:`Processes`), each
window checked as :meth:`~prml2_edge.runtime.inference.OnnxModel.step` checks it (:func:`run_windows`)."""

from __future__ import annotations

import os
import time

import numpy as np

from prml2_edge import schema
from prml2_edge.errors import ModelError, first_line
from prml2_edge.runtime.status import InferenceStatus


def free_batch(session) -> bool:
    dim = session.get_inputs()[0].shape[0]
    return not isinstance(dim, int)


def run_windows(session, output_names, input_name, output_rows: int, array: np.ndarray, rows, window_len: int,
                batch: int = 1):
    """The windows of ``array`` ending at ``rows``, ``batch`` per call, checked as ``OnnxModel.step`` checks:
    ``(status (n,) int8 InferenceStatus, mean (n, 5), var (n, 5), last error or '')``, newest decoder row."""
    n = len(rows)
    L = window_len
    status = np.full(n, int(InferenceStatus.SUCCESS), dtype=np.int8)
    mean = np.zeros((n, schema.NUM_STATES))
    var = np.ones((n, schema.NUM_STATES))
    error = ""
    for b in range(0, n, batch):
        sel = rows[b:b + batch]
        x = array[sel[0] - L + 1:sel[0] + 1][None] if len(sel) == 1 else \
            np.stack([array[i - L + 1:i + 1] for i in sel])
        try:
            m, v = session.run(output_names, {input_name: x})
        except Exception as exc:  # onnxruntime wraps every failure in its own types
            status[b:b + len(sel)] = int(InferenceStatus.ERROR)
            error = first_line(exc, 200)
            continue
        if m.shape != (len(sel), output_rows, schema.NUM_STATES) or v.shape != m.shape:
            status[b:b + len(sel)] = int(InferenceStatus.INVALID_OUTPUT)
            continue
        # checked over every row, as OnnxModel.step does; the runtime consumes the newest decoder row only
        bad = ~(np.isfinite(m).all(axis=(1, 2)) & np.isfinite(v).all(axis=(1, 2)) & (v > 0).all(axis=(1, 2)))
        m, v = m[:, -1], v[:, -1]
        status[b:b + len(sel)][bad] = int(InferenceStatus.INVALID_OUTPUT)
        mean[b:b + len(sel)] = m
        var[b:b + len(sel)] = v
    return status, mean, var, error


def _worker_main(path: str, threads: int, spinning: bool, providers: list, batch: int, tasks, results,
                 parent: int) -> None:
    """An inference process: the same session options as the runtime's model, windows in, outputs out.
    It ends with ``None`` from the parent, or once the parent is gone (killed: nobody would read its results)."""
    import queue

    import onnxruntime as ort

    from prml2_edge.runtime.inference import session_options

    try:
        sess = ort.InferenceSession(path, sess_options=session_options(threads, spinning=spinning),
                                    providers=providers)
        meta = None
        from prml2_edge.model_meta import METADATA_KEY, ModelMetadata

        meta = ModelMetadata.from_json(sess.get_modelmeta().custom_metadata_map[METADATA_KEY], source=path)
    except Exception as exc:  # reported by the parent in one line
        results.put((-1, first_line(exc, 200)))
        return
    names, inp, rows_out, L = list(meta.output_names), meta.input_name, meta.rows, int(meta.L)
    while True:
        try:
            task = tasks.get(timeout=1.0)
        except queue.Empty:
            if os.getppid() != parent:
                return
            continue
        if task is None:
            return
        task_id, first_row, piece, rows = task
        t0 = time.perf_counter()
        out = run_windows(sess, names, inp, rows_out, piece, np.asarray(rows) - first_row, L, batch)
        results.put((task_id, (*out, time.perf_counter() - t0)))


class Inline:
    """Windows run in this thread, when the filter asks for them (one worker: nothing to overlap)."""

    def __init__(self, model, batch: int) -> None:
        self.model, self.batch = model, batch
        self.busy_s = 0.0
        self._pending: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def submit(self, task_id: int, array: np.ndarray, rows: np.ndarray) -> None:
        self._pending[task_id] = (array, rows)  # (rows written before a submit stay in that array)

    def result(self, task_id: int):
        array, rows = self._pending.pop(task_id)
        m = self.model
        t0 = time.perf_counter()
        out = run_windows(m.session, m.output_names, m.input_name, m.output_rows, array, rows, m.window_len,
                          self.batch)
        self.busy_s += time.perf_counter() - t0
        return out

    def close(self) -> None:
        pass


class Processes:
    """Windows run by ``n`` worker processes, each with its own session (the GIL would serialise threads: the
    filter is Python and a thread returning from ``session.run`` waits for it)."""

    def __init__(self, model, batch: int, n: int) -> None:
        import multiprocessing as mp

        ctx = mp.get_context("spawn")  # no fork of onnxruntime's threads
        self.tasks, self.results = ctx.Queue(), ctx.Queue()
        choice = getattr(model, "provider_choice", None)
        providers = list(getattr(choice, "providers", None) or ["CPUExecutionProvider"])
        args = (str(model.path), int(model.session.get_session_options().intra_op_num_threads),
                bool(getattr(model, "spinning", False)), providers, batch, self.tasks, self.results, os.getpid())
        self.procs = [ctx.Process(target=_worker_main, args=args, name=f"prml2-infer-{k}", daemon=True)
                      for k in range(n)]
        for p in self.procs:
            p.start()
        self.window_len = model.window_len
        self.done: dict[int, tuple] = {}
        self.busy_s = 0.0

    def submit(self, task_id: int, array: np.ndarray, rows: np.ndarray) -> None:
        first = int(rows[0]) - self.window_len + 1
        self.tasks.put((task_id, first, np.ascontiguousarray(array[first:int(rows[-1]) + 1]), rows.tolist()))

    def result(self, task_id: int):
        import queue

        while task_id not in self.done:
            try:
                got_id, out = self.results.get(timeout=5.0)
            except queue.Empty:
                dead = [p.name for p in self.procs if not p.is_alive()]
                if dead:
                    raise ModelError(f"offline inference worker(s) {', '.join(dead)} died") from None
                continue
            if got_id < 0:
                raise ModelError(f"offline inference worker cannot load the model ({out})")
            self.busy_s += out[-1]
            self.done[got_id] = out[:-1]
        return self.done.pop(task_id)

    def close(self) -> None:
        for _ in self.procs:
            self.tasks.put(None)
        for p in self.procs:
            p.join(timeout=5.0)
            if p.is_alive():
                p.terminate()
        self.tasks.close()
        self.results.close()


__all__ = ["Inline", "Processes", "free_batch", "run_windows"]
