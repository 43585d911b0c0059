"""Is the runtime's filter consistent with what it fuses? Normalised innovations per cue, and their whiteness.

Every 60 s window of a split (paper protocol: from the true pose, GNSS off) through the runtime's default filter
(``prml2_edge.evaluation.protocol.run_window``, calibration on, the shipped model), with the EKF keeping each
update's innovations ``nu`` and their predicted variances ``S = diag(H P H^T + R)``
(:attr:`prml2_edge.ekf.numpy_ekf.Ekf.innovation_log`). Per cue, the model's five outputs, the CAN yaw rate and the
rear-axle wheel speed, over the normalised innovations ``e = nu / sqrt(S)``:

* **NIS**, the mean of ``e^2``: 1 for a filter whose stated variances are right, above 1 overconfident, below
  1 over-cautious (the model's ω_z next to a fine gyro is meant to be far below 1: its variance is inflated
  5 × 10^4 so that the gyro carries the yaw rate);
* **whiteness**, the autocorrelation of ``e`` at 1 step, 1 s and 5 s (pooled within windows): 0 for white
  innovations; near 1 where the error is slow and the filter takes every step's as new.

Usage::

    .venv/bin/python benchmarks/innovation_check.py [--data data/bench2] [--split val] [--jobs 2]
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from prml2_edge import schema
from prml2_edge.bench.machine import machine_info
from prml2_edge.bench.results import write_json
from prml2_edge.data.datasets import EVAL_SPLITS, load_dataset
from prml2_edge.ekf.numpy_ekf import Ekf
from prml2_edge.errors import DataError
from prml2_edge.evaluation.protocol import ModelSpec, run_window, split_tasks
from prml2_edge.progress import Progress
from prml2_edge.runtime.inference import default_model_path

HERE = Path(__file__).resolve().parent
OUT = HERE / "results" / "innovation_check.json"
MODEL_CUES = tuple(f"model {n}" for n in schema.STATE_NAMES)
CUES = (*MODEL_CUES, "CAN yaw rate", "rear wheel speed")
LAGS = {"1 step": 1, "1 s": 50, "5 s": 250}


def _series(log: list) -> dict[str, list[float]]:
    """Normalised innovations per cue, in step order (a cue absent at a step is left out)."""
    out: dict[str, list[float]] = {c: [] for c in CUES}
    for (model, yaw, wheel), nu, s in log:
        e = (nu / np.sqrt(s)).tolist()
        names = (MODEL_CUES if model else ()) + (("CAN yaw rate",) if yaw else ()) + \
            (("rear wheel speed",) if wheel else ())
        for name, v in zip(names, e, strict=True):
            out[name].append(v)
    return out


def _window(args: tuple[ModelSpec, object]) -> dict[str, list[float]]:
    spec, task = args
    Ekf.innovation_log = []
    try:
        run_window(spec, task)
        return _series(Ekf.innovation_log)
    finally:
        Ekf.innovation_log = None


def _acf(windows: list[np.ndarray], lag: int) -> float:
    """Autocorrelation at ``lag`` of the normalised innovations, pooled over windows (pairs within one window)."""
    num = den = 0.0
    for e in windows:
        e = e - e.mean() if e.size else e
        if e.size > lag:
            num += float(e[:-lag] @ e[lag:])
            den += float(e @ e) * (e.size - lag) / e.size
    return num / den if den > 0 else float("nan")


def summarise(per_window: list[dict[str, list[float]]]) -> dict:
    out = {}
    for cue in CUES:
        windows = [np.asarray(w[cue]) for w in per_window if w[cue]]
        if not windows:
            continue
        e = np.concatenate(windows)
        out[cue] = {"steps": int(e.size), "nis": float(np.mean(e * e)),
                    "acf": {name: _acf(windows, lag) for name, lag in LAGS.items()}}
    return out


def markdown(doc: dict) -> list[str]:
    lines = [f"| cue | steps | NIS (1: consistent) | {' | '.join(f'autocorrelation {k}' for k in LAGS)} |",
             "|---|---:|---:|" + "---:|" * len(LAGS)]
    for cue, r in doc["cues"].items():
        acf = " | ".join(f"{r['acf'][k]:.2f}" for k in LAGS)
        lines.append(f"| {cue} | {r['steps']} | {r['nis']:.3g} | {acf} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default="data/bench2")
    p.add_argument("--model", default=str(default_model_path()))
    p.add_argument("--split", default="val", choices=EVAL_SPLITS)
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--out", default=str(OUT))
    args = p.parse_args(argv)
    try:
        tasks = split_tasks(load_dataset(args.data), args.split)
    except DataError as e:
        print(f"innovation_check: {e}", file=sys.stderr)
        return 1
    if not tasks:
        print(f"no windows in split {args.split!r} of {args.data}", file=sys.stderr)
        return 1
    spec = ModelSpec("PRML2", "onnx", args.model, calibration=True)
    t0 = time.time()
    per_window = []
    with ProcessPoolExecutor(args.jobs) as pool, Progress(len(tasks), desc="innovations", unit="win") as bar:
        for res in pool.map(_window, [(spec, t) for t in tasks]):
            per_window.append(res)
            bar.update()
    doc = {"benchmark": "innovation_check", "data": args.data, "model": Path(args.model).name, "split": args.split,
           "windows": len(tasks), "seconds": round(time.time() - t0, 1), "machine": machine_info(),
           "cues": summarise(per_window)}
    write_json(doc, args.out)
    print("\n".join(markdown(doc)))
    print(f"{len(tasks)} windows of {args.split}, {doc['seconds']} s; written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
