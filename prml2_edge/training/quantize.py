"""Faster variants of a PRML2 ONNX model for ``prml2 export`` and ``prml2 bench``: int8 and fused graphs.

* **Dynamic int8** (:func:`quantize_int8`, :func:`quantize_prml2`; ``prml2 export --int8``): the MatMul
  weights stored as int8, the activations quantised at run time (u8 x s8 products, the AVX-512 VNNI /
  Arm dot-product path).
* **Static int8, QDQ** (:func:`quantize_static_int8`; ``prml2 export --int8 static``): the activation
  scales are calibrated once, on windows of simulated drives (:func:`simulated_windows`, the project's
  simulator; never the test data), and stored in QuantizeLinear/DequantizeLinear pairs that
  onnxruntime folds into integer kernels; no run-time min/max pass over the activations.
* **Fused graph** (:func:`optimize_transformer`; ``prml2 export --optimize``): onnxruntime's offline
  transformer optimiser (``onnxruntime.transformers.optimizer``, BERT fusions); it reports which fusions
  applied.

Every variant is a plain ONNX graph (standard and ``com.microsoft`` operators) that the edge install
(onnxruntime, no torch, no onnx) runs; making one needs the ``onnx`` package (part of the ``train``
extra); :func:`int8_available` says whether this install has it. The PRML2 metadata is carried over
with ``training["int8"] = True`` (and ``training["variant"]`` naming the recipe).
"""

from __future__ import annotations

import importlib.util
import json
from collections.abc import Sequence
from pathlib import Path

from prml2_edge.errors import ModelError
from prml2_edge.model_meta import METADATA_KEY

# Module-path parts of PRML2 node names (torch exporter names) kept in fp32 by :func:`quantize_prml2` and
# ``prml2 export --int8``: the input projection (9 -> d), the output head (d -> 10) and the linear skip
# (9 -> 5). Together under 1 % of the FLOPs, but rounding them costs up to 37 % z RMSE (docs/benchmarks.md).
PRML2_KEEP_FP32 = ("/input_proj/", "/head/", "/skip/")


def int8_available() -> bool:
    """True when onnxruntime's quantisation tool can run here (it needs ``onnx``)."""
    return importlib.util.find_spec("onnx") is not None


def quantize_int8(src: str | Path, dst: str | Path, per_channel: bool = False, keep_fp32: Sequence[str] = (),
                  weights_only: bool = False) -> Path:
    """Write the dynamically int8-quantised ``src`` to ``dst`` (weights s8, per tensor or per output channel).

    ``keep_fp32``: module-path parts of node names (``"/head/"``) left in fp32 (e.g. a model's tiny
    first and last layers, where rounding costs accuracy and saves nothing); ``weights_only``:
    quantise only products with a constant weight (not the attention's activation x activation products).
    """
    if not int8_available():
        raise ModelError("int8 quantisation needs the 'onnx' package (pip install 'prml2-edge[train]')")
    import logging

    import onnx
    from onnxruntime.quantization import QuantType, quantize_dynamic

    src, dst = Path(src), Path(dst)
    root = logging.getLogger()
    level = root.level
    root.setLevel(logging.ERROR)  # the tool logs a pre-processing hint at WARNING on every call
    try:
        exclude = []
        if keep_fp32:
            graph = onnx.load(str(src), load_external_data=False).graph
            # substring match: in a newest-rows (streaming) export the module names sit under "/model/"
            exclude = [n.name for n in graph.node if any(prefix in n.name for prefix in keep_fp32)]
        quantize_dynamic(str(src), str(dst), weight_type=QuantType.QInt8, per_channel=per_channel,
                         nodes_to_exclude=exclude, extra_options={"MatMulConstBOnly": bool(weights_only),
                                        "DefaultTensorType": onnx.TensorProto.FLOAT})
    finally:
        root.setLevel(level)
    _carry_metadata(src, dst, {"int8": True})
    return dst


def _read_prml2_meta(src: str | Path) -> dict:
    import onnx

    props = {p.key: p.value for p in onnx.load(str(src), load_external_data=False).metadata_props}
    if METADATA_KEY not in props:
        raise ModelError(f"{src}: no PRML2 metadata to carry over")
    return json.loads(props[METADATA_KEY])


