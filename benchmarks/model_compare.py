"""Two models through the runtime's default filter, paired window by window on the validation splits (issue 26).

A training recipe change (an augmentation, a residual output, another seed) is chosen on validation by what the car
gets: the runtime's default filter (calibration on, the gyro gain its unit's earlier drives taught, the standstill
offset and wheel scale from its calibration file), in the paper protocol (60 s from the true pose, no GNSS) and in
the deployment protocol (30 s of GNSS first). ``filter_ablation.py`` varies the filter for one model; this varies
the model for the default filter: every window runs both models (and OSD, tuned on val, for scale), and the result
is the per-window difference B - A of the 60 s position RMSE with its paired bootstrap 95 % interval, per split,
protocol and car, with each model's drift and 2σ / 3σ coverage.

Splits: ``val`` (the fleet's validation drives, the real-car ones among them), ``dry_val`` and ``snow_val`` (the
fleet's dry test and snow drives simulated again with other seeds, as in ``filter_ablation.py``); ``test``,
``snow`` and ``heldout`` are there for the one report after the choice.

Usage::

    .venv/bin/python benchmarks/model_compare.py --data data/bench2 --a export/default/prml2_edge.onnx \\
        --b out/candidate.onnx [--splits val dry_val snow_val] [--protocols paper deployment] [--jobs 2]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from filter_ablation import DRY_VAL, OSD, PROTOCOLS, RESIMULATED, SNOW_VAL, by_car, resimulated

from prml2_edge.bench.results import announce, finish
from prml2_edge.data.datasets import load_dataset
from prml2_edge.evaluation.metrics import coverage, coverage_text, dr_summary, paired_comparison, paired_text
from prml2_edge.evaluation.protocol import ModelSpec, run_all, split_tasks
from prml2_edge.evaluation.tuning import tune_osd
from prml2_edge.evaluation.unit_history import HISTORY_MINUTES
from prml2_edge.progress import Progress

HERE = Path(__file__).resolve().parent
OUT = HERE / "results" / "model_compare.json"


def per_car(a: list, b: list) -> dict:
    """Per car: each model's mean RMSE [m] and B - A paired over that car's windows."""
    out = {}
    b_cars = by_car(b)
    for car, ca in by_car(a).items():
        cb = b_cars[car]
        out[car] = {"a_rmse_m": float(np.mean([r.rmse_m for r in ca])),
                    "b_rmse_m": float(np.mean([r.rmse_m for r in cb])), "b_minus_a": paired_comparison(ca, cb)}
    return out


def compare(a: list, b: list, osd: list) -> dict:
    """One split and protocol: both models' RMSE, drift and coverage, B - A paired, per car."""
    row = {"windows": len(a), "osd_rmse_m": dr_summary(osd)["rmse_mean_m"]}
    for name, res in (("a", a), ("b", b)):
        s = dr_summary(res)
        row[name] = {"rmse_mean_m": s["rmse_mean_m"], "drift_mean_pct": s["drift_mean_pct"],
                     "coverage_pct": coverage(res)}
    row["b_minus_a"] = paired_comparison(a, b)
    row["per_car"] = per_car(a, b)
    return row


def measure(args: argparse.Namespace) -> dict:
    dataset = load_dataset(args.data)
    specs = [ModelSpec("A", "onnx", args.a, calibration=True), ModelSpec("B", "onnx", args.b, calibration=True)]
    osd_spec = tune_osd(ModelSpec(OSD, "osd"), split_tasks(dataset, "val"), jobs=args.jobs)
    doc = {"data": str(args.data), "a": str(args.a), "b": str(args.b), "osd_q_scale": osd_spec.q_scale,
           "history_min": args.history_min, "rows": {}}
    for split in args.splits:
        source = resimulated(dataset.manifest, split) if split in RESIMULATED else dataset
        for protocol in args.protocols:
            tasks = split_tasks(source, split, max_windows=args.max_windows, preroll_s=PROTOCOLS[protocol],
                                history_min=args.history_min)
            if not tasks:
                continue
            bar = Progress(3 * len(tasks), desc=f"{split} / {protocol}", unit="win")
            res = run_all([osd_spec, *specs], tasks, jobs=args.jobs, on_done=lambda _r, bar=bar: bar.update())
            bar.close()
            row = doc["rows"][f"{split} / {protocol}"] = compare(res["A"], res["B"], res[OSD])
            print(f"{split} / {protocol}: B - A {paired_text(row['b_minus_a'])} m", file=sys.stderr, flush=True)
    return doc


def markdown(doc: dict) -> list[str]:
    out = [f"A = `{doc['a']}`, B = `{doc['b']}`, the runtime's default filter, on `{doc['data']}`. 60 s position RMSE "
           "[m], drift, 2σ / 3σ coverage; B − A paired per window with its bootstrap 95 % interval.", "",
           "| split / protocol | windows | OSD m | A m (drift %) | B m (drift %) | B − A m | A cov. % | B cov. % |",
           "|---|---:|---:|---|---|---|---|---|"]
    for key, r in doc["rows"].items():
        a, b = r["a"], r["b"]
        out.append(f"| {key} | {r['windows']} | {r['osd_rmse_m']:.2f} | {a['rmse_mean_m']:.2f} "
                   f"({a['drift_mean_pct']:.2f}) | {b['rmse_mean_m']:.2f} ({b['drift_mean_pct']:.2f}) | "
                   f"{paired_text(r['b_minus_a'])} | {coverage_text(a['coverage_pct'])} | "
                   f"{coverage_text(b['coverage_pct'])} |")
    out += ["", "| split / protocol | car | A m | B m | B − A m |", "|---|---|---:|---:|---|"]
    for key, r in doc["rows"].items():
        for car, c in r["per_car"].items():
            out.append(f"| {key} | {car} | {c['a_rmse_m']:.2f} | {c['b_rmse_m']:.2f} | {paired_text(c['b_minus_a'])} |")
    out += ["", f"OSD Q scale {doc['osd_q_scale']:g} (tuned on val). {doc['wall_s']:.0f} s."]
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=str(HERE.parent / "data" / "bench"))
    p.add_argument("--a", default=str(HERE.parent / "export" / "default" / "prml2_edge.onnx"),
                   help="the reference model (default: the shipped one)")
    p.add_argument("--b", required=True, help="the candidate model (.onnx from prml2 export --data)")
    p.add_argument("--splits", nargs="+", default=["val", DRY_VAL, SNOW_VAL],
                   choices=("val", DRY_VAL, SNOW_VAL, "test", "snow", "heldout"))
    p.add_argument("--protocols", nargs="+", choices=tuple(PROTOCOLS), default=list(PROTOCOLS))
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--max-windows", type=int, default=None, help="at most N windows per drive segment")
    p.add_argument("--history-min", type=float, default=HISTORY_MINUTES,
                   help="minutes of the car's earlier drives behind its calibration file (0: none)")
    p.add_argument("--out", default=str(OUT), help=f"result JSON (default {OUT.relative_to(HERE.parent)})")
    args = p.parse_args(argv)
    for name in (args.a, args.b):
        if not Path(name).is_file():
            p.error(f"no model file {name}: give the .onnx that prml2 export wrote")
    t0 = time.monotonic()
    doc = {"machine": announce("model_compare"), "args": vars(args), **measure(args)}
    finish(doc, args.out, markdown, t0)
    return 0


if __name__ == "__main__":
    sys.exit(main())
