"""Model rate against accuracy (issue 29): the model every k-th 50 Hz step, the filter at 50 Hz in between.

The model runs once per 60 s window at stride 1 (``RecordingModel``); every stride k then replays the outputs
of the windows it would have run (call i of a stride-k run is the window ending k * i rows after the first,
``StrideReplay``), so the rows differ only by the rate. Between model calls the estimator holds the newest output
(``runtime/estimator.py``) and the filter fuses the raw cues. Cost: model inferences per driven second (50 / k),
times the edge model's measured inference time when ``--infer-ms`` is given. Paired intervals against k = 1.

Usage::

    .venv/bin/python benchmarks/stride_table.py --data data/bench2 [--splits test] [--strides 1 2 3 5 10 25]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from prml2_edge import schema
from prml2_edge.bench.machine import machine_info
from prml2_edge.bench.results import write_json
from prml2_edge.data.datasets import load_dataset
from prml2_edge.evaluation.metrics import coverage, coverage_text, dr_summary, paired_comparison, paired_text
from prml2_edge.evaluation.models import RecordingModel, ReplayModel
from prml2_edge.evaluation.protocol import ModelSpec, build_model, run_window, split_tasks
from prml2_edge.progress import Progress

HERE = Path(__file__).resolve().parent
OUT = HERE / "results" / "stride_table.json"


class StrideReplay(ReplayModel):
    """Call i gives back the stride-1 record of call ``i * stride``."""

    def __init__(self, records, metadata, stride: int) -> None:
        super().__init__(records, metadata)
        self.stride, self._i = int(stride), 0

    def step(self, window: np.ndarray):
        self.calls, self._i = self._i * self.stride, self._i + 1
        return super().step(window)


def install_lag(lag: int) -> None:
    """Every stride > 1 run consumes each output ``lag`` rows after its window ended, as async inference does
    (``runtime/async_estimator.py``; 2.9 rows measured for the paper-size model), deterministically: until it
    arrives, the previous output stays in use. Stride 1 stays the reference without lag. Patches
    :meth:`Estimator.step` in this process (and the forked workers)."""
    from prml2_edge.runtime import estimator as est_mod

    sync_step = est_mod.Estimator.step

    def step(self, values, all_valid, discontinuity=False):
        est = sync_step(self, values, all_valid, discontinuity)
        if self.stride == 1:
            return est
        if discontinuity or not hasattr(self, "_lag_queue"):
            self._lag_queue, self._lag_cur = [], None
        n = self.window.count
        if est.inferred and est.z is not None:
            self._lag_queue.append((n + lag, est.z.copy(), est.z_var.copy(), est.guard_fired))
        while self._lag_queue and self._lag_queue[0][0] <= n:
            self._lag_cur = self._lag_queue.pop(0)[1:]
        if est.z is None or self._lag_cur is None:
            return est_mod.Estimate(est.inferred, infer_ns=est.infer_ns, guard_ns=est.guard_ns)
        return est_mod.Estimate(est.inferred, *self._lag_cur, est.infer_ns, est.guard_ns)

    est_mod.Estimator.step = step


def _one_task(args):
    spec, task, strides = args
    rec = RecordingModel(build_model(spec, task.bias))
    out = {1: run_window(spec, task, model=rec)}
    for k in strides:
        if k != 1:
            out[k] = run_window(spec, task, stride=k, model=StrideReplay(rec.records, rec.metadata, k))
    return out


def measure(args) -> dict:
    spec = ModelSpec("PRML2", "onnx", args.model, calibration=True)
    dataset = load_dataset(args.data)
    doc = {"data": args.data, "model": args.model, "strides": args.strides, "lag_rows": args.lag, "splits": {}}
    for split in args.splits:
        tasks = split_tasks(dataset, split, max_windows=args.max_windows)
        res: dict[int, list] = {k: [] for k in [1, *args.strides] if k}
        bar = Progress(len(tasks), desc=f"stride {split}", unit="win")
        ctx = mp.get_context("fork" if os.name == "posix" else "spawn")
        with ProcessPoolExecutor(args.jobs, mp_context=ctx) as pool:
            for out in pool.map(_one_task, [(spec, t, args.strides) for t in tasks], chunksize=1):
                for k, r in out.items():
                    res[k].append(r)
                bar.update()
        bar.close()
        rows = {}
        for k in args.strides:
            s = dr_summary(res[k])
            per_s = schema.SAMPLE_RATE_HZ / k
            rows[k] = {"rmse_mean_m": s["rmse_mean_m"], "drift_mean_pct": s["drift_mean_pct"],
                       "coverage_pct": coverage(res[k]), "inferences_per_s": per_s,
                       "infer_ms_per_s": None if args.infer_ms is None else per_s * args.infer_ms,
                       "paired_vs_k1": None if k == 1 else paired_comparison(res[1], res[k])}
        doc["splits"][split] = rows
    return doc


def markdown(doc: dict) -> list[str]:
    out = ["60 s position RMSE [m], drift, 2σ / 3σ coverage and model cost per driven second, the runtime's default "
           f"filter, model `{Path(doc['model']).name}`. Paired: mean of (k − k=1) RMSE per window, 95 % interval.", "",
           "| split | stride k | model Hz | RMSE m | drift % | paired vs k = 1 m | 2σ / 3σ % | inference ms per s |",
           "|---|---:|---:|---:|---:|---|---|---:|"]
    for split, rows in doc["splits"].items():
        for k, r in rows.items():
            paired = paired_text(r["paired_vs_k1"])
            cost = "–" if r["infer_ms_per_s"] is None else f"{r['infer_ms_per_s']:.1f}"
            out.append(f"| {split} | {k} | {r['inferences_per_s']:g} | {r['rmse_mean_m']:.2f} | "
                       f"{r['drift_mean_pct']:.2f} | {paired} | {coverage_text(r['coverage_pct'])} | {cost} |")
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=str(HERE.parent / "data" / "bench"))
    p.add_argument("--model", default=str(HERE.parent / "export" / "default" / "prml2_edge.onnx"))
    p.add_argument("--splits", nargs="+", default=["test"])
    p.add_argument("--strides", nargs="+", type=int, default=[1, 2, 3, 5, 10, 25])
    p.add_argument("--infer-ms", type=float, default=None, help="the model's inference time [ms] for the cost column")
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--max-windows", type=int, default=None, help="at most N windows per drive segment")
    p.add_argument("--lag", type=int, default=0,
                   help="rows after its window that each output of a stride > 1 run is used (async inference)")
    p.add_argument("--out", default=str(OUT))
    args = p.parse_args(argv)
    if args.lag > 0:
        install_lag(args.lag)
    if 1 not in args.strides:
        args.strides = [1, *args.strides]
    t0 = time.time()
    doc = {"machine": machine_info(), **measure(args)}
    doc["wall_s"] = time.time() - t0
    write_json(doc, args.out)
    print("\n".join(markdown(doc)))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