def _carry_metadata(src: str | Path, dst: str | Path, training: dict) -> None:
    """Copy the PRML2 metadata of ``src`` into ``dst`` (rewritten in place), ``training`` merged into its
    ``training`` entry."""
    import onnx

    meta = _read_prml2_meta(src)
    meta["training"] = {**meta.get("training", {}), **training}
    proto = onnx.load(str(dst))
    keep = [(p.key, p.value) for p in proto.metadata_props if p.key != METADATA_KEY]
    del proto.metadata_props[:]
    for key, value in keep:
        proto.metadata_props.add(key=key, value=value)
    proto.metadata_props.add(key=METADATA_KEY, value=json.dumps(meta, sort_keys=True))
    onnx.save(proto, str(dst))


def quantize_prml2(src: str | Path, dst: str | Path) -> Path:
    """The int8 recipe the benchmarks use for PRML2 models: per-channel s8 weights, constant-weight products
    only, first and last layers in fp32 (:data:`PRML2_KEEP_FP32`)."""
    return quantize_int8(src, dst, per_channel=True, keep_fp32=PRML2_KEEP_FP32, weights_only=True)


# Seeds of the simulated drives that calibrate static int8 and of those that measure the accuracy change
# (``prml2 bench``); the benchmark dataset's drives use seeds 3000 and up, so neither overlaps it.
CALIBRATION_SEED = 7000
ACCURACY_SEED = 8000
_SIM_PLAN = (("reference", "mixed", 1.0), ("compact_fwd", "lateral", 0.9), ("rwd_sedan", "longitudinal", 1.0),
             ("van_fwd", "mixed", 0.85), ("suv_awd", "lateral", 1.0), ("city_fwd", "snow", 0.3))


def simulated_windows(n: int, seed: int = CALIBRATION_SEED, L: int | None = None, H: int | None = None,
                      minutes: float = 1.0):
    """``n`` windows of simulated drives: ``(onboard (n, L, 9) float32 raw SI, z (n, L - H, 5) float32)``.

    Six drives of ``minutes`` each (seeds ``seed``, ``seed + 1``, ...) on six cars of the simulated fleet,
    dry longitudinal / lateral / mixed driving and one snow drive, windows spread evenly over them. The
    project's simulator (:func:`prml2_edge.data.simulate.simulate_drive`), torch-free.
    """
    import numpy as np

    from prml2_edge import schema
    from prml2_edge.data.simulate import simulate_drive
    from prml2_edge.data.windows import build_windows

    L = schema.WINDOW_LEN if L is None else int(L)
    H = schema.ENCODER_LEN if H is None else int(H)
    if n < 1:
        raise ModelError(f"need at least one window, got {n}")
    drives = [simulate_drive(minutes, mu, seed + k, family, vehicle=car)
              for k, (car, family, mu) in enumerate(_SIM_PLAN)]
    windows = build_windows(drives, L=L, H=H, stride=1)
    if len(windows) == 0:
        raise ModelError(f"simulated drives of {minutes:g} min are shorter than the window ({L} samples)")
    idx = np.linspace(0, len(windows) - 1, min(n, len(windows))).round().astype(int)
    onboard, z, _ = windows.get(idx)
    return onboard.astype(np.float32), z[:, H:].astype(np.float32)


class _WindowReader:
    """onnxruntime ``CalibrationDataReader`` over (n, L, 9) windows, one (1, L, 9) input per call."""

    def __init__(self, input_name: str, windows) -> None:
        import numpy as np

        self.input_name = input_name
        self.windows = np.asarray(windows, dtype=np.float32)
        self.i = 0

    def get_next(self):
        if self.i >= len(self.windows):
            return None
        self.i += 1
        return {self.input_name: self.windows[self.i - 1][None]}

    def rewind(self) -> None:
        self.i = 0


STATIC_ACTIVATIONS = ("u8", "s8")


