"""int8 variants of a PRML2 ONNX model for ``prml2 export --int8`` and the latency benchmark (dynamic quantisation).

Dynamic quantisation stores the MatMul weights as int8 and quantises activations at run
time (u8 x s8 products, the AVX-512 VNNI / Arm dot-product path). It needs the ``onnx``
package (part of the ``train`` extra); :func:`int8_available` says whether this install has it.
The PRML2 metadata is carried over with ``training["int8"] = True``.
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
# (9 -> 5). Together under 1 % of the FLOPs, but rounding them costs up to 37 % z RMSE (benchmarks/README.md).
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
                         nodes_to_exclude=exclude, extra_options={"MatMulConstBOnly": bool(weights_only)})
    finally:
        root.setLevel(level)
    props = {p.key: p.value for p in onnx.load(str(src), load_external_data=False).metadata_props}
    if METADATA_KEY not in props:
        raise ModelError(f"{src}: no PRML2 metadata to carry over")
    meta = json.loads(props[METADATA_KEY])
    meta["training"] = {**meta.get("training", {}), "int8": True}
    proto = onnx.load(str(dst))
    keep = [(p.key, p.value) for p in proto.metadata_props if p.key != METADATA_KEY]
    del proto.metadata_props[:]
    for key, value in keep:
        proto.metadata_props.add(key=key, value=value)
    proto.metadata_props.add(key=METADATA_KEY, value=json.dumps(meta, sort_keys=True))
    onnx.save(proto, str(dst))
    return dst


def quantize_prml2(src: str | Path, dst: str | Path) -> Path:
    """The int8 recipe the benchmarks use for PRML2 models: per-channel s8 weights, constant-weight products
    only, first and last layers in fp32 (:data:`PRML2_KEEP_FP32`)."""
    return quantize_int8(src, dst, per_channel=True, keep_fp32=PRML2_KEEP_FP32, weights_only=True)
