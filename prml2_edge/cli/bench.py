"""``prml2 bench``: the quick latency benchmark of the runtime on this machine (torch-free).

A seeded simulated drive is encoded to CAN frames with the project DBC and fed frame by frame
through the real pipeline (decode -> assemble -> ONNX inference -> physics guard -> EKF); per
50 Hz step it reports p50/p95/p99/max of the end-to-end latency, the model alone and the rest
(overhead), for every model x precision x thread count asked for, beside this CPU's measured
fp32 GEMM rate. Precisions (variants made here from each fp32 model, as ``prml2 export`` makes them):
``fp32``; ``int8`` dynamic quantisation; ``int8-static`` static QDQ calibrated on simulated windows;
``fp32-opt`` fused attention (``prml2 export --optimize``);
``int8-opt`` that graph dynamically quantised (``--optimize --int8``). Each variant's z RMSE change
against its fp32 graph is measured in the same run on ``--accuracy-windows`` windows of simulated
drives (seeds apart from the calibration drives and from the benchmark dataset). ``--json`` prints
one JSON object: ``{"configs": [{"name", "e2e_ms": {"p50", "p95", "p99", "max", ...}, "model_ms",
"overhead_ms", "accuracy", ...}], "machine", "gemm", ...}``.
The full benchmarks (paper-size model, torch comparison, throughput) are in ``benchmarks/``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

HELP = "Measure per-step latency of the runtime on this machine (quick benchmark)."
NEEDS: tuple[tuple[str, str], ...] = ()


def _int_list(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected integers >= 1, got {text!r}")
    return values


PRECISIONS = ("fp32", "int8", "int8-static", "fp32-opt", "int8-opt")
MADE_HERE = ("int8", "int8-static", "fp32-opt", "int8-opt")  # variants made here: they need the onnx package


def _precisions(text: str) -> list[str]:
    values = [v.strip() for v in text.split(",") if v.strip()]
    bad = [v for v in values if v not in PRECISIONS]
    if not values or bad:
        raise argparse.ArgumentTypeError(f"precisions are {', '.join(PRECISIONS)}, got {text!r}")
    return values


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", action="append", metavar="PATH",
                        help="ONNX model to measure (repeatable; default: the shipped edge model)")
    parser.add_argument("--threads", type=_int_list, default=[1, 2], metavar="N[,N]",
                        help="onnxruntime intra-op thread counts to measure (default 1,2; capped at this box's cores)")
    parser.add_argument("--precision", type=_precisions, default=["fp32", "int8"], metavar="P[,P]",
                        help="any of fp32, int8 (dynamic quantisation), int8-static (static QDQ, calibrated on "
                             "simulated windows), fp32-opt (fused attention, as prml2 export "
                             "--optimize), int8-opt (that, dynamically quantised); the variants are "
                             "made here and need the onnx package (skipped with a note otherwise). Default fp32,int8")
    parser.add_argument("--accuracy-windows", type=int, default=100, metavar="N",
                        help="simulated windows on which each variant's z RMSE change against fp32 is measured "
                             "(default 100; 0 skips it)")
    parser.add_argument("--calibration-windows", type=int, default=256, metavar="N",
                        help="simulated windows that calibrate int8-static (default 256)")
    parser.add_argument("--seconds", type=float, default=25.0,
                        help="simulated drive length [s]; the first 5 s only fill the model window (default 25)")
    parser.add_argument("--warmup-steps", type=int, default=50, help="inference steps not counted (default 50)")
    parser.add_argument("--seed", type=int, default=0, help="simulator seed (default 0)")
    parser.add_argument("--chunk-s", type=float, default=2.0, metavar="S",
                        help="the variants are measured side by side, fed the drive in turns of S seconds (default 2)")
    parser.add_argument("--no-gemm", action="store_true", help="skip the NumPy fp32 GEMM reference")
    parser.add_argument("--spinning", action="store_true",
                        help="onnxruntime thread spinning on (the runtime's default is off)")
    parser.add_argument("--fixed-threads", action="store_true",
                        help="run on each thread count as given; by default 2 or more is an upper bound, as in the "
                             "runtime (a model faster on one intra-op thread gets one: the record's threads_used)")
    parser.add_argument("--providers", default="cpu", metavar="P[,P]",
                        help="onnxruntime execution providers in order of preference: tensorrt, cuda, cpu "
                             "(default cpu; on a Jetson try tensorrt,cuda,cpu)")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of the table")


def _label(model) -> str:
    preset = getattr(model.metadata, "preset", "") or ""
    return preset if preset and preset != "unknown" else model.path.stem


def _plan(args: argparse.Namespace) -> tuple[list[Path], list[int], list[str], list[str]]:
    """Check the arguments and settle what to measure: (model paths, thread counts, precisions, notes)."""
    from prml2_edge import schema
    from prml2_edge.bench.machine import usable_cores
    from prml2_edge.errors import ConfigError
    from prml2_edge.runtime.inference import default_model_path
    from prml2_edge.training.quantize import int8_available

    if args.seconds * schema.SAMPLE_RATE_HZ <= schema.WINDOW_LEN + args.warmup_steps:
        raise ConfigError(f"--seconds {args.seconds:g} is too short: the first {schema.WINDOW_LEN} steps fill the "
                          f"window and {args.warmup_steps} more are warm-up")
    model_paths = [Path(p) for p in (args.model or [default_model_path()])]
    cores = usable_cores()
    threads = [t for t in args.threads if t <= cores] or [1]
    notes: list[str] = []
    if len(threads) < len(args.threads):
        notes.append(f"thread counts above this box's {cores} usable cores skipped")
    precisions = list(dict.fromkeys(args.precision))
    if args.accuracy_windows < 0 or args.calibration_windows < 1 or args.chunk_s <= 0:
        raise ConfigError("--accuracy-windows must be >= 0, --calibration-windows >= 1 and --chunk-s > 0")
    missing = [p for p in precisions if p in MADE_HERE]
    if missing and not int8_available():
        precisions = [p for p in precisions if p not in MADE_HERE]
        notes.append(f"{', '.join(missing)} skipped: making them needs the onnx package "
                     "(pip install 'prml2-edge[train]'), or pass such a model with --model")
    if not precisions:
        raise ConfigError("nothing to measure: the variants asked for need the onnx package and fp32 was not asked for")
    return model_paths, threads, precisions, notes


def _variants(path: Path, precisions: list[str], tmp: Path, calibration_windows: int,
              notes: list[str]) -> list[tuple[str, Path]]:
    """(precision, model path) for each precision of one model; the variants are made into ``tmp`` (a variant
    this model cannot have, e.g. the optimiser on a graph without attention metadata, is skipped with a note)."""
    from prml2_edge.errors import ModelError
    from prml2_edge.training import quantize

    variants = []
    for precision in precisions:
        dst = tmp / f"{path.stem}_{precision}.onnx"
        try:
            if precision == "fp32":
                variants.append(("fp32", path))
            elif precision == "int8":
                variants.append((precision, quantize.quantize_prml2(path, dst)))
            elif precision == "int8-static":
                meta = quantize.graph_metadata(path)
                windows, _ = quantize.simulated_windows(calibration_windows, L=meta.L, H=meta.H)
                variants.append((precision, quantize.quantize_static_int8(path, dst, windows)))
            elif precision == "fp32-opt":
                quantize.optimize_transformer(path, dst)
                variants.append((precision, dst))
            else:  # int8-opt
                fused = tmp / f"{path.stem}_fp32-opt.onnx"
                if not fused.is_file():
                    quantize.optimize_transformer(path, fused)
                variants.append((precision, quantize.quantize_prml2(fused, dst)))
        except ModelError as exc:
            notes.append(f"{precision} of {path.name} skipped: {exc}")
    return variants


def _accuracy(fp32: Path, variant: Path, n_windows: int) -> dict | None:
    """z RMSE change of ``variant`` against ``fp32`` on ``n_windows`` simulated windows (None when 0)."""
    if n_windows <= 0:
        return None
    from prml2_edge.training import quantize

    meta = quantize.graph_metadata(fp32)
    windows, z = quantize.simulated_windows(n_windows, seed=quantize.ACCURACY_SEED, L=meta.L, H=meta.H)
    return quantize.z_rmse_change(fp32, variant, windows, z)


def _measure_group(args: argparse.Namespace, path: Path, variants: list[tuple[str, Path]], n_threads: int,
                   providers: list[str], replay, gemm: dict[int, dict], accuracy: dict) -> list[dict]:
    """Every variant of one model at one thread count, side by side: one pipeline each, fed the same frames
    interleaved in chunks of ``--chunk-s`` seconds of driving; one record per variant (its latency summary,
    FLOP rate beside the GEMM reference measured once per thread count into ``gemm``, and its z RMSE change
    against the fp32 graph from ``accuracy``)."""
    from prml2_edge import schema
    from prml2_edge.bench.latency import StepSamples, build_pipeline, measure_steps, open_session_model, split_frames
    from prml2_edge.bench.machine import load_average
    from prml2_edge.runtime.latency import DEADLINE_MS

    models = {p: open_session_model(vp, threads=n_threads, spinning=args.spinning, providers=providers,
                                    fixed_threads=args.fixed_threads) for p, vp in variants}
    pipes = {p: build_pipeline(m, replay.initial_pose) for p, m in models.items()}
    warm, chunks = split_frames(replay.frames, schema.WINDOW_LEN + args.warmup_steps, args.chunk_s)
    for pipe in pipes.values():
        measure_steps(pipe, warm)  # window fill and warm-up: not counted
    samples = {p: StepSamples() for p in pipes}
    load_before = load_average()
    for chunk in chunks:
        for p, pipe in pipes.items():
            samples[p].extend(measure_steps(pipe, chunk))
    load_after = load_average()
    records = []
    for (precision, variant_path), model in zip(variants, models.values(), strict=True):
        s = samples[precision]
        record = {
            "name": f"{_label(model)}-{precision}-{n_threads}t",
            "model": str(path), "variant": str(variant_path), "preset": model.metadata.preset,
            "precision": precision, "threads": n_threads, "spinning": bool(args.spinning),
            "threads_used": model.threads,  # thread_timing_ms: {threads: mean ms} of the start-up choice, if one
            "thread_timing_ms": {str(k): v for k, v in model.thread_timing_ms.items()} if model.thread_timing_ms
            else None,
            "providers": model.providers, "steps": len(s.e2e_ms),
            **s.summary(),
            "deadline_ms": DEADLINE_MS,
            "deadline_misses": int(sum(v > DEADLINE_MS for v in s.e2e_ms)),
            "load_average": [load_before, load_after],
            "accuracy": accuracy.get(precision),
        }
        _add_rates(record, dict(model.metadata.config), model.metadata.output_rows, n_threads, gemm,
                   no_gemm=args.no_gemm)
        records.append(record)
    return records


def _add_rates(record: dict, cfg: dict, output_rows, n_threads: int, gemm: dict[int, dict], no_gemm: bool) -> None:
    """Add ``flops``, ``model_gflops_per_s`` and (unless ``no_gemm``) the GEMM reference to ``record``."""
    from prml2_edge.bench.flops import gemm_shapes, inference_flops
    from prml2_edge.bench.machine import gemm_rate

    try:
        flops = inference_flops(cfg, output_rows)["total"]
    except ValueError:
        flops = None
    record["flops"] = flops
    p50 = record["model_ms"].get("p50")
    record["model_gflops_per_s"] = flops / (p50 * 1e6) if flops and p50 else None
    if not no_gemm and flops:
        if n_threads not in gemm:
            gemm[n_threads] = gemm_rate(gemm_shapes(cfg), threads=n_threads)
        ref = gemm[n_threads]["flop_weighted_gflops"]
        record["gemm_gflops"] = ref
        record["fraction_of_gemm"] = record["model_gflops_per_s"] / ref if ref else None


def run(args: argparse.Namespace) -> int:
    import tempfile

    from prml2_edge.bench.machine import machine_info
    from prml2_edge.bench.replay_input import simulated_frames
    from prml2_edge.runtime.latency import PAPER_INFER_MS

    model_paths, threads, precisions, notes = _plan(args)
    providers = [p.strip() for p in args.providers.split(",") if p.strip()]
    replay = simulated_frames(args.seconds, seed=args.seed)
    machine = machine_info()
    gemm: dict[int, dict] = {}
    configs = []
    with tempfile.TemporaryDirectory(prefix="prml2-bench-") as tmp:
        for path in model_paths:
            variants = _variants(path, precisions, Path(tmp), args.calibration_windows, notes)
            accuracy = {p: _accuracy(path, vp, args.accuracy_windows) for p, vp in variants if p != "fp32"}
            for n_threads in threads:
                configs.extend(_measure_group(args, path, variants, n_threads, providers, replay, gemm, accuracy))
    doc = {
        "benchmark": "prml2 bench (quick)",
        "drive": {"seconds": args.seconds, "seed": args.seed, "frames": len(replay.frames)},
        "warmup_steps": args.warmup_steps,
        "accuracy_windows": {"n": args.accuracy_windows, "source": "simulated drives, seeds from "
                             "prml2_edge.training.quantize.ACCURACY_SEED", "reference": "the fp32 graph"},
        "configs": configs,
        "gemm": {str(k): v for k, v in gemm.items()},
        "paper_orin_infer_ms": list(PAPER_INFER_MS),
        "machine": machine,
        "notes": notes,
    }
    if args.json:
        json.dump(doc, sys.stdout, indent=None, sort_keys=False)
        sys.stdout.write("\n")
        return 0
    for line in table_lines(doc):
        print(line)
    return 0


def table_lines(doc: dict) -> list[str]:
    """The quick benchmark as a fixed-width table."""
    m = doc["machine"]
    lines = [f"{m['cpu_model']} | {m['cores_usable']} cores | {' '.join(m['flags']) or '-'} | "
             f"onnxruntime {m['onnxruntime']} | load {m['load_average']}",
             f"{'config':<30} {'steps':>6} {'e2e p50':>8} {'p95':>7} {'p99':>7} {'max':>7}  {'model p50':>9} "
             f"{'p99':>7}  {'ovh p99':>7}  {'GFLOP/s':>7} {'of GEMM':>7}  50 Hz  {'z RMSE chg':>10}"]
    for c in doc["configs"]:
        e, mo, ov = c["e2e_ms"], c["model_ms"], c["overhead_ms"]
        if not e.get("count"):
            lines.append(f"{c['name']:<30} {0:>6}  (no inference steps measured)")
            continue
        rate = f"{c['model_gflops_per_s']:7.1f}" if c.get("model_gflops_per_s") else f"{'-':>7}"
        frac = f"{100 * c['fraction_of_gemm']:6.0f}%" if c.get("fraction_of_gemm") else f"{'-':>7}"
        ok = "yes" if e["p99"] <= c["deadline_ms"] else "NO"
        acc = c.get("accuracy")
        chg = f"{100 * acc['max_abs_relative_change']:9.2f}%" if acc else f"{'-':>10}"
        lines.append(f"{c['name']:<30} {e['count']:>6} {e['p50']:>8.2f} {e['p95']:>7.2f} {e['p99']:>7.2f} "
                     f"{e['max']:>7.2f}  {mo['p50']:>9.2f} {mo['p99']:>7.2f}  {ov['p99']:>7.2f}  {rate} {frac}  "
                     f"{ok:<5}  {chg}")
    for k, g in doc["gemm"].items():
        lines.append(f"NumPy fp32 GEMM, {k} thread(s), model shapes: {g['flop_weighted_gflops']:.1f} GFLOP/s "
                     f"(best shape {g['best_gflops']:.1f})")
    lo, hi = doc["paper_orin_infer_ms"]
    lines.append(f"times in ms per 50 Hz step (deadline 20 ms); paper: {lo:g}-{hi:g} ms inference on an NVIDIA Orin")
    n_acc = doc.get("accuracy_windows", {}).get("n")
    if n_acc:
        lines.append(f"z RMSE chg: largest relative change of a state's z RMSE against the fp32 graph, {n_acc} "
                     "simulated windows")
    for c in doc["configs"]:
        if c.get("threads_used", c["threads"]) != c["threads"]:
            t = c["thread_timing_ms"]
            lines.append(f"note: {c['name']} ran on {c['threads_used']} intra-op thread(s), faster for this model here "
                         f"(mean {t[str(c['threads_used'])]:.2f} against {t[str(c['threads'])]:.2f} ms at start; "
                         "--fixed-threads runs it as asked)")
    lines.extend(f"note: {n}" for n in doc["notes"])
    return lines
