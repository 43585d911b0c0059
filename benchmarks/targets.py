"""The issue's targets (issue 7, on 2 cores of the development machine) and how a result is judged."""

from __future__ import annotations

PAPER_FP32_P99_MS = 20.0  # paper-size fp32, end-to-end p99 per 50 Hz step
PAPER_REDUCED_P99_MS = 8.0  # paper-size int8 (or bf16), end-to-end p99
REDUCED_RMSE_CHANGE = 0.05  # |relative change| of every z RMSE with reduced precision
EDGE_P99_MS = 3.0  # edge model, end-to-end p99
EDGE_SPEEDUP_VS_TORCH = 1.5  # runtime vs torch-eager pipeline, same run (edge model)
PAPER_GEMM_FRACTION = 0.60  # paper-size fp32 model rate / measured NumPy GEMM rate
OVERHEAD_P99_MS = 1.0  # end-to-end minus model, p99
OUTSIDE_P50_MS, OUTSIDE_P99_MS = 0.25, 0.5  # issue 29: everything per step outside the model (bench.latency)
REPLAY_X_REALTIME = 20.0  # 10-minute drive, edge model
OFFLINE_X_REALTIME = 25.0  # issue 17: offline replay of a recorded log, edge model, fp32
OFFLINE_REDUCED_X_REALTIME = 100.0  # issue 17: offline replay with a reduced-precision graph ...
OFFLINE_REDUCED_RMSE_CHANGE = 0.01  # ... whose z RMSE changes by at most 1 % (every state)
RSS_GROWTH_FRACTION = 0.05  # "flat": RSS growth over the second half of the replay / RSS at half time


RUNTIME_CONFIGS = ("onnx", "onnxspin")  # the runtime as it ships (spinning off) and with [model] spinning = true


def _by_name(configs: list[dict]) -> dict[str, dict]:
    return {c["name"]: c for c in configs}


def ratios(configs: list[dict]) -> list[dict]:
    """torch-eager / runtime for e2e p50 and p99 and model p50, per model, precision fp32 and thread count."""
    by = _by_name(configs)
    out = []
    for c in configs:
        if c["runtime"] != "onnx" or c["precision"] != "fp32":
            continue
        ref = by.get(f"{c['model']}-torch-fp32-{c['threads']}t")
        if ref is None:
            continue
        out.append({"model": c["model"], "threads": c["threads"],
                    "e2e_p50": ref["e2e_ms"]["p50"] / c["e2e_ms"]["p50"],
                    "e2e_p99": ref["e2e_ms"]["p99"] / c["e2e_ms"]["p99"],
                    "model_p50": ref["model_ms"]["p50"] / c["model_ms"]["p50"]})
    return out


def fraction_of_gemm(configs: list[dict], gemm: dict) -> list[dict]:
    """Model GFLOP/s (FLOPs / model p50) over the NumPy GEMM rate at the same thread count (fp32 runtimes)."""
    out = []
    for c in configs:
        g = gemm.get(str(c["threads"]))
        if g is None or c["precision"] != "fp32":
            continue
        out.append({"name": c["name"], "model_gflops_per_s": c["model_gflops_per_s"],
                    "gemm_gflops": g["flop_weighted_gflops"],
                    "fraction": c["model_gflops_per_s"] / g["flop_weighted_gflops"]})
    return out


def _best(configs: list[dict], model: str, runtimes: tuple[str, ...], precision: str) -> dict | None:
    cands = [c for c in configs if c["model"] == model and c["runtime"] in runtimes and c["precision"] == precision
             and c["e2e_ms"].get("count")]
    return min(cands, key=lambda c: c["e2e_ms"]["p99"]) if cands else None


def _row(target: str, measured: str, met: bool | None, config: str | None = None) -> dict:
    return {"target": target, "measured": measured, "met": met, "config": config}


