"""The model on a worker thread (``async_inference``) against the model in the step, fed as a bus delivers frames.

A seeded simulated drive is encoded to CAN frames and fed to two runtime pipelines, one after the other, each frame
at its own time (real time: what a live bus does; an asynchronous model needs the time between steps to run in).
Every 50 Hz row counts: end-to-end latency p50 / p99 / max and the rows past the 20 ms deadline, the model's own
time (on the worker thread for the asynchronous pipeline) and how many rows late its outputs were consumed. The
synchronous pipeline at the same stride is the reference of the same run.

Usage::

    .venv/bin/python benchmarks/async_latency.py [--model paper|edge] [--threads 1] [--seconds 40]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from prml2_edge import schema
from prml2_edge.bench.latency import build_pipeline, measure_steps, open_session_model, summarize
from prml2_edge.bench.machine import load_average, load_label, machine_info
from prml2_edge.bench.replay_input import simulated_frames
from prml2_edge.bench.results import write_json
from prml2_edge.config import DEFAULT_STRIDE
from prml2_edge.runtime.latency import DEADLINE_MS

sys.path.insert(0, str(Path(__file__).resolve().parent))
from paths import prepared_paths  # noqa: E402

OUT = Path(__file__).resolve().parent / "results" / "async_latency.json"


def run(model_path: str, frames, pose, threads: int, stride: int, asynchronous: bool) -> dict:
    """One paced pass over ``frames``; per-row figures (module docstring)."""
    pipe = build_pipeline(open_session_model(model_path, threads=threads), pose, stride=stride,
                          async_inference=asynchronous)
    load0 = load_average()
    warm = int(schema.WINDOW_LEN * schema.DT_S / (frames[-1].timestamp - frames[0].timestamp) * len(frames)) + 1
    measure_steps(pipe, frames[:warm])  # the window fills, as fast as it takes them
    s = measure_steps(pipe, frames[warm:], paced=True)
    summ = pipe.summary()
    pipe.close()
    e2e = np.asarray(s.e2e_ms)
    est = summ.get("async") or {}
    return {"async": asynchronous, "stride": stride, "threads": threads, "rows": len(e2e),
            "e2e_ms": summarize(e2e), "deadline_misses": int(np.count_nonzero(e2e > DEADLINE_MS)),
            "model_ms": summ["latency"]["infer"], "inferences": summ["inferences"],
            "lag_steps_mean": est.get("lag_steps_mean"), "lag_steps_max": est.get("lag_steps_max"),
            "model_used_steps": summ["model_used_steps"],
            "load_average": [load0, load_average()], "load": load_label(load0, load_average())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="paper", help="paper or edge (benchmarks/bench_models.py)")
    ap.add_argument("--threads", type=int, default=1, help="onnxruntime intra-op threads")
    ap.add_argument("--stride", type=int, default=DEFAULT_STRIDE)
    ap.add_argument("--seconds", type=float, default=40.0, help="drive length [s] (fed in real time, twice)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args(argv)
    t0 = time.time()
    machine = machine_info()
    print(f"machine: {machine.get('cpu_model')}, {machine.get('cores_usable')} usable cores; load at start "
          f"{machine.get('load_average')}", flush=True)
    path = prepared_paths(args.model, seed=args.seed)["fp32"]
    replay = simulated_frames(args.seconds, seed=args.seed)
    runs = [run(path, replay.frames, replay.initial_pose, args.threads, args.stride, a) for a in (False, True)]
    print(f"{args.model} model, fp32, {args.threads} thread(s), stride {args.stride}, {args.seconds:g} s fed in "
          f"real time; every row counts [ms]:")
    for r in runs:
        e, m = r["e2e_ms"], r["model_ms"]
        lag = "" if r["lag_steps_mean"] is None else (f"; outputs used {r['lag_steps_mean']:.1f} rows after their "
                                                       f"window (max {r['lag_steps_max']})")
        print(f"  {'async' if r['async'] else 'sync '}: e2e p50 {e['p50']:.2f} p99 {e['p99']:.2f} max {e['max']:.2f}, "
              f"{r['deadline_misses']} of {r['rows']} rows past {DEADLINE_MS:g} ms; model p50 "
              f"{m.get('p50_ms', float('nan')):.1f} ms, {r['inferences']} inferences, model used at "
              f"{r['model_used_steps']} rows{lag}; {r['load']}")
    doc = {"benchmark": "async_latency", "machine": machine, "args": vars(args), "runs": runs,
           "wall_s": time.time() - t0}
    write_json(doc, args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
