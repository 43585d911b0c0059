"""Models for the full benchmarks: the shipped edge model and a paper-size model, fp32 and int8.

* ``edge``: ``export/default/prml2_edge.onnx`` when it is there (trained); otherwise the edge
  preset exported with initial weights (latency does not depend on the weights; the int8 RMSE
  check then says "untrained").
* ``paper``: the paper's size (d = 512, 8 heads, 2 layers, d_ff = 2048, L = 250, H = 150). Training
  it needs a GPU, so it is exported with initial transformer weights but with the dataset's
  normalisation, z statistics and the least-squares linear skip fitted on the training split, so
  its outputs are physically meaningful and the int8-vs-fp32 RMSE compares like with like.

The torch twin of each ONNX model (same config and weights) feeds the torch-eager pipeline.
"""

from __future__ import annotations

import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from prml2_edge import schema
from prml2_edge.training.export_onnx import export_onnx, metadata_for, model_from_onnx
from prml2_edge.training.model import Prml2Model
from prml2_edge.training.presets import get_preset
from prml2_edge.training.quantize import quantize_int8, quantize_prml2

sys.path.insert(0, str(Path(__file__).resolve().parent))
from paths import DATASET, MODEL_DIR, REPO, SHIPPED_EDGE  # noqa: E402


@dataclass
class BenchModel:
    name: str  # "edge" | "paper"
    fp32: Path  # streaming graph: the newest decoder step only (what the runtime consumes; prml2 export's default)
    fp32_all: Path  # every decoder step (the graph before streaming exports), for the side-by-side
    int8: Path  # quantize_prml2: per-channel, weights only, first/last layers fp32
    int8_plain: Path  # onnxruntime's defaults (per tensor, every MatMul): for the RMSE comparison only
    torch_model: Prml2Model
    config: dict  # ModelConfig as plain data
    trained: bool
    source: str


def _dataset_stats(dataset_root: Path):
    """(norm_mean, norm_std, z_mean, z_std, onboard rows, z rows) of the training split, or None."""
    try:
        from prml2_edge.data.datasets import load_dataset
        from prml2_edge.training.trainer import z_statistics

        ds = load_dataset(dataset_root)
    except Exception:  # noqa: BLE001 - no dataset here: plain statistics
        return None
    train = [d for d in ds.split("train") if d.has_ground_truth]
    z_rows = np.concatenate([d.z_gt for d in train])
    z_mean, z_std = z_statistics(z_rows)
    return ds.norm_mean, ds.norm_std, z_mean, z_std, np.concatenate([d.onboard for d in train]), z_rows


def prepare(name: str, out_dir: Path = MODEL_DIR, seed: int = 0, checkpoint: str | Path | None = None) -> BenchModel:
    """Export (or find) model ``name`` and its int8 variants under ``out_dir``.

    ``checkpoint``: a trained checkpoint (``runs/<name>/best.pt``) to export instead; its torch model is
    then the exact twin of the ONNX graph.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    ckpt: dict = {"preset": name}
    stem = name
    if checkpoint is not None:
        from prml2_edge.training.checkpoint import load_model

        model, ckpt = load_model(checkpoint)
        stem = f"{name}_trained"
        trained = True
        source = (f"{ckpt.get('preset')} preset trained checkpoint {checkpoint} (epoch {ckpt.get('epoch')}, "
                  f"stage {ckpt.get('stage')}), exported here")
    elif name == "edge" and SHIPPED_EDGE.is_file():
        model, ckpt, info = model_from_onnx(SHIPPED_EDGE)
        stem = "edge_shipped"
        trained, source = True, f"shipped {SHIPPED_EDGE.relative_to(REPO)}"
        source += (f" (torch twin: {info['weights_loaded']}/{info['weights_total']} tensors from the ONNX file, "
                   "re-exported here)")
    else:
        torch.manual_seed(seed)
        cfg = get_preset(name).model
        stats = _dataset_stats(DATASET)
        if stats is None:
            model = Prml2Model(cfg, np.zeros(schema.NUM_SIGNALS), np.ones(schema.NUM_SIGNALS),
                               np.zeros(schema.NUM_STATES), np.ones(schema.NUM_STATES))
            source = f"{name} preset, initial weights (seed {seed})"
        else:
            norm_mean, norm_std, z_mean, z_std, rows, z_rows = stats
            model = Prml2Model(cfg, norm_mean, norm_std, z_mean, z_std)
            model.init_skip(rows, z_rows)
            source = (f"{name} preset, initial transformer weights (seed {seed}), linear skip fitted on "
                      f"{DATASET.relative_to(REPO)} train split")
        trained = False
    model.eval()
    fp32_all = export_onnx(model, metadata_for(model, ckpt), out_dir / f"{stem}_all_rows.onnx")
    fp32 = export_onnx(model, metadata_for(model, ckpt), out_dir / f"{stem}.onnx", rows=1)
    int8 = quantize_prml2(fp32, out_dir / f"{fp32.stem}_int8.onnx")
    int8_plain = quantize_int8(fp32, out_dir / f"{fp32.stem}_int8_plain.onnx")
    return BenchModel(name, fp32, fp32_all, int8, int8_plain, model.eval(), asdict(model.cfg), trained, source)


def test_windows(stride: int = 20, limit: int = 600):
    """(onboard (n, L, 9), z (n, L - H, 5)) test-split windows of the benchmark dataset, or None."""
    try:
        from prml2_edge.data.datasets import load_dataset
        from prml2_edge.data.windows import build_windows

        ds = load_dataset(DATASET)
    except Exception:  # noqa: BLE001
        return None
    drives = [d for d in ds.split("test") if d.has_ground_truth]
    ws = build_windows(drives, stride=stride)
    idx = np.arange(min(len(ws), limit))
    onboard, z, _ = ws.get(idx)
    return onboard, z[:, schema.ENCODER_LEN:]


def paper_config() -> dict:
    """The paper-size model config as plain data (for the GEMM shapes)."""
    return asdict(get_preset("paper").model)


if __name__ == "__main__":
    bm = prepare(sys.argv[1], seed=int(sys.argv[2]) if len(sys.argv) > 2 else 0,
                 checkpoint=sys.argv[3] if len(sys.argv) > 3 else None)
    print(json.dumps({"fp32": str(bm.fp32), "fp32_all": str(bm.fp32_all), "int8": str(bm.int8), "source": bm.source,
                      "trained": bm.trained}))
