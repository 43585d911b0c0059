"""ONNX Runtime session for a PRML2 model: load, check its metadata, run one window.

The session is configured for a small, predictable edge footprint: ``intra_op_num_threads``
from the config (default 1; more only where they are faster: :meth:`OnnxModel.pick_threads`), one
inter-op thread, thread spinning off unless asked for (an idle spinning thread would steal the CPU
the CAN loop needs; with 2+ threads spinning tightens the tail latency of a large model), all graph
optimisations. Providers come
from :func:`prml2_edge.runtime.providers.select_providers` (TensorRT -> CUDA -> CPU,
whichever this onnxruntime offers).

Graph contract (:mod:`prml2_edge.model_meta`): input ``onboard`` float32 (1, L, 9) raw SI;
outputs ``z_mean``, ``z_var`` float32 (1, R, 5) before the physics guard, for the newest
R = ``metadata.rows`` decoder steps (1 for a streaming export, L - H for a full one).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from prml2_edge import schema
from prml2_edge.errors import ModelError, first_line
from prml2_edge.model_meta import METADATA_KEY, ModelMetadata
from prml2_edge.resources import resource_path
from prml2_edge.runtime.status import InferenceStatus

log = logging.getLogger(__name__)


def default_model_path() -> Path:
    """The shipped default model (``export/default/prml2_edge.onnx``; ``prml2_edge/_data/model`` when installed).

    Raises :class:`ModelError` when it is not there.
    """
    for parts in (("model", "prml2_edge.onnx"), ("export", "default", "prml2_edge.onnx")):
        try:
            return resource_path(*parts)
        except Exception:
            continue
    raise ModelError("the shipped default model export/default/prml2_edge.onnx is missing from this installation; "
                     "pass --model PATH (an ONNX file from 'prml2 export')")


def session_options(threads: int = 1, spinning: bool = False):
    """The runtime's ONNX Runtime session options: ``threads`` intra-op threads, one inter-op thread,
    sequential execution, all graph optimisations, thread spinning off unless ``spinning``."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = int(threads)
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    flag = "1" if spinning else "0"
    opts.add_session_config_entry("session.intra_op.allow_spinning", flag)
    opts.add_session_config_entry("session.inter_op.allow_spinning", flag)
    opts.log_severity_level = 3
    return opts


def _dim_ok(dim: object, want: int) -> bool:
    return not isinstance(dim, int) or dim == want  # symbolic dims (strings/None) accept any size


