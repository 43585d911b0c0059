"""Full latency benchmark: end-to-end per 50 Hz step, runtime vs torch eager, model vs hardware.

For the shipped edge model and a paper-size model (d = 512, 8 heads, 2 layers, L = 250,
H = 150), fp32 and int8, with 1 and 2 threads, a seeded simulated drive is encoded to CAN frames
and fed frame by frame through the real runtime pipeline (decode -> assemble -> ONNX inference ->
guard -> EKF); the runtime's configurations are interleaved in chunks so that a change of machine
load hits all of them alike. In the same run and on the same frames, after them and interleaved
the same way, a plain PyTorch eager pipeline does the same per-step work (the reference; ratio =
torch / runtime). The model's analytic FLOPs per inference over its
measured time give its rate, compared with this CPU's NumPy fp32 GEMM rate on the model's
shapes measured in the same run. int8 costs are checked as z RMSE on test windows.

Usage::

    .venv/bin/python benchmarks/latency.py [--quick] [--models edge,paper] [--threads 1,2]

Writes ``benchmarks/results/latency.json`` and updates the table in ``docs/benchmarks.md``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from prml2_edge import schema
from prml2_edge.bench.flops import gemm_shapes, inference_flops
from prml2_edge.bench.latency import StepSamples, build_pipeline, measure_steps, open_session_model, split_frames
from prml2_edge.bench.machine import gemm_rate, load_average, load_label, machine_info
from prml2_edge.bench.replay_input import simulated_frames
from prml2_edge.runtime.latency import DEADLINE_MS, PAPER_INFER_MS

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_models  # noqa: E402
import report  # noqa: E402
import targets  # noqa: E402
from torch_pipeline import torch_pipeline  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def run_model(bm: bench_models.BenchModel, threads: int, seconds: float, warmup_steps: int, chunk_s: float,
              seed: int, with_bf16: bool) -> list[dict]:
    """Every configuration of one model at one thread count, interleaved on the same frames."""
    torch.set_num_threads(threads)
    replay = simulated_frames(seconds, seed=seed)
    pipes = {
        "onnx-fp32": build_pipeline(open_session_model(bm.fp32, threads=threads), replay.initial_pose),
        # the same weights as a graph returning every decoder step (before streaming exports): report only
        "onnxall-fp32": build_pipeline(open_session_model(bm.fp32_all, threads=threads), replay.initial_pose),
        "onnx-int8": build_pipeline(open_session_model(bm.int8, threads=threads), replay.initial_pose),
        "torch-fp32": torch_pipeline(bm.torch_model, replay.initial_pose),
    }
    if threads > 1:  # the runtime's [model] spinning = true: worker threads busy-wait instead of sleeping
        pipes["onnxspin-fp32"] = build_pipeline(open_session_model(bm.fp32, threads=threads, spinning=True),
                                                replay.initial_pose)
        pipes["onnxspin-int8"] = build_pipeline(open_session_model(bm.int8, threads=threads, spinning=True),
                                                replay.initial_pose)
    if with_bf16:
        pipes["torch-bf16"] = torch_pipeline(bm.torch_model, replay.initial_pose, dtype=torch.bfloat16)
    warm, chunks = split_frames(replay.frames, schema.WINDOW_LEN + warmup_steps, chunk_s)
    samples = {k: StepSamples() for k in pipes}
    for pipe in pipes.values():
        measure_steps(pipe, warm)  # window fill and warm-up: not counted
    load_before = load_average()
    # The runtime's configurations interleaved chunk by chunk, then the torch references the same way: torch's
    # OpenMP workers spin for up to 200 ms after each parallel region, and interleaved with the onnxruntime
    # sessions they took the second core from them (bimodal 2-thread latencies, p95 ~1.5 x p50).
    for group in ([n for n in pipes if not n.startswith("torch")], [n for n in pipes if n.startswith("torch")]):
        for chunk in chunks:
            for name in group:
                samples[name].extend(measure_steps(pipes[name], chunk))
    load_after = load_average()
    out = []
    for name, s in samples.items():
        flops = inference_flops(bm.config, None if name.startswith("onnxall") else 1)["total"]
        summ = s.summary()
        p50 = summ["model_ms"]["p50"]
        out.append({
            "name": f"{bm.name}-{name}-{threads}t", "model": bm.name, "runtime": name.split("-")[0],
            "precision": name.split("-")[1], "threads": threads, "steps": len(s.e2e_ms), **summ,
            "deadline_misses": int(np.count_nonzero(np.asarray(s.e2e_ms) > DEADLINE_MS)),
            "flops": flops, "model_gflops_per_s": flops / (p50 * 1e6),
            "rows_per_s": s.rows / s.wall_s if s.wall_s > 0 else None,
            "load_average": [load_before, load_after], "load": load_label(load_before, load_after),
        })
    return out


def int8_rmse(bm: bench_models.BenchModel) -> dict | None:
    """z RMSE (before the guard) of fp32 and int8 graphs on test windows, and the relative change per state."""
    from prml2_edge.training.export_onnx import compare_int8

    win = bench_models.test_windows()
    if win is None:
        return None
    onboard, z_gt = win
    res = {}
    for label, path in (("int8", bm.int8), ("int8_ort_defaults", bm.int8_plain)):
        cmp = compare_int8(bm.fp32, path, onboard, z_gt)
        rel = {k: (cmp["int8"][k] - cmp["fp32"][k]) / cmp["fp32"][k] for k in cmp["fp32"]}
        res[label] = {"fp32_rmse": cmp["fp32"], "int8_rmse": cmp["int8"], "relative_change": rel,
                      "max_abs_relative_change": max(abs(v) for v in rel.values()),
                      "max_abs_mean_diff": cmp["max_abs_mean_diff"], "n_windows": cmp["n_windows"]}
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="edge,paper", help="comma-separated: edge, paper")
    ap.add_argument("--threads", default="1,2", help="comma-separated thread counts")
    ap.add_argument("--seconds-edge", type=float, default=60.0, help="drive length for the edge model [s]")
    ap.add_argument("--seconds-paper", type=float, default=30.0, help="drive length for the paper-size model [s]")
    ap.add_argument("--warmup-steps", type=int, default=50, help="inference steps not counted")
    ap.add_argument("--chunk-s", type=float, default=2.0, help="interleaving chunk [s of drive]")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--edge-checkpoint", default=None,
                    help="trained edge checkpoint (e.g. runs/edge/best.pt) to export and measure instead of the "
                         "shipped ONNX file (its torch twin then has the exact weights)")
    ap.add_argument("--no-bf16", action="store_true", help="skip the torch bf16 reference of the paper-size model")
    ap.add_argument("--quick", action="store_true", help="short drives, for development (not for the table)")
    ap.add_argument("--out", default=str(RESULTS / "latency.json"))
    args = ap.parse_args(argv)
    if args.quick:
        args.seconds_edge, args.seconds_paper, args.warmup_steps = 9.0, 7.0, 10

    t_start = time.time()
    machine = machine_info(with_torch=True)
    print(f"[latency] load average at start {machine['load_average']}", file=sys.stderr, flush=True)
    models = [m.strip() for m in args.models.split(",") if m.strip()]
    threads = [int(t) for t in args.threads.split(",")]
    configs, model_info, gemm, rmse = [], {}, {}, {}
    for name in models:
        bm = bench_models.prepare(name, seed=args.seed, checkpoint=args.edge_checkpoint if name == "edge" else None)
        model_info[name] = {"source": bm.source, "trained": bm.trained, "config": bm.config,
                            "flops": inference_flops(bm.config, 1), "flops_all_rows": inference_flops(bm.config),
                            "fp32": str(bm.fp32), "fp32_all_rows": str(bm.fp32_all), "int8": str(bm.int8)}
        seconds = args.seconds_edge if name == "edge" else args.seconds_paper
        for n in threads:
            print(f"[latency] {name}, {n} thread(s), load {load_average()}", file=sys.stderr, flush=True)
            configs.extend(run_model(bm, n, seconds, args.warmup_steps, args.chunk_s, args.seed,
                                     with_bf16=(name == "paper" and not args.no_bf16)))
            key = str(n)
            if key not in gemm:  # same run, between the models
                gemm[key] = gemm_rate(gemm_shapes(bench_models.paper_config()), threads=n)
        rmse[name] = int8_rmse(bm)
    load_end = load_average()
    print(f"[latency] load average at end {load_end}", file=sys.stderr, flush=True)
    doc = {
        "benchmark": "latency",
        "started": time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(t_start)),
        "wall_s": time.time() - t_start,
        "quick": args.quick,
        "settings": {k: v for k, v in vars(args).items() if k != "out"},
        "machine": machine,
        "load_average_end": load_end,
        "load": load_label(machine["load_average"], load_end),
        "models": model_info,
        "configs": configs,
        "gemm": gemm,
        "int8_rmse": rmse,
        "paper_orin_infer_ms": list(PAPER_INFER_MS),
        "deadline_ms": DEADLINE_MS,
    }
    doc["ratios"] = targets.ratios(configs)
    doc["fraction_of_gemm"] = targets.fraction_of_gemm(configs, gemm)
    doc["targets"] = targets.latency_targets(doc)
    out = report.save(doc, args.out, update=not args.quick)
    for line in report.latency_lines(doc):
        print(line)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
