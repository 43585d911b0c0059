"""What a car without brake pressure costs: the shipped model's 60 s dead reckoning with the brake-pressure
input replaced by what the runtime feeds for an absent signal (a signal map's ``absent = true``,
``substitute = VALUE``), against the measured signal it was trained with.

Windows: the benchmark recipe's validation split (``prml2 simulate --recipe benchmark``; the 12 dry drives'
10 % validation parts, 60 s non-overlapping windows, the paper protocol: no GNSS, true start state), the
shipped model ``export/default/prml2_edge.onnx`` through ``prml2_edge.evaluation.protocol.run_window``
(the streaming path ``prml2 evaluate`` uses). Variants: the measured brake pressure (reference), a constant
0 bar (the Toyota map's substitute), a constant 0.85 bar (the middle of the simulated idle level, about
the sample's), and ``substitute = "wheel_deceleration"``: derived from the deceleration of the mean
wheel speed over 0.2 s (idle 0.85 bar + 10 bar per m/s^2 of deceleration, the simulated car's brake gain).

Usage::

    .venv/bin/python benchmarks/brake_substitute.py [--data data/bench] [--jobs 2]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from prml2_edge import schema
from prml2_edge.bench.machine import machine_info
from prml2_edge.bench.results import write_json
from prml2_edge.can.signal_map import DECEL_BAR_PER_MPS2, DECEL_IDLE_BAR
from prml2_edge.data.datasets import generate_dataset, load_dataset
from prml2_edge.evaluation.protocol import ModelSpec, run_all, split_tasks
from prml2_edge.runtime.assembler import wheel_deceleration_substitute

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
OUT = HERE / "results" / "brake_substitute.json"
BRAKE = schema.SIGNAL_BY_NAME["brake_pressure_bar"].index


def decel_brake(onboard: np.ndarray) -> np.ndarray:
    """The runtime's ``substitute = "wheel_deceleration"`` with its defaults (the assembler's own formula)."""
    return wheel_deceleration_substitute(onboard, DECEL_IDLE_BAR, DECEL_BAR_PER_MPS2)


def _with_brake(onboard: np.ndarray, fn) -> np.ndarray:
    out = onboard.copy()
    out[:, BRAKE] = fn(onboard)
    return out


VARIANTS = {
    "measured (trained with)": None,
    "constant 0 bar": lambda o: np.zeros(len(o)),
    "constant 0.85 bar": lambda o: np.full(len(o), 0.85),
    "wheel_deceleration (0.85 bar + 10 bar per m/s^2)": decel_brake,
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(REPO / "data" / "bench"))
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--model", default=str(REPO / "export" / "default" / "prml2_edge.onnx"))
    args = ap.parse_args(argv)
    data = Path(args.data)
    if not (data / "manifest.json").is_file():
        print(f"simulating the benchmark recipe into {data} ...", flush=True)
        generate_dataset(data, "benchmark", workers=args.jobs, progress=False)
    tasks = split_tasks(load_dataset(data), "val")
    if not tasks:
        raise SystemExit(f"{data}: no validation windows (not a benchmark-recipe dataset of this version?)")
    spec = ModelSpec("PRML2", "onnx", args.model)
    t0 = time.time()
    rows = {}
    for name, fn in VARIANTS.items():
        variant = tasks if fn is None else [dataclasses.replace(t, onboard=_with_brake(t.onboard, fn)) for t in tasks]
        results = run_all([spec], variant, jobs=args.jobs)["PRML2"]
        rmse = np.array([r.rmse_m for r in results])
        drift = np.array([r.drift_pct for r in results])
        rows[name] = {"rmse_m_mean": float(rmse.mean()), "rmse_m_std": float(rmse.std()),
                      "drift_pct_mean": float(np.nanmean(drift)), "rmse_m": rmse.tolist()}
        print(f"{name:<46} 60 s RMSE {rmse.mean():6.2f} +- {rmse.std():5.2f} m, drift {np.nanmean(drift):5.2f} %",
              flush=True)
    ref = np.array(rows["measured (trained with)"]["rmse_m"])
    for r in rows.values():
        d = np.array(r["rmse_m"]) - ref
        r["paired_diff_m_mean"] = float(d.mean())
        r["windows_worse"] = int((d > 0).sum())
    out = {"benchmark": "brake_substitute", "windows": len(tasks), "model": args.model, "data": str(data),
           "wall_s": time.time() - t0, "machine": machine_info(), "results": rows}
    write_json(out, OUT)
    print(f"{len(tasks)} windows, {time.time() - t0:.0f} s; wrote {OUT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
