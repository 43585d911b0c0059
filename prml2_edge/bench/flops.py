"""Analytic FLOPs of one PRML2 inference (one window), from the model config in the ONNX metadata.

A multiply-add counts 2 FLOPs; only the matrix products are counted (LayerNorm, softmax, GELU,
the normalisation and residual adds are O(n d) and below 1 % of the total at paper size).
With ``d`` = d_model, ``f`` = d_ff, ``H`` encoder steps, ``T = L - H`` decoder steps,
``m`` = 9 signals, ``s`` = 5 states and ``N`` layers (each of encoder and decoder)::

    input projection            2 L m d
    encoder layer (x N)         8 H d^2      (Q, K, V, output projections)
                              + 4 H^2 d      (scores Q K^T and weights @ V, all heads)
                              + 4 H d f      (feed-forward d -> f -> d)
    decoder layer (x N)         8 T d^2 + 4 T^2 d              (self-attention)
                              + 4 T d^2 + 4 H d^2 + 4 T H d    (cross-attention: Q, out on T; K, V on H)
                              + 4 T d f                        (feed-forward)
    head and skip               2 T d (2 s) + 2 T m s
"""

from __future__ import annotations

from collections.abc import Mapping


def _cfg(config: Mapping) -> tuple[int, int, int, int, int, int, int, int]:
    try:
        d = int(config["d_model"])
        f = int(config["d_ff"])
        n = int(config["n_layers"])
        L = int(config["window_len"])
        H = int(config["encoder_len"])
    except KeyError as exc:
        raise ValueError(f"model config lacks {exc.args[0]!r}: cannot count FLOPs") from None
    m = int(config.get("num_signals", 9))
    s = int(config.get("num_states", 5))
    return d, f, n, L, H, L - H, m, s


def inference_flops(config: Mapping) -> dict:
    """FLOPs of one forward pass, by part: ``{"total", "input_proj", "encoder", "decoder", "head", "per_layer"}``.

    ``config`` is the model config as the ONNX metadata carries it (``d_model``, ``d_ff``,
    ``n_layers``, ``window_len``, ``encoder_len``; ``num_signals``, ``num_states``).
    """
    d, f, n, L, H, T, m, s = _cfg(config)
    enc_layer = 8 * H * d * d + 4 * H * H * d + 4 * H * d * f
    dec_layer = (8 * T * d * d + 4 * T * T * d) + (4 * T * d * d + 4 * H * d * d + 4 * T * H * d) + 4 * T * d * f
    parts = {
        "input_proj": 2 * L * m * d,
        "encoder": n * enc_layer,
        "decoder": n * dec_layer,
        "head": 2 * T * d * 2 * s + 2 * T * m * s,
    }
    return {"total": sum(parts.values()), **parts, "per_layer": {"encoder": enc_layer, "decoder": dec_layer}}


def gemm_shapes(config: Mapping) -> list[tuple[int, int, int]]:
    """The model's large matrix products as ``(m, k, n)``: projections and feed-forward on H and T rows."""
    d, f, _, _, H, T, _, _ = _cfg(config)
    return [(H, d, d), (H, d, f), (H, f, d), (T, d, d), (T, d, f), (T, f, d)]