def quantize_static_int8(src: str | Path, dst: str | Path, windows, keep_fp32: Sequence[str] = PRML2_KEEP_FP32,
                         activation: str = "u8", per_channel: bool = True, weights_only: bool = True,
                         method: str = "minmax", quantize_outputs: bool = True) -> Path:
    """Write the statically int8-quantised (QDQ) ``src`` to ``dst``, calibrated on ``windows`` (n, L, 9) float32.

    The recipe of :func:`quantize_prml2` with calibrated activation scales: per-channel s8 weights,
    ``activation`` u8 (the x86 VNNI u8 x s8 path, the default) or s8 activations, products with a
    constant weight only (``weights_only``; the attention's activation x activation products stay
    float), :data:`PRML2_KEEP_FP32` in fp32; ``method`` minmax, percentile or entropy calibration.
    """
    if not int8_available():
        raise ModelError("int8 quantisation needs the 'onnx' package (pip install 'prml2-edge[train]')")
    if activation not in STATIC_ACTIVATIONS:
        raise ModelError(f"activation type must be one of {', '.join(STATIC_ACTIVATIONS)}, got {activation!r}")
    import logging
    import tempfile

    import onnx
    from onnxruntime.quantization import (
        CalibrationDataReader,
        CalibrationMethod,
        QuantFormat,
        QuantType,
        quantize_static,
    )

    methods = {"minmax": CalibrationMethod.MinMax, "percentile": CalibrationMethod.Percentile,
               "entropy": CalibrationMethod.Entropy}
    if method not in methods:
        raise ModelError(f"calibration method must be one of {', '.join(methods)}, got {method!r}")
    if len(windows) == 0:
        raise ModelError("static int8 needs calibration windows, got none")
    src, dst = Path(src), Path(dst)
    meta = _read_prml2_meta(src)
    reader_cls = type("PRML2WindowReader", (_WindowReader, CalibrationDataReader), {})
    reader = reader_cls(meta.get("input_name", "onboard"), windows)
    graph = onnx.load(str(src), load_external_data=False).graph
    exclude = [n.name for n in graph.node if any(part in n.name for part in keep_fp32)]
    root = logging.getLogger()
    level = root.level
    root.setLevel(logging.ERROR)  # the tool logs a pre-processing hint at WARNING on every call
    try:
        with tempfile.TemporaryDirectory(prefix="prml2-calib-") as tmp:
            quantize_static(str(src), str(dst), reader, quant_format=QuantFormat.QDQ,
                            activation_type=QuantType.QUInt8 if activation == "u8" else QuantType.QInt8,
                            weight_type=QuantType.QInt8, per_channel=per_channel, op_types_to_quantize=["MatMul"],
                            nodes_to_exclude=exclude, calibrate_method=methods[method],
                            calibration_providers=["CPUExecutionProvider"],
                            extra_options={"MatMulConstBOnly": bool(weights_only), "CalibTensorRangeSymmetric": False,
                                           "OpTypesToExcludeOutputQuantization": [] if quantize_outputs else ["MatMul"],
                                           "CalibIntermediateOutputPath": str(Path(tmp) / "calib.onnx")})
    finally:
        root.setLevel(level)
    _carry_metadata(src, dst, {"int8": True, "variant": f"static-qdq-{activation}",
                               "calibration": {"windows": int(len(windows)), "method": method}})
    return dst


def optimize_transformer(src: str | Path, dst: str | Path, attention: bool = True, ort_fusions: bool = False) -> dict:
    """Write ``src`` optimised to ``dst``: the project's attention fusion (:mod:`prml2_edge.training.fusion`;
    ``attention``), and with ``ort_fusions`` also onnxruntime's offline transformer optimiser (BERT fusions, CPU).

    ``prml2 export --optimize`` is the attention fusion alone: measured on the paper-size graph
    (``benchmarks/paper_variants.py``), the optimiser's own fusions (SkipLayerNormalization over every
    residual + LayerNorm, BiasGelu) run slower than what onnxruntime fuses at session start by itself
    (LayerNormalization and Gelu after Gemm), and it fuses none of the attentions.

    Returns the fusions that applied, e.g. ``{"MultiHeadAttention": 6}`` and with ``ort_fusions`` the
    optimiser's statistics (``"ort_Attention"``: the attentions its own fusion found), and records them in
    the metadata (``training["variant"] = "optimized"``, ``training["fusions"]``).
    """
    if not int8_available():
        raise ModelError("the transformer optimiser needs the 'onnx' package (pip install 'prml2-edge[train]')")
    import logging
    import tempfile

    import onnx

    from prml2_edge.training.fusion import fuse_attention

    src, dst = Path(src), Path(dst)
    meta = _read_prml2_meta(src)
    cfg = meta.get("config", {})
    if "n_heads" not in cfg or "d_model" not in cfg:
        raise ModelError(f"{src}: not a PRML2 transformer (no n_heads/d_model in its metadata); nothing to fuse")
    proto = onnx.load(str(src))
    n_mha = fuse_attention(proto) if attention else 0
    fused: dict[str, int] = {"MultiHeadAttention": n_mha} if n_mha else {}
    if not ort_fusions:
        onnx.checker.check_model(proto)
        onnx.save(proto, str(dst))
    else:
        from onnxruntime.transformers import optimizer
        from onnxruntime.transformers.fusion_options import FusionOptions

        quiet = [logging.getLogger(name) for name in ("onnxruntime.transformers", "")]
        levels = [lg.level for lg in quiet]
        for lg in quiet:
            lg.setLevel(logging.ERROR)  # "Model producer not matched" and per-fusion INFO lines
        try:
            with tempfile.TemporaryDirectory(prefix="prml2-opt-") as tmp:
                staged = Path(tmp) / "attention.onnx"
                onnx.save(proto, str(staged))
                model = optimizer.optimize_model(str(staged), model_type="bert", num_heads=int(cfg["n_heads"]),
                                                 hidden_size=int(cfg["d_model"]),
                                                 optimization_options=FusionOptions("bert"), opt_level=0,
                                                 use_gpu=False)
                stats = model.get_fused_operator_statistics()
                model.save_model_to_file(str(dst))
        finally:
            for lg, lv in zip(quiet, levels, strict=True):
                lg.setLevel(lv)
        fused.update({k: int(v) for k, v in stats.items() if v and k not in ("MultiHeadAttention", "Attention")})
        # the optimiser counts every MultiHeadAttention node in the graph, the pass's included
        fused["ort_Attention"] = int(stats.get("Attention", 0)) + max(0, int(stats.get("MultiHeadAttention", 0))
                                                                       - n_mha)
    _carry_metadata(src, dst, {"variant": "optimized" if not ort_fusions else "optimized-ort", "fusions": fused})
    return fused


