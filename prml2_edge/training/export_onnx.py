"""Export a trained checkpoint to ONNX for the edge runtime (contract: :mod:`prml2_edge.model_meta`).

The graph takes ``onboard`` float32 (1, L, 9) raw SI (normalisation is inside the graph) and
returns ``z_mean`` and ``z_var`` float32 (1, R, 5) for the newest R decoder steps (``rows``; all
L - H when None), before the physics guard (the guard runs in NumPy at runtime so the friction
coefficient can be set there). The streaming runtime consumes only the newest step, so a graph
with R = 1 (the ``prml2 export`` default) gives it the same numbers while its last decoder layer
computes one query row instead of L - H. The
:class:`~prml2_edge.model_meta.ModelMetadata` JSON is stored under the ``metadata_props`` key
``"prml2"``. The legacy TorchScript-based exporter (``dynamo=False``) is used: it gives a clean,
fixed-shape graph at opset 17 that onnxruntime runs with the same numbers as torch (checked by
:func:`parity`).

``quantize_int8`` applies onnxruntime's dynamic quantisation (int8 weights of the MatMul/Gemm
layers); :func:`compare_int8` measures what it costs in z RMSE on validation windows.
"""

from __future__ import annotations

import io
import warnings
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from prml2_edge import __version__, schema
from prml2_edge.errors import ModelError
from prml2_edge.model_meta import INPUT_NAME, METADATA_KEY, OUTPUT_NAMES, ModelMetadata
from prml2_edge.training.model import Prml2Model

OPSET = 17


def metadata_for(model: Prml2Model, ckpt: dict[str, Any], *, quantized: bool = False) -> ModelMetadata:
    """The :class:`ModelMetadata` of a checkpoint's model (process noise Q from the NumPy EKF defaults)."""
    from prml2_edge.ekf.numpy_ekf import default_process_noise

    train_cfg = dict(ckpt.get("train_config", {}))
    metrics = ckpt.get("metrics", {})
    training = {
        "epochs": train_cfg.get("epochs"),
        "epochs_completed": ckpt.get("epoch"),
        "finetune": train_cfg.get("finetune"),
        "pretrain_epochs": None,
        "seed": train_cfg.get("seed"),
        "batch_size": train_cfg.get("batch_size"),
        "lr": train_cfg.get("lr"),
        "window_stride": train_cfg.get("window_stride"),
        "beta": train_cfg.get("beta"),
        "stage": ckpt.get("stage"),
        "code_version": ckpt.get("code_version"),
        "val_objective": metrics.get("val_objective"),
        "int8": quantized,
    }
    try:
        from prml2_edge.training.presets import train_config_from_dict

        training["pretrain_epochs"] = train_config_from_dict(train_cfg).pretrain_epochs()
    except Exception:  # noqa: BLE001 - metadata stays exportable for an older train config
        training.pop("pretrain_epochs")
    return ModelMetadata(
        version=__version__,
        preset=str(ckpt.get("preset", "unknown")),
        norm_mean=[float(v) for v in model.in_mean.tolist()],
        norm_std=[float(v) for v in model.in_std.tolist()],
        dataset_fingerprint=str(ckpt.get("dataset_fingerprint", "")),
        config={**asdict(model.cfg), "z_mean": model.z_mean.tolist(), "z_std": model.z_std.tolist()},
        ekf_process_noise=default_process_noise(schema.DT_S).tolist(),
        training=training,
        L=model.cfg.window_len,
        H=model.cfg.encoder_len,
    )


