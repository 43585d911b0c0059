"""``prml2 bench``: the quick latency benchmark of the runtime on this machine (torch-free).

A seeded simulated drive is encoded to CAN frames with the project DBC and fed frame by frame
through the real pipeline (decode -> assemble -> ONNX inference -> physics guard -> EKF); per
50 Hz step it reports p50/p95/p99/max of the end-to-end latency, the model alone and the rest
(overhead), for every model x precision x thread count asked for, beside this CPU's measured
fp32 GEMM rate. ``--json`` prints one JSON object: ``{"configs": [{"name", "e2e_ms": {"p50",
"p95", "p99", "max", ...}, "model_ms", "overhead_ms", ...}], "machine", "gemm", ...}``.
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


def _precisions(text: str) -> list[str]:
    values = [v.strip() for v in text.split(",") if v.strip()]
    bad = [v for v in values if v not in ("fp32", "int8")]
    if not values or bad:
        raise argparse.ArgumentTypeError(f"precisions are fp32 and int8, got {text!r}")
    return values


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", action="append", metavar="PATH",
                        help="ONNX model to measure (repeatable; default: the shipped edge model)")
    parser.add_argument("--threads", type=_int_list, default=[1, 2], metavar="N[,N]",
                        help="onnxruntime intra-op thread counts to measure (default 1,2; capped at this box's cores)")
    parser.add_argument("--precision", type=_precisions, default=["fp32", "int8"], metavar="P[,P]",
                        help="fp32 and/or int8 (dynamic quantisation made here; needs the onnx package, "
                             "skipped with a note otherwise). Default fp32,int8")
    parser.add_argument("--seconds", type=float, default=25.0,
                        help="simulated drive length [s]; the first 5 s only fill the model window (default 25)")
    parser.add_argument("--warmup-steps", type=int, default=50, help="inference steps not counted (default 50)")
    parser.add_argument("--seed", type=int, default=0, help="simulator seed (default 0)")
    parser.add_argument("--no-gemm", action="store_true", help="skip the NumPy fp32 GEMM reference")
    parser.add_argument("--spinning", action="store_true",
                        help="onnxruntime thread spinning on (the runtime's default is off)")
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
    precisions = list(args.precision)
    if "int8" in precisions and not int8_available():
        precisions.remove("int8")
        notes.append("int8 skipped: quantising needs the onnx package (pip install 'prml2-edge[train]'), "
                     "or pass an int8 model with --model")
    if not precisions:
        raise ConfigError("nothing to measure: int8 needs the onnx package and fp32 was not asked for")
    return model_paths, threads, precisions, notes


def _variants(path: Path, precisions: list[str], tmp: Path) -> list[tuple[str, Path]]:
    """(precision, model path) for each precision of one model; int8 graphs are quantised into ``tmp``."""
    from prml2_edge.training.quantize import quantize_prml2

    variants = []
    for precision in precisions:
        if precision == "fp32":
            variants.append(("fp32", path))
        else:
            variants.append(("int8", quantize_prml2(path, tmp / f"{path.stem}_int8.onnx")))
    return variants


def _measure(args: argparse.Namespace, path: Path, precision: str, variant_path: Path, n_threads: int,
             providers: list[str], replay, gemm: dict[int, dict]) -> dict:
    """One config's record: the latency summary of the replayed drive, then its FLOP rate beside the GEMM
    reference (measured once per thread count into ``gemm``)."""
    from prml2_edge.bench.latency import build_pipeline, measure_steps, open_session_model
    from prml2_edge.bench.machine import load_average
    from prml2_edge.runtime.latency import DEADLINE_MS

    model = open_session_model(variant_path, threads=n_threads, spinning=args.spinning, providers=providers)
    label = _label(model)
    cfg = dict(model.metadata.config)
    pipeline = build_pipeline(model, replay.initial_pose)
    load_before = load_average()
    samples = measure_steps(pipeline, replay.frames, skip=args.warmup_steps)
    record = {
        "name": f"{label}-{precision}-{n_threads}t",
        "model": str(path), "preset": model.metadata.preset, "precision": precision,
        "threads": n_threads, "spinning": bool(args.spinning), "providers": model.providers,
        "steps": len(samples.e2e_ms),
        **samples.summary(),
        "deadline_ms": DEADLINE_MS,
        "deadline_misses": int(sum(v > DEADLINE_MS for v in samples.e2e_ms)),
        "load_average": [load_before, load_average()],
    }
    _add_rates(record, cfg, model.metadata.output_rows, n_threads, gemm, no_gemm=args.no_gemm)
    return record


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
            for precision, variant_path in _variants(path, precisions, Path(tmp)):
                for n_threads in threads:
                    configs.append(_measure(args, path, precision, variant_path, n_threads, providers, replay, gemm))
    doc = {
        "benchmark": "prml2 bench (quick)",
        "drive": {"seconds": args.seconds, "seed": args.seed, "frames": len(replay.frames)},
        "warmup_steps": args.warmup_steps,
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
             f"{'config':<22} {'steps':>6} {'e2e p50':>8} {'p95':>7} {'p99':>7} {'max':>7}  {'model p50':>9} "
             f"{'p99':>7}  {'ovh p99':>7}  {'GFLOP/s':>7} {'of GEMM':>7}  50 Hz"]
    for c in doc["configs"]:
        e, mo, ov = c["e2e_ms"], c["model_ms"], c["overhead_ms"]
        if not e.get("count"):
            lines.append(f"{c['name']:<22} {0:>6}  (no inference steps measured)")
            continue
        rate = f"{c['model_gflops_per_s']:7.1f}" if c.get("model_gflops_per_s") else f"{'-':>7}"
        frac = f"{100 * c['fraction_of_gemm']:6.0f}%" if c.get("fraction_of_gemm") else f"{'-':>7}"
        ok = "yes" if e["p99"] <= c["deadline_ms"] else "NO"
        lines.append(f"{c['name']:<22} {e['count']:>6} {e['p50']:>8.2f} {e['p95']:>7.2f} {e['p99']:>7.2f} "
                     f"{e['max']:>7.2f}  {mo['p50']:>9.2f} {mo['p99']:>7.2f}  {ov['p99']:>7.2f}  {rate} {frac}  {ok}")
    for k, g in doc["gemm"].items():
        lines.append(f"NumPy fp32 GEMM, {k} thread(s), model shapes: {g['flop_weighted_gflops']:.1f} GFLOP/s "
                     f"(best shape {g['best_gflops']:.1f})")
    lo, hi = doc["paper_orin_infer_ms"]
    lines.append(f"times in ms per 50 Hz step (deadline 20 ms); paper: {lo:g}-{hi:g} ms inference on an NVIDIA Orin")
    lines.extend(f"note: {n}" for n in doc["notes"])
    return lines
