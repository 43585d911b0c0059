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

A streaming graph that returns only the newest ``R`` decoder steps (``output_rows``, see
:mod:`prml2_edge.model_meta`) computes R query rows in its last decoder layer: there T becomes R
everywhere except in the self-attention's K and V projections (still on all T rows, ``4 T d^2``),
and the scores read ``4 R T d`` (self) and ``4 R H d`` (cross); the head and skip run on R rows.
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


def _decoder_layer(d: int, f: int, H: int, T: int, R: int) -> int:
    """One decoder layer computing R of its T query rows (R = T: the full layer)."""
    self_attn = 4 * R * d * d + 4 * T * d * d + 4 * R * T * d  # Q, out on R rows; K, V on T rows; scores
    cross_attn = 4 * R * d * d + 4 * H * d * d + 4 * R * H * d  # Q, out on R rows; K, V on H memory rows
    return self_attn + cross_attn + 4 * R * d * f


def inference_flops(config: Mapping, output_rows: int | None = None) -> dict:
    """FLOPs of one forward pass, by part: ``{"total", "input_proj", "encoder", "decoder", "head", "per_layer"}``.

    ``config`` is the model config as the ONNX metadata carries it (``d_model``, ``d_ff``,
    ``n_layers``, ``window_len``, ``encoder_len``; ``num_signals``, ``num_states``);
    ``output_rows`` the decoder steps the graph returns (None: all T).
    """
    d, f, n, L, H, T, m, s = _cfg(config)
    R = T if output_rows is None else int(output_rows)
    if not 1 <= R <= T:
        raise ValueError(f"output_rows must be in [1, {T}], got {output_rows}")
    enc_layer = 8 * H * d * d + 4 * H * H * d + 4 * H * d * f
    dec_layer = _decoder_layer(d, f, H, T, T)
    parts = {
        "input_proj": 2 * L * m * d,
        "encoder": n * enc_layer,
        "decoder": (n - 1) * dec_layer + _decoder_layer(d, f, H, T, R),
        "head": 2 * R * d * 2 * s + 2 * R * m * s,
    }
    return {"total": sum(parts.values()), **parts, "output_rows": R,
            "per_layer": {"encoder": enc_layer, "decoder": dec_layer}}


def gemm_shapes(config: Mapping) -> list[tuple[int, int, int]]:
    """The model's large matrix products as ``(m, k, n)``: projections and feed-forward on H and T rows."""
    d, f, _, _, H, T, _, _ = _cfg(config)
    return [(H, d, d), (H, d, f), (H, f, d), (T, d, d), (T, d, f), (T, f, d)]