def latency_targets(doc: dict) -> list[dict]:
    """Each latency target with the measured figure (best thread count where the target allows a choice)."""
    configs = doc["configs"]
    rows = []
    c = _best(configs, "paper", RUNTIME_CONFIGS, "fp32")
    if c:
        p99 = c["e2e_ms"]["p99"]
        rows.append(_row(f"paper-size fp32 e2e p99 <= {PAPER_FP32_P99_MS:g} ms", f"{p99:.2f} ms",
                         p99 <= PAPER_FP32_P99_MS, c["name"]))
    c = _best(configs, "paper", RUNTIME_CONFIGS, "int8")
    if c:
        p99 = c["e2e_ms"]["p99"]
        rm = (doc.get("int8_rmse") or {}).get("paper") or {}
        change = rm.get("int8", {}).get("max_abs_relative_change")
        ok = p99 <= PAPER_REDUCED_P99_MS and change is not None and change <= REDUCED_RMSE_CHANGE
        ch = f", z RMSE change {100 * change:.1f} %" if change is not None else ", z RMSE change not measured"
        rows.append(_row(f"paper-size int8 e2e p99 <= {PAPER_REDUCED_P99_MS:g} ms and z RMSE change <= "
                         f"{100 * REDUCED_RMSE_CHANGE:g} %", f"{p99:.2f} ms{ch}", ok, c["name"]))
    c = _best(configs, "edge", RUNTIME_CONFIGS, "fp32")
    if c:
        p99 = c["e2e_ms"]["p99"]
        rows.append(_row(f"edge fp32 e2e p99 <= {EDGE_P99_MS:g} ms", f"{p99:.2f} ms", p99 <= EDGE_P99_MS, c["name"]))
    for r in doc.get("ratios", []):
        if r["model"] == "edge":
            rows.append(_row(f"edge runtime >= {EDGE_SPEEDUP_VS_TORCH:g}x faster than torch eager (e2e p50, "
                             f"{r['threads']} thread(s))", f"{r['e2e_p50']:.2f}x (p99 {r['e2e_p99']:.2f}x)",
                             r["e2e_p50"] >= EDGE_SPEEDUP_VS_TORCH, f"edge-onnx-fp32-{r['threads']}t"))
        else:
            rows.append(_row(f"{r['model']}: runtime vs torch eager (report only, {r['threads']} thread(s))",
                             f"{r['e2e_p50']:.2f}x (p99 {r['e2e_p99']:.2f}x)", None,
                             f"{r['model']}-onnx-fp32-{r['threads']}t"))
    fr = [f for f in doc.get("fraction_of_gemm", []) if f["name"].startswith("paper-onnx-fp32")]
    if fr:
        best = max(fr, key=lambda f: f["fraction"])
        rows.append(_row(f"paper-size fp32 >= {100 * PAPER_GEMM_FRACTION:g} % of the measured GEMM rate",
                         f"{100 * best['fraction']:.0f} % ({best['model_gflops_per_s']:.0f} of "
                         f"{best['gemm_gflops']:.0f} GFLOP/s)", best["fraction"] >= PAPER_GEMM_FRACTION, best["name"]))
    onnx = [c for c in configs if c["runtime"] in RUNTIME_CONFIGS and c["overhead_ms"].get("count")]
    if onnx:
        worst = max(onnx, key=lambda c: c["overhead_ms"]["p99"])
        rows.append(_row(f"pipeline overhead outside the model p99 <= {OVERHEAD_P99_MS:g} ms (worst runtime config)",
                         f"{worst['overhead_ms']['p99']:.2f} ms", worst["overhead_ms"]["p99"] <= OVERHEAD_P99_MS,
                         worst["name"]))
    c = _best(configs, "edge", ("onnx",), "fp32")
    if c and (c.get("outside_ms") or {}).get("count"):
        o = c["outside_ms"]
        rows.append(_row(f"everything outside the model per step (decode + assemble + plausibility + guard + filter "
                         f"+ sinks) p50 <= {OUTSIDE_P50_MS:g} ms and p99 <= {OUTSIDE_P99_MS:g} ms",
                         f"{o['p50']:.3f} / {o['p99']:.3f} ms, {c.get('load', 'load unknown')}",
                         o["p50"] <= OUTSIDE_P50_MS and o["p99"] <= OUTSIDE_P99_MS, c["name"]))
    return rows