class _NewestRows(torch.nn.Module):
    """``model`` returning its newest ``rows`` decoder steps: computed only for those rows when the model
    can (``forward(onboard, rows=...)``, the PRML2 transformer), else sliced from the full output."""

    def __init__(self, model: torch.nn.Module, rows: int) -> None:
        super().__init__()
        self.model = model
        self.rows = int(rows)
        self.native = isinstance(model, Prml2Model)

    def forward(self, onboard: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if self.native:
            return self.model(onboard, rows=self.rows)
        mean, var = self.model(onboard)
        return mean[:, -self.rows:], var[:, -self.rows:]


def newest_rows(model: torch.nn.Module, rows: int | None) -> torch.nn.Module:
    """``model`` itself (rows None: every decoder step) or its :class:`_NewestRows` wrapper."""
    return model if rows is None else _NewestRows(model, rows).eval()


def export_onnx(model: Prml2Model, metadata: ModelMetadata, out_path: str | Path, *, opset: int = OPSET,
                rows: int | None = None) -> Path:
    """Write ``model`` as a fixed-shape ONNX graph with ``metadata`` embedded; returns the path.

    ``rows``: the graph returns the newest ``rows`` decoder steps (None: all L - H); recorded in the
    metadata's ``output_rows``.
    """
    import onnx

    out_path = Path(out_path)
    model = model.eval()
    decoder_len = model.cfg.window_len - model.cfg.encoder_len
    if rows is not None and not 1 <= int(rows) <= decoder_len:
        raise ModelError(f"rows must be in [1, L - H = {decoder_len}], got {rows}")
    metadata = ModelMetadata(**{**asdict(metadata), "output_rows": None if rows is None else int(rows)})
    dummy = torch.zeros(1, model.cfg.window_len, schema.NUM_SIGNALS, dtype=torch.float32)
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # TracerWarnings and the legacy-exporter deprecation notice
        torch.onnx.export(
            newest_rows(model, rows),
            (dummy,),
            buf,
            input_names=[INPUT_NAME],
            output_names=list(OUTPUT_NAMES),
            opset_version=opset,
            do_constant_folding=True,
            dynamo=False,
        )
    proto = onnx.load_from_string(buf.getvalue())
    set_metadata(proto, metadata)
    onnx.checker.check_model(proto)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(proto, str(out_path))
    return out_path


def model_from_onnx(path: str | Path) -> tuple[Prml2Model, dict, dict]:
    """Rebuild the torch PRML2 model of an exported ONNX file: ``(model, checkpoint-like dict, info)``.

    The config and statistics come from the metadata; the weights from the graph's initialisers:
    by parameter name, and for each ``Linear`` the exporter turned into ``/<module path>/MatMul``
    with a constant (transposed) weight, from that node. Raises :class:`ModelError` unless every
    parameter is found, so a re-export (say to a newest-row streaming graph) computes the same
    numbers as the original. ``info``: ``{"weights_loaded", "weights_total"}``.
    """
    import onnx
    from onnx import numpy_helper

    from prml2_edge.training.presets import model_config_from_dict

    proto = onnx.load(str(path))
    props = {p.key: p.value for p in proto.metadata_props}
    if METADATA_KEY not in props:
        raise ModelError(f"{path}: no PRML2 metadata (key {METADATA_KEY!r}); not a 'prml2 export' model")
    meta = ModelMetadata.from_json(props[METADATA_KEY], str(path))
    try:
        cfg = model_config_from_dict({k: v for k, v in meta.config.items() if k not in ("z_mean", "z_std")})
    except Exception as exc:  # noqa: BLE001 - a baseline or foreign config
        raise ModelError(f"{path}: not a PRML2 transformer model ({exc})") from exc
    model = Prml2Model(cfg, meta.norm_mean, meta.norm_std, meta.config.get("z_mean", [0.0] * schema.NUM_STATES),
                       meta.config.get("z_std", [1.0] * schema.NUM_STATES))
    def unwrapped(name: str) -> str:  # a newest-rows export holds the model as the submodule "model"
        return name[len("model."):] if name.startswith("model.") else name

    inits = {t.name: numpy_helper.to_array(t) for t in proto.graph.initializer}
    inits.update({unwrapped(k): v for k, v in list(inits.items())})
    for node in proto.graph.node:  # Linear -> MatMul(x, W^T) (+ Add bias) under the module's path
        if node.op_type == "MatMul" and node.name.endswith("/MatMul") and node.input[1] in inits:
            module = unwrapped(node.name[1 : -len("/MatMul")].replace("/", "."))
            inits.setdefault(f"{module}.weight", inits[node.input[1]].T)
    state = model.state_dict()
    missing = []
    with torch.no_grad():
        for name, tensor in state.items():
            arr = inits.get(name)
            if arr is not None and tuple(arr.shape) == tuple(tensor.shape):
                tensor.copy_(torch.as_tensor(np.array(arr)))
            elif name not in ("z_mean", "z_std"):  # those two come from the metadata
                missing.append(name)
    if missing:
        raise ModelError(f"{path}: cannot recover {len(missing)} weight tensor(s) from the graph "
                         f"(first {missing[0]!r}); export from the checkpoint instead")
    model.load_state_dict(state)
    ckpt = {"preset": meta.preset, "dataset_fingerprint": meta.dataset_fingerprint, "training": meta.training}
    return model.eval(), ckpt, {"weights_loaded": len(state) - len(missing), "weights_total": len(state)}


def set_metadata(proto, metadata: ModelMetadata) -> None:
    """Put ``metadata`` JSON under ``metadata_props[METADATA_KEY]`` of an ONNX ModelProto (replacing any)."""
    keep = [p for p in proto.metadata_props if p.key != METADATA_KEY]
    del proto.metadata_props[:]
    for p in keep:
        proto.metadata_props.add(key=p.key, value=p.value)
    proto.metadata_props.add(key=METADATA_KEY, value=metadata.to_json())
    proto.producer_name = "prml2-edge"
    proto.producer_version = __version__


def read_metadata(path: str | Path) -> ModelMetadata:
    """The PRML2 metadata of an ONNX file (via onnxruntime, as the runtime reads it)."""
    import onnxruntime as ort

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    props = sess.get_modelmeta().custom_metadata_map
    if METADATA_KEY not in props:
        raise ModelError(f"{path}: no PRML2 metadata (key {METADATA_KEY!r})")
    return ModelMetadata.from_json(props[METADATA_KEY], str(path))


def ort_session(path: str | Path):
    """A single-threaded CPU onnxruntime session for ``path`` (deterministic numbers)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.inter_op_num_threads = 1
    return ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])


def run_ort(session, windows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Run the (1, L, 9) graph over ``windows`` (n, L, 9) one at a time: ``(mean, var)`` (n, L-H, 5)."""
    means, variances = [], []
    for w in np.asarray(windows, dtype=np.float32):
        m, v = session.run(list(OUTPUT_NAMES), {INPUT_NAME: w[None]})
        means.append(m[0])
        variances.append(v[0])
    return np.stack(means), np.stack(variances)


def parity(model: Prml2Model, onnx_path: str | Path, windows: np.ndarray) -> dict[str, float]:
    """Max abs difference between torch (every decoder step) and onnxruntime over ``windows`` (n, L, 9), on
    the rows the graph returns: ``{"mean", "var", "n"}``."""
    session = ort_session(onnx_path)
    o_mean, o_var = run_ort(session, windows)
    with torch.no_grad():
        t_mean, t_var = model.eval()(torch.as_tensor(np.asarray(windows, dtype=np.float32)))
    rows = o_mean.shape[1]
    t_mean, t_var = t_mean[:, -rows:], t_var[:, -rows:]
    return {"mean": float(np.max(np.abs(o_mean - t_mean.numpy()))),
            "var": float(np.max(np.abs(o_var - t_var.numpy()))),
            "n": int(len(windows))}


def quantize_int8(fp32_path: str | Path, int8_path: str | Path) -> Path:
    """Dynamic int8 quantisation (onnxruntime ``quantize_dynamic``) of the transformer's MatMul weights.

    The layers in :data:`prml2_edge.training.quantize.PRML2_KEEP_FP32` (input projection, head, skip: the
    output head and the skip carry the fine resolution of the outputs, int8 weights there cost ~2.5x the
    yaw-rate RMSE) stay float32; the metadata is carried over with ``training["int8"] = True``
    (:func:`prml2_edge.training.quantize.quantize_int8` does the work).
    """
    from prml2_edge.training import quantize

    return quantize.quantize_int8(fp32_path, int8_path, keep_fp32=quantize.PRML2_KEEP_FP32)


def compare_int8(fp32_path: str | Path, int8_path: str | Path, windows: np.ndarray, z_gt: np.ndarray) -> dict:
    """z RMSE per state of the fp32 and int8 graphs on ``windows`` (n, L, 9) against ``z_gt`` (n, L-H, 5),
    over the decoder steps the graphs return (the newest ones).

    Returns ``{"fp32": {state: rmse}, "int8": {...}, "max_abs_mean_diff": float, "n_windows": n}``
    (before the guard, SI units).
    """
    f_mean, _ = run_ort(ort_session(fp32_path), windows)
    q_mean, _ = run_ort(ort_session(int8_path), windows)
    z_gt = np.asarray(z_gt, dtype=np.float64)[:, -f_mean.shape[1]:]

    def rmse(mean: np.ndarray) -> dict[str, float]:
        err = mean.astype(np.float64) - z_gt
        return {name: float(np.sqrt(np.mean(err[..., i] ** 2))) for i, name in enumerate(schema.STATE_NAMES)}

    return {"fp32": rmse(f_mean), "int8": rmse(q_mean), "max_abs_mean_diff": float(np.max(np.abs(f_mean - q_mean))),
            "n_windows": int(len(windows))}