class OnnxModel:
    """A PRML2 ONNX model in an onnxruntime session, checked against the runtime's schema.

    Parameters
    ----------
    path:
        ONNX file.
    threads:
        Intra-op threads (CPU provider).
    spinning:
        onnxruntime's worker threads busy-wait between parallel sections (``threads`` >= 2).
    fixed_threads:
        Run on ``threads`` as given. By default ``threads`` >= 2 is an upper bound: a model that runs faster on one
        intra-op thread on this machine gets one (:meth:`pick_threads`; :attr:`threads` says which).
    providers:
        Provider short names in order of preference (``tensorrt``, ``cuda``, ``cpu``).

    After :meth:`step` returned ``SUCCESS``, :attr:`mean` and :attr:`var` hold the decoder
    outputs (R, 5) float64 [z units] of the newest R = :attr:`output_rows` decoder steps (the last
    row is the newest step), before the physics guard.
    """

    def __init__(self, path: str | Path, threads: int = 1, providers: Sequence[str] = ("cpu",),
                 trt_cache_dir: str = "~/.cache/prml2/trt", trt_fp16: bool = False, spinning: bool = False,
                 fixed_threads: bool = False) -> None:

        from prml2_edge.runtime.providers import select_providers

        self.path = Path(path)
        if not self.path.is_file():
            raise ModelError(f"{self.path}: model file not found")
        if threads < 1:
            raise ModelError(f"threads must be >= 1, got {threads}")
        self.spinning = bool(spinning)
        self.provider_choice = select_providers(providers, trt_cache_dir=trt_cache_dir, trt_fp16=trt_fp16)
        self.session = self._open(threads)
        self.providers = self.session.get_providers()
        props = self.session.get_modelmeta().custom_metadata_map
        if METADATA_KEY not in props:
            raise ModelError(f"{self.path}: no PRML2 metadata (metadata_props key {METADATA_KEY!r}); "
                             "export the model with 'prml2 export'")
        self.metadata = ModelMetadata.from_json(props[METADATA_KEY], source=str(self.path))
        self.metadata.check_schema(source=str(self.path))
        if self.metadata.guard_in_graph:
            raise ModelError(f"{self.path}: the physics guard is inside this graph; the runtime applies it itself "
                             "(re-export with the guard outside)")
        self.window_len = int(self.metadata.L)
        self.decoder_len = int(self.metadata.L - self.metadata.H)
        self.output_rows = self.metadata.rows
        self._check_io()
        self.input_name = self.metadata.input_name
        self.output_names = list(self.metadata.output_names)
        self.mean = np.zeros((self.output_rows, schema.NUM_STATES))
        self.var = np.ones((self.output_rows, schema.NUM_STATES))
        self.n_runs = 0
        self.n_invalid = 0
        self.n_errors = 0
        self.last_error = ""
        log.info("%s; %s", self.provider_choice.describe(), self.describe())
        self.warm_up_ms = self.warm_up()
        self.threads_requested = self.threads = int(threads)
        self.thread_timing_ms: dict[int, float] | None = None
        if threads > 1 and not fixed_threads and self.providers[0] == "CPUExecutionProvider":
            self.pick_threads()

    def pick_threads(self, budget_s: float = 0.5, min_runs: int = 15) -> int:
        """One intra-op thread instead of :attr:`threads_requested` when the model runs faster so on this machine.

        A small model's operators are too short for a second thread to pay for waking it (the edge model: e2e p99
        1.9-2.4 ms on 2 threads against 1.7-1.8 on 1, docs/benchmarks.md), a large one's are not. Both sessions
        run the warm-up window alternately, at least ``min_runs`` times each and for about ``budget_s`` seconds;
        the lower mean (which a slow tail raises) wins. :attr:`thread_timing_ms` keeps the means.
        """
        one = self._open(1)
        sessions = {self.threads_requested: self.session, 1: one}
        window = self._neutral_window()
        times: dict[int, list[float]] = {n: [] for n in sessions}
        one.run(self.output_names, {self.input_name: window})
        t_end = time.perf_counter() + budget_s
        while len(times[1]) < min_runs or (time.perf_counter() < t_end and len(times[1]) < 1000):
            for n, sess in sessions.items():
                t0 = time.perf_counter()
                sess.run(self.output_names, {self.input_name: window})
                times[n].append((time.perf_counter() - t0) * 1e3)
        self.thread_timing_ms = {n: float(np.mean(t)) for n, t in times.items()}
        if self.thread_timing_ms[1] < self.thread_timing_ms[self.threads_requested]:
            self.session, self.threads = one, 1
            log.info("%s: %d intra-op threads asked for, one is faster for this model here (mean %.2f against "
                     "%.2f ms over %d runs each): using 1 ([model] fixed_threads = true keeps %d)", self.path.name,
                     self.threads_requested, self.thread_timing_ms[1], self.thread_timing_ms[self.threads_requested],
                     len(times[1]), self.threads_requested)
        return self.threads

    def _open(self, threads: int):
        """An onnxruntime session of this model on ``threads`` intra-op threads (one-line error if it cannot load)."""
        import onnxruntime as ort

        try:
            return ort.InferenceSession(str(self.path), sess_options=session_options(threads, spinning=self.spinning),
                                        providers=self.provider_choice.providers)
        except Exception as exc:
            raise ModelError(f"{self.path}: onnxruntime cannot load the model ({first_line(exc)[:200]})") from exc

    def _neutral_window(self) -> np.ndarray:
        """(1, L, 9) float32: every row the model's normalisation mean (a car at rest on its mean signals)."""
        window = np.zeros((1, self.window_len, schema.NUM_SIGNALS), dtype=np.float32)
        window[0] = np.asarray(self.metadata.norm_mean, dtype=np.float32)
        return window

    def warm_up(self, runs: int = 3) -> list[float]:
        """Run a few inferences on a neutral window before the first real frame [ms each].

        The first onnxruntime call allocates buffers (and, with TensorRT, builds or loads the
        engine); doing it here keeps that out of the first real 50 Hz step. Not counted in
        :attr:`n_runs`. Raises :class:`ModelError` when the model cannot run at all.
        """
        window = self._neutral_window()
        times = []
        for _ in range(runs):
            t0 = time.perf_counter()
            try:
                self.session.run(self.output_names, {self.input_name: window})
            except Exception as exc:
                first = first_line(exc, 200)
                raise ModelError(f"{self.path}: warm-up inference failed ({first})") from exc
            times.append((time.perf_counter() - t0) * 1e3)
        return times

    def _check_io(self) -> None:
        meta = self.metadata
        inputs = {i.name: i for i in self.session.get_inputs()}
        outputs = {o.name: o for o in self.session.get_outputs()}
        if list(inputs) != [meta.input_name]:
            raise ModelError(f"{self.path}: graph inputs {list(inputs)} differ from the metadata's "
                             f"[{meta.input_name!r}]")
        shape = inputs[meta.input_name].shape
        if len(shape) != 3 or not (_dim_ok(shape[1], meta.L) and _dim_ok(shape[2], schema.NUM_SIGNALS)):
            raise ModelError(f"{self.path}: input {meta.input_name!r} has shape {shape}, want (1, {meta.L}, "
                             f"{schema.NUM_SIGNALS})")
        if inputs[meta.input_name].type != "tensor(float)":
            raise ModelError(f"{self.path}: input type {inputs[meta.input_name].type}, want tensor(float)")
        for name in meta.output_names:
            if name not in outputs:
                raise ModelError(f"{self.path}: graph lacks output {name!r} (has {sorted(outputs)})")
            oshape = outputs[name].shape
            if len(oshape) != 3 or not (_dim_ok(oshape[1], self.output_rows) and _dim_ok(oshape[2], schema.NUM_STATES)):
                raise ModelError(f"{self.path}: output {name!r} has shape {oshape}, want (1, {self.output_rows}, "
                                 f"{schema.NUM_STATES}) as its metadata says")

    def describe(self) -> str:
        m = self.metadata
        return (f"model {self.path.name}: preset {m.preset}, L={m.L}, H={m.H}, {self.output_rows} output row(s), "
                f"version {m.version}, providers {', '.join(self.providers)}")

    def step(self, window: np.ndarray) -> InferenceStatus:
        """Run one window (1, L, 9) float32 [SI]; never raises.

        ``SUCCESS`` fills :attr:`mean`/:attr:`var`; ``INVALID_OUTPUT`` when the model returned a
        non-finite mean or a non-positive/non-finite variance or a wrong shape; ``ERROR`` when
        onnxruntime raised (message in :attr:`last_error`).
        """
        self.n_runs += 1
        try:
            mean, var = self.session.run(self.output_names, {self.input_name: window})
        except Exception as exc:  # onnxruntime wraps every failure in its own types
            self.n_errors += 1
            self.last_error = first_line(exc, 200)
            return InferenceStatus.ERROR
        want = (1, self.output_rows, schema.NUM_STATES)
        if mean.shape != want or var.shape != want:
            self.n_invalid += 1
            return InferenceStatus.INVALID_OUTPUT
        if not (np.isfinite(mean).all() and np.isfinite(var).all() and (var > 0).all()):
            self.n_invalid += 1
            return InferenceStatus.INVALID_OUTPUT
        self.mean[:] = mean[0]
        self.var[:] = var[0]
        return InferenceStatus.SUCCESS
