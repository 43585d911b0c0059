"""Are the errors the filter fuses as large as their variances say, over the time scales that integrate into a pose?

For each cue on the validation split's 60 s windows (issue 26): the model's five states, streamed as the runtime
streams them (``prml2_edge.evaluation.protocol.run_all``, calibration off), and the CAN yaw rate less the drive's
standstill offset, with the variance the calibrated filter gives it (``yaw_cue_std`` and ``yaw_cue_quant_gain``
times the resolution the filter measures: the 10th percentile of the steps between distinct readings). Printed
per cue and stretch length T: the measured variance of T-second mean errors over the variance the stated
per-step variances give them if the errors were independent (``prml2_edge.evaluation.error_model``). 1 at every
T: white and consistent; growing with T: the error is slow, and the EKF, which takes every step's error as new,
trusts the cue's T-second means that many times too much. The model's figure at T = 5 s is what
``prml2 export --data`` stores as its variance inflation.

Usage::

    .venv/bin/python benchmarks/cue_consistency.py [--data data/bench] [--model export/default/prml2_edge.onnx]
        [--split val] [--jobs 2]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from prml2_edge import schema
from prml2_edge.bench.machine import machine_info
from prml2_edge.bench.results import write_json
from prml2_edge.data.datasets import load_dataset
from prml2_edge.evaluation.error_model import consistency, model_errors
from prml2_edge.evaluation.protocol import ModelSpec, run_all, split_tasks
from prml2_edge.runtime.filter import yaw_cue_var
from prml2_edge.runtime.localizer import LocalizerConfig

HERE = Path(__file__).resolve().parent
OUT = HERE / "results" / "cue_consistency.json"
SCALES_S = (0.02, 1.0, 5.0, 20.0)
_YAW = schema.SIGNAL_BY_NAME["yaw_rate_radps"].index


def yaw_cue_errors(tasks, cfg: LocalizerConfig) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per window: the CAN yaw rate less the standstill offset minus the truth (n, 1), and the filter's variance."""
    errs, vars_ = [], []
    for t in tasks:
        yaw = t.onboard[t.history + t.preroll:, _YAW]
        steps = np.abs(np.diff(yaw))
        steps = steps[steps > 0]
        res = float(np.percentile(steps, 10)) if len(steps) else cfg.yaw_cue_resolution_radps
        var = yaw_cue_var(cfg, res)
        errs.append((yaw - t.bias.yaw_rate_radps - t.z_gt[:, schema.Z.OMEGA_Z])[:, None])
        vars_.append(np.full((len(yaw), 1), var))
    return errs, vars_


def measure(args: argparse.Namespace) -> dict:
    dataset = load_dataset(args.data)
    tasks = split_tasks(dataset, args.split)
    if not tasks:
        raise SystemExit(f"{args.data}: no 60 s {args.split} window")
    results = run_all([ModelSpec("model", "onnx", str(args.model))], tasks, jobs=args.jobs)["model"]
    m_err, m_var = model_errors(results, tasks)
    y_err, y_var = yaw_cue_errors(tasks, LocalizerConfig())
    model = consistency(m_err, m_var, SCALES_S)
    cues = {name: {str(t): ratios[i] for t, ratios in model.items()} for i, name in enumerate(schema.STATE_NAMES)}
    cues["CAN yaw rate (filter's variance)"] = {str(t): r[0] for t, r in consistency(y_err, y_var, SCALES_S).items()}
    return {"data": str(args.data), "split": args.split, "model": str(args.model), "windows": len(tasks),
            "scales_s": list(SCALES_S), "ratio": cues}


def markdown(doc: dict) -> list[str]:
    scales = doc["scales_s"]
    out = [f"Measured over stated variance of T-second mean errors, {doc['windows']} windows of the "
           f"`{doc['split']}` split of `{doc['data']}`, model `{Path(doc['model']).name}`.", "",
           "| cue | " + " | ".join(f"T = {t:g} s" for t in scales) + " |", "|---|" + "---:|" * len(scales)]
    for name, by_t in doc["ratio"].items():
        out.append(f"| {name} | " + " | ".join(f"{by_t[str(t)]:.3g}" for t in scales) + " |")
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=str(HERE.parent / "data" / "bench"))
    p.add_argument("--model", default=str(HERE.parent / "export" / "default" / "prml2_edge.onnx"))
    p.add_argument("--split", default="val")
    p.add_argument("--jobs", type=int, default=2)
    args = p.parse_args(argv)
    doc = {"machine": machine_info(), **measure(args)}
    write_json(doc, OUT)
    print("\n".join(markdown(doc)))
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
