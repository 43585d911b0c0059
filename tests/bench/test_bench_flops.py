"""Analytic FLOPs of one inference (the benchmarks' fraction-of-GEMM figure) against torch's own count."""

from __future__ import annotations

from dataclasses import asdict

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from prml2_edge.bench.flops import inference_flops  # noqa: E402
from prml2_edge.training.model import Prml2Model  # noqa: E402
from prml2_edge.training.presets import ModelConfig  # noqa: E402


@pytest.mark.parametrize("rows", [None, 1, 10])
def test_analytic_flops_match_torchs_flop_counter(rows, monkeypatch):
    from torch.utils.flop_counter import FlopCounterMode

    import prml2_edge.training.model as model_module

    # the attention written out as MatMul/Softmax (the exported graph's form): the counter sees its products
    monkeypatch.setattr(model_module, "_exporting", lambda: True)
    cfg = ModelConfig(d_model=32, n_heads=4, n_layers=2, d_ff=48)
    model = Prml2Model(cfg, np.zeros(9), np.ones(9), np.zeros(5), np.ones(5)).eval()
    counter = FlopCounterMode(display=False)
    with torch.no_grad(), counter:
        model(torch.zeros(1, cfg.window_len, 9), rows=rows)
    counted = counter.get_total_flops()
    analytic = inference_flops(asdict(cfg), rows)
    assert analytic["total"] == pytest.approx(counted, rel=1e-9)
    assert analytic["output_rows"] == (rows or cfg.window_len - cfg.encoder_len)


def test_newest_row_graph_saves_most_of_the_last_decoder_layer():
    cfg = asdict(ModelConfig(d_model=512, n_heads=8, n_layers=2, d_ff=2048))
    full, one = inference_flops(cfg)["total"], inference_flops(cfg, 1)["total"]
    assert 0.15 < 1 - one / full < 0.20  # paper size: the last of 4 layers shrinks to its K/V projections
    with pytest.raises(ValueError, match="output_rows"):
        inference_flops(cfg, 0)
