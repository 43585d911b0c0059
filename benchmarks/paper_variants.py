"""The paper-size model (d 512, 8 heads) within its budget on CPU? Every ``prml2 export`` variant side by side.

One run of ``prml2 bench`` (torch-free, in a child process) on the paper-size streaming graph
(``benchmarks/bench_models.py``): fp32, dynamic int8, static int8 (QDQ, calibrated on simulated
windows) and the transformer-optimised fp32 graph, interleaved chunk by chunk on the same replayed
drive through the real pipeline, each with its z RMSE change against fp32 on simulated windows;
then onnxruntime's per-operator profile (``model_profile.py``) of each variant and of the graph of
onnxruntime's own offline transformer optimiser, so that a missed target says where the time goes
and by how much; and what the box offers for bf16 (AMX flags; whether onnxruntime's CPU provider has
a bf16 MatMul kernel, tried). Targets (issue 17): e2e p99 <= 20 ms fp32, or
<= 8 ms reduced precision with z RMSE change <= 1 %, 2 threads, idle machine.

Usage::

    .venv/bin/python benchmarks/paper_variants.py [--threads 2] [--seconds 20] [--spinning] [--profile-runs 30]

Writes ``benchmarks/results/paper_variants.json`` (machine: CPU model, flags, load average before and
after every part) and prints the table and the profiles.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from prml2_edge.bench.machine import load_average, machine_info

sys.path.insert(0, str(Path(__file__).resolve().parent))
import report  # noqa: E402
from model_profile import profile  # noqa: E402
from paths import REPO, RESULTS, prepared_paths  # noqa: E402

FP32_P99_MS, REDUCED_P99_MS, RMSE_CHANGE = 20.0, 8.0, 0.01
PRECISIONS = "fp32,int8,int8-static,fp32-opt,int8-opt"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", default="2", help="intra-op thread counts, comma-separated (default 2)")
    ap.add_argument("--seconds", type=float, default=20.0, help="replayed drive [s] (default 20)")
    ap.add_argument("--spinning", action="store_true", help="onnxruntime thread spinning on ([model] spinning)")
    ap.add_argument("--precision", default=PRECISIONS, help=f"variants (default {PRECISIONS})")
    ap.add_argument("--accuracy-windows", type=int, default=100)
    ap.add_argument("--profile-runs", type=int, default=30, help="inferences per variant profiled (0: no profile)")
    ap.add_argument("--profile-threads", type=int, default=1)
    ap.add_argument("--no-ort-optimizer", dest="ort_optimizer", action="store_false",
                    help="skip the profile of onnxruntime's offline transformer optimiser (its fusions alone)")
    ap.add_argument("--out", default=str(RESULTS / "paper_variants.json"))
    args = ap.parse_args(argv)

    paths = prepared_paths("paper")
    doc: dict = {"benchmark": "paper_variants", "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
                 "machine": machine_info(), "model": paths, "settings": vars(args)}
    cmd = [sys.executable, "-m", "prml2_edge.cli.main", "bench", "--json", "--model", paths["fp32"],
           "--threads", args.threads, "--precision", args.precision, "--seconds", str(args.seconds),
           "--accuracy-windows", str(args.accuracy_windows), "--no-gemm"] + (["--spinning"] if args.spinning else [])
    doc["bench_command"] = " ".join(cmd[1:])
    print(f"[paper_variants] load {load_average()}: {doc['bench_command']}", file=sys.stderr, flush=True)
    res = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, check=False)
    if res.returncode != 0:
        print(res.stderr.strip().splitlines()[-1] if res.stderr.strip() else "prml2 bench failed", file=sys.stderr)
        return 1
    bench = json.loads(res.stdout)
    doc["bench"] = bench
    rows = []
    for c in bench["configs"]:
        e, acc = c["e2e_ms"], c.get("accuracy")
        change = acc["max_abs_relative_change"] if acc else 0.0
        target = FP32_P99_MS if c["precision"].startswith("fp32") else REDUCED_P99_MS
        met = e["p99"] <= target and change <= RMSE_CHANGE
        rows.append({"name": c["name"], "precision": c["precision"], "threads": c["threads"], "e2e_ms": e,
                     "model_ms": c["model_ms"], "z_rmse_change": change, "target_p99_ms": target, "met": met,
                     "load_average": c["load_average"]})
    doc["rows"] = rows
    if args.profile_runs > 0:
        doc["profiles"] = {}
        with tempfile.TemporaryDirectory(prefix="prml2-variants-") as tmp:
            variants = _variants(paths["fp32"], [r["precision"] for r in rows], Path(tmp))
            if args.ort_optimizer:  # onnxruntime's own offline fusions, for the record (profile only)
                from prml2_edge.training.quantize import optimize_transformer

                ort_path = Path(tmp) / "paper_ort_optimizer.onnx"
                doc["ort_optimizer_fusions"] = optimize_transformer(paths["fp32"], ort_path, attention=False,
                                                                    ort_fusions=True)
                variants.append(("fp32-ort-optimizer", ort_path))
            for precision, path in variants:
                load0 = load_average()
                prof = profile(path, args.profile_threads, args.profile_runs)
                prof["load_average"] = [load0, load_average()]
                doc["profiles"][precision] = prof
    doc["bf16"] = bf16_paths(doc["machine"])
    doc["load_average_end"] = load_average()
    out = report.save(doc, args.out, update=False)
    for line in lines(doc):
        print(line)
    print(f"wrote {out}")
    return 0


def bf16_paths(machine: dict) -> dict:
    """What this box offers for bf16: the CPU flags, and whether onnxruntime's CPU provider has a bf16 MatMul
    kernel (tried on a one-node graph, not assumed)."""
    import onnxruntime as ort
    from onnx import TensorProto, helper

    info = {"amx": [f for f in machine["flags"] if f.startswith("amx")],
            "avx512_bf16": "avx512_bf16" in machine["flags"]}
    io = [helper.make_tensor_value_info(n, TensorProto.BFLOAT16, [4, 4]) for n in ("a", "b", "c")]
    graph = helper.make_graph([helper.make_node("MatMul", ["a", "b"], ["c"])], "bf16", io[:2], io[2:])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    try:
        ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
        info["ort_cpu_bf16_matmul"] = True
    except Exception as exc:  # noqa: BLE001 - onnxruntime's NOT_IMPLEMENTED
        info["ort_cpu_bf16_matmul"] = False
        info["ort_cpu_bf16_matmul_error"] = str(exc).splitlines()[0][:160]
    return info


def _variants(fp32: str, precisions: list[str], tmp: Path) -> list[tuple[str, Path]]:
    """The same variants ``prml2 bench`` made (same recipes), remade here for the profiler."""
    from prml2_edge.cli.bench import _variants as bench_variants

    notes: list[str] = []
    return bench_variants(Path(fp32), list(dict.fromkeys(precisions)), tmp, 256, notes)


def lines(doc: dict) -> list[str]:
    m = doc["machine"]
    out = [f"{m['cpu_model']}, {m['cores_usable']} cores, flags {' '.join(m['flags'])}, onnxruntime {m['onnxruntime']}",
           f"{'variant':<28} {'e2e p50':>8} {'p95':>7} {'p99':>7} {'model p50':>9} {'z RMSE chg':>10} "
           f"{'target':>7}  met  load before/after"]
    for r in doc["rows"]:
        e = r["e2e_ms"]
        out.append(f"{r['name']:<28} {e['p50']:>8.2f} {e['p95']:>7.2f} {e['p99']:>7.2f} {r['model_ms']['p50']:>9.2f} "
                   f"{100 * r['z_rmse_change']:>9.2f}% {r['target_p99_ms']:>6g}  {'yes' if r['met'] else 'NO ':<4} "
                   f"{r['load_average'][0]} / {r['load_average'][1]}")
    if "ort_optimizer_fusions" in doc:
        out.append(f"onnxruntime's transformer optimiser on the fp32 graph: {doc['ort_optimizer_fusions']}")
    b = doc.get("bf16", {})
    out.append(f"bf16: AMX flags {b.get('amx') or 'none'}, avx512_bf16 {b.get('avx512_bf16')}, onnxruntime CPU "
               f"bf16 MatMul kernel {b.get('ort_cpu_bf16_matmul')} {b.get('ort_cpu_bf16_matmul_error', '')}")
    for precision, prof in doc.get("profiles", {}).items():
        out.append(f"profile {precision}: {prof['kernel_us'] / 1e3:.2f} ms kernel time in "
                   f"{prof['nodes_per_inference']:.0f} nodes ({prof['threads']} thread(s), "
                   f"load {prof['load_average'][0]})")
        for op in prof["ops"][:8]:
            out.append(f"  {op['op']:<26} {op['us'] / 1e3:7.2f} ms {100 * op['fraction']:5.1f} %  "
                       f"{op['nodes']:4.0f} nodes")
    return out


if __name__ == "__main__":
    sys.exit(main())
