"""Self-calibration on replayed CAN logs: drives with known sensor errors, 20 s of GNSS, then an outage.

Each drive is simulated with a known CAN yaw-rate offset and wheel-radius error (``prml2 simulate
--yaw-offset-dps ... --wheel-scale-pct ...``), encoded with the project DBC and GNSS fixes for the
first ``--gnss-s`` seconds (``prml2 encode``), and replayed through the runtime twice in this run:
with the filter's calibration (the default) and without it (``--no-calibration``), the reference.
Reported per drive and as means: drift and RMSE over the outage, the share of steps inside the
reported 1/2/3-sigma ellipses, and the calibration estimate when GNSS was lost against the truth.
The drives' seeds are not the benchmark dataset's: the shipped model never saw them.

Usage::

    .venv/bin/python benchmarks/calibration_replay.py [--drives 6] [--seconds 60] [--gnss-s 20]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from prml2_edge.bench.machine import machine_info
from prml2_edge.can.encode import encode_drive_to_log
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.runtime.demo import compare_with_truth
from prml2_edge.runtime.pipeline import MemorySink, Pipeline, run_source
from prml2_edge.runtime.source import LogReplay

HERE = Path(__file__).resolve().parent
OUT = HERE / "results" / "calibration_replay.json"
LOG_DIR = HERE.parent / "out" / "bench_calibration"
SEED0 = 9000  # far from the benchmark recipe's seeds


def replay(log: Path, drive, calibration: bool) -> dict:
    mem = MemorySink()
    pipeline = Pipeline.build(sinks=[mem], calibration=calibration)
    with LogReplay(log) as source:
        run_source(pipeline, source)
    pipeline.close()
    m = compare_with_truth(mem.arrays(), drive)
    m["frames_balanced"] = pipeline.stats.balanced()
    return m


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drives", type=int, default=6)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--gnss-s", type=float, default=20.0)
    ap.add_argument("--yaw-offset-dps", type=float, default=-0.4)
    ap.add_argument("--wheel-scale-pct", type=float, default=1.0)
    args = ap.parse_args(argv)
    LOG_DIR.mkdir(parents=True, exist_ok=True)
    started = time.strftime("%Y-%m-%d %H:%M:%S")
    errors = {"yaw_offset_radps": math.radians(args.yaw_offset_dps), "wheel_radius_error": args.wheel_scale_pct / 100}
    rows = []
    for i in range(args.drives):
        seed = SEED0 + i
        drive = simulate_drive(args.seconds / 60.0, 1.0, seed, "mixed", name=f"cal_{seed}", sensor_errors=errors)
        log = LOG_DIR / f"cal_{seed}.log"
        encode_drive_to_log(drive, log, gnss_seconds=args.gnss_s)
        on, off = replay(log, drive, True), replay(log, drive, False)
        rows.append({"seed": seed, "calibrated": on, "reference": off})
        cal = on.get("calibration_at_outage", {})
        print(f"seed {seed}: drift {on['drift_pct']:.2f} % (without calibration {off['drift_pct']:.2f} %), "
              f"RMSE {on['rmse_m']:.1f} / {off['rmse_m']:.1f} m, 2σ/3σ {on.get('coverage_2sigma_pct', 0):.0f}/"
              f"{on.get('coverage_3sigma_pct', 0):.0f} % (without {off.get('coverage_2sigma_pct', 0):.0f}/"
              f"{off.get('coverage_3sigma_pct', 0):.0f} %), yaw offset {cal.get('yaw_rate_offset_dps', math.nan):+.3f}"
              f" °/s, wheel scale {cal.get('wheel_scale_pct', math.nan):+.2f} %", flush=True)

    def mean(side: str, key: str) -> float:
        return float(np.nanmean([r[side].get(key, math.nan) for r in rows]))

    summary = {side: {k: mean(side, k) for k in ("drift_pct", "rmse_m", "coverage_1sigma_pct",
                                                   "coverage_2sigma_pct", "coverage_3sigma_pct")}
               for side in ("calibrated", "reference")}
    cal = [r["calibrated"].get("calibration_at_outage", {}) for r in rows]
    summary["calibrated"]["yaw_offset_estimate_dps"] = float(np.mean([c["yaw_rate_offset_dps"] for c in cal]))
    summary["calibrated"]["wheel_scale_estimate_pct"] = float(np.mean([c["wheel_scale_pct"] for c in cal]))
    doc = {"started": started, "machine": machine_info(), "args": vars(args), "drives": rows, "summary": summary,
           "truth": {"yaw_offset_dps": args.yaw_offset_dps, "wheel_scale_pct": args.wheel_scale_pct}}
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(doc, indent=1, default=float))
    s, r = summary["calibrated"], summary["reference"]
    print(f"mean over {len(rows)} drives: drift {s['drift_pct']:.2f} % against {r['drift_pct']:.2f} % without "
          f"calibration; RMSE {s['rmse_m']:.1f} against {r['rmse_m']:.1f} m; coverage 1/2/3σ "
          f"{s['coverage_1sigma_pct']:.0f}/{s['coverage_2sigma_pct']:.0f}/{s['coverage_3sigma_pct']:.0f} % against "
          f"{r['coverage_1sigma_pct']:.0f}/{r['coverage_2sigma_pct']:.0f}/{r['coverage_3sigma_pct']:.0f} %; "
          f"estimates: yaw offset {s['yaw_offset_estimate_dps']:+.3f} °/s (truth {args.yaw_offset_dps:+.3f}), "
          f"wheel scale {s['wheel_scale_estimate_pct']:+.2f} % (truth {args.wheel_scale_pct:+.2f}, per-wheel "
          f"slip and the rear axle's share make the effective value a little lower)")
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
