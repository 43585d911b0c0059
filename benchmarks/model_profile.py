"""Where a model's inference time goes: onnxruntime's own per-node profile, summed by operator type.

Runs the graph on one window ``--runs`` times with the runtime's session options (sequential, all
graph optimisations, ``--threads`` intra-op threads) and onnxruntime profiling on, then sums the
kernel times of every node by operator type. It explains the latency table: a graph whose time
is spread over a hundred small nodes (Reshape, Transpose, Softmax on 64-wide tensors) is bound by
per-node overhead and gains nothing from batching, while one dominated by MatMul/Gemm is bound by
compute and is judged against the GEMM rate.

Usage::

    .venv/bin/python benchmarks/model_profile.py [--models edge,paper] [--threads 1] [--runs 200]

Writes ``benchmarks/results/model_profile.json``; prints a table per model.
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from prml2_edge import schema
from prml2_edge.bench.machine import load_average, machine_info
from prml2_edge.runtime.inference import session_options

sys.path.insert(0, str(Path(__file__).resolve().parent))
import report  # noqa: E402
from paths import prepared_paths  # noqa: E402

HERE = Path(__file__).resolve().parent


def profile(path: str | Path, threads: int = 1, runs: int = 200) -> dict:
    """Per-operator-type kernel time of ``runs`` inferences of ``path`` [us per inference]."""
    import onnxruntime as ort

    with tempfile.TemporaryDirectory(prefix="prml2-prof-") as tmp:
        opts = session_options(threads)
        opts.enable_profiling = True
        opts.profile_file_prefix = str(Path(tmp) / "ort")
        sess = ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])
        meta = json.loads(sess.get_modelmeta().custom_metadata_map["prml2"])
        window = np.tile(np.asarray(meta["norm_mean"], dtype=np.float32), (1, schema.WINDOW_LEN, 1))
        name = sess.get_inputs()[0].name
        for _ in range(10):
            sess.run(None, {name: window})
        t0 = time.perf_counter()
        for _ in range(runs):
            sess.run(None, {name: window})
        wall_ms = (time.perf_counter() - t0) / runs * 1e3
        events = json.loads(Path(sess.end_profiling()).read_text())
    us: collections.Counter = collections.Counter()
    nodes: collections.Counter = collections.Counter()
    by_part: collections.Counter = collections.Counter()
    for ev in events:
        if ev.get("cat") == "Node" and ev.get("name", "").endswith("_kernel_time"):
            op = ev["args"]["op_name"]
            us[op] += ev["dur"]
            nodes[op] += 1
            by_part[model_part(ev["name"])] += ev["dur"]
    n_inf = runs + 10
    total = sum(us.values()) / n_inf
    ops = [{"op": op, "us": v / n_inf, "fraction": v / n_inf / total, "nodes": nodes[op] / n_inf}
           for op, v in us.most_common()]
    parts = {k: {"us": v / n_inf, "fraction": v / n_inf / total} for k, v in by_part.most_common()}
    return {"model": str(path), "threads": threads, "runs": runs, "wall_ms_profiled": wall_ms,
            "kernel_us": total, "nodes_per_inference": sum(nodes.values()) / n_inf, "ops": ops, "parts": parts}


def model_part(node: str) -> str:
    """The part of the transformer a node belongs to, from its exported name (``/model/encoder.0/attn/...``):
    ``encoder`` (its layers and final norm), ``decoder`` (its layers, final norm, head and skip) or ``input``
    (normalisation, features, input projection, positions). Issue 29: the encoder is the part that re-reads
    the 150 samples it saw one inference before."""
    path = node.removesuffix("_kernel_time").lstrip("/").removeprefix("model/")
    first = path.split("/", 1)[0]
    if first.startswith(("encoder", "enc_norm")):
        return "encoder"
    if first.startswith(("decoder", "dec_norm", "head", "skip")):
        return "decoder"
    return "input"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="edge,paper", help="comma-separated: edge, paper (benchmarks/bench_models.py)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--runs", type=int, default=200)
    ap.add_argument("--out", default=str(HERE / "results" / "model_profile.json"))
    args = ap.parse_args(argv)
    doc = {"benchmark": "model_profile", "started": time.strftime("%Y-%m-%dT%H:%M:%S"), "machine": machine_info(),
           "load_average_start": load_average(), "profiles": {}}
    for name in [m.strip() for m in args.models.split(",") if m.strip()]:
        paths = prepared_paths(name)
        for label, key in (("newest row", "fp32"), ("all rows", "fp32_all"), ("int8", "int8")):
            res = profile(paths[key], args.threads, args.runs if name == "edge" else max(20, args.runs // 10))
            doc["profiles"][f"{name} {label}"] = res
            print(f"{name} {label}: {res['kernel_us'] / 1e3:.2f} ms in {res['nodes_per_inference']:.0f} nodes "
                  f"({args.threads} thread(s), profiled wall {res['wall_ms_profiled']:.2f} ms)")
            print("  by part: " + ", ".join(f"{k} {100 * v['fraction']:.0f} %" for k, v in res["parts"].items()))
            for op in res["ops"][:8]:
                print(f"  {op['op']:<26} {op['us']:9.1f} us {100 * op['fraction']:5.1f} %  {op['nodes']:4.0f} nodes")
    doc["load_average_end"] = load_average()
    out = report.save(doc, args.out, update=False)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