def graph_metadata(path: str | Path):
    """The PRML2 :class:`~prml2_edge.model_meta.ModelMetadata` of an ONNX file, read with onnxruntime (torch-
    and onnx-free)."""
    import onnxruntime as ort

    from prml2_edge.model_meta import ModelMetadata

    opts = ort.SessionOptions()
    opts.log_severity_level = 3
    props = ort.InferenceSession(str(path), sess_options=opts,
                                 providers=["CPUExecutionProvider"]).get_modelmeta().custom_metadata_map
    if METADATA_KEY not in props:
        raise ModelError(f"{path}: no PRML2 metadata (key {METADATA_KEY!r})")
    return ModelMetadata.from_json(props[METADATA_KEY], str(path))


def run_windows(path: str | Path, windows, threads: int = 1):
    """``(mean, var)`` (n, R, 5) of the graph ``path`` over ``windows`` (n, L, 9), one window per call, in a
    single-threaded CPU session (torch-free; the runtime's graph contract)."""
    import numpy as np
    import onnxruntime as ort

    from prml2_edge.model_meta import INPUT_NAME, OUTPUT_NAMES

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = int(threads)
    opts.inter_op_num_threads = 1
    opts.log_severity_level = 3
    sess = ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])
    out = [sess.run(list(OUTPUT_NAMES), {INPUT_NAME: w[None]}) for w in np.asarray(windows, dtype=np.float32)]
    return np.stack([m[0] for m, _ in out]), np.stack([v[0] for _, v in out])


def max_output_difference(ref: str | Path, path: str | Path, windows) -> dict:
    """Largest ``|d mean|`` and ``|d var|`` between graphs ``ref`` and ``path`` over ``windows``."""
    import numpy as np

    (m0, v0), (m1, v1) = run_windows(ref, windows), run_windows(path, windows)
    return {"mean": float(np.max(np.abs(m1 - m0))), "var": float(np.max(np.abs(v1 - v0))), "n": int(len(windows))}


def z_rmse_change(ref: str | Path, path: str | Path, windows, z) -> dict:
    """z RMSE per state (before the guard) of graphs ``ref`` (fp32) and ``path`` on ``windows`` (n, L, 9)
    against ``z`` (n, L - H, 5), over the decoder steps the graphs return, and the relative change:
    ``{"ref": {state: rmse}, "variant": {...}, "relative_change": {...}, "max_abs_relative_change", "n_windows"}``."""
    import numpy as np

    from prml2_edge import schema

    (m0, _), (m1, _) = run_windows(ref, windows), run_windows(path, windows)
    truth = np.asarray(z, dtype=np.float64)[:, -m0.shape[1]:]

    def rmse(mean):
        err = mean.astype(np.float64) - truth
        return {name: float(np.sqrt(np.mean(err[..., i] ** 2))) for i, name in enumerate(schema.STATE_NAMES)}

    a, b = rmse(m0), rmse(m1)
    rel = {k: (b[k] - a[k]) / a[k] if a[k] > 0 else 0.0 for k in a}
    return {"ref": a, "variant": b, "relative_change": rel,
            "max_abs_relative_change": max(abs(v) for v in rel.values()), "n_windows": int(len(windows))}
