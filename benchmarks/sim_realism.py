"""Simulator realism: which sensor-model choice makes the simulated benchmark harsher than real roads.

The anchor is the paper's OSD-Baseline row on real ReV-StED drives (60 s windows from the true
pose: 5.3 ± 2.1 m dry). This script dead-reckons the OSD baseline's z (mean wheel speed, yaw rate
minus its standstill bias; ``prml2_edge.evaluation.osd``) by plain kinematic integration over
non-overlapping 60 s windows of simulated drives, for the sensor model as it is now and with one
choice changed at a time, on every car of the fleet, in one run. (The OSD row of ``prml2
evaluate`` runs the same z through the tuned EKF; this integrator isolates the sensors.)

Usage::

    .venv/bin/python benchmarks/sim_realism.py [--drives 4] [--minutes 5] [--json benchmarks/results/sim_realism.json]
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

from prml2_edge import schema
from prml2_edge.bench.machine import machine_info
from prml2_edge.bench.results import write_json
from prml2_edge.data.simulate import CARS, simulate_drive
from prml2_edge.evaluation.osd import drive_bias, osd_baseline_z
from prml2_edge.schema import Z

REPO = Path(__file__).resolve().parents[1]
_DEG = schema.DEG_TO_RAD
WINDOW_S = 60.0


def variants(car):
    """(name, car) pairs: the sensor model now, and one choice changed at a time."""
    s = car.sensors
    return [
        ("now", car),
        ("before: yaw offset sigma 0.25 deg/s, no gain error or drift",
         replace(car, sensors=replace(s, yaw_offset_dps=0.25, yaw_scale_sigma=0.0, yaw_drift_dps=0.0))),
        ("yaw offset sigma 0.25 deg/s", replace(car, sensors=replace(s, yaw_offset_dps=0.25))),
        ("no yaw gain error", replace(car, sensors=replace(s, yaw_scale_sigma=0.0))),
        ("no yaw offset drift", replace(car, sensors=replace(s, yaw_drift_dps=0.0))),
        ("no yaw quantisation", replace(car, sensors=replace(s, steps=(*s.steps, ("yaw_rate_radps", 1e-9))))),
    ]


def osd_windows(drive) -> list[tuple[float, float]]:
    """(RMSE [m], drift [%]) of the OSD z integrated from the true pose over each 60 s window."""
    n = int(WINDOW_S / schema.DT_S)
    z = osd_baseline_z(drive.onboard, drive_bias(drive.onboard))
    out = []
    for s in range(schema.WINDOW_LEN - 1, len(drive) - n, n):
        x0, y0, psi0 = drive.pose_gt[s]
        v, w = z[s:s + n, Z.V_X], z[s:s + n, Z.OMEGA_Z]
        psi = psi0 + np.concatenate([[0.0], np.cumsum(w[:-1]) * schema.DT_S])
        px = x0 + np.concatenate([[0.0], np.cumsum(v[:-1] * np.cos(psi[:-1])) * schema.DT_S])
        py = y0 + np.concatenate([[0.0], np.cumsum(v[:-1] * np.sin(psi[:-1])) * schema.DT_S])
        gt = drive.pose_gt[s:s + n]
        err = np.hypot(px - gt[:, 0], py - gt[:, 1])
        dist = float(np.sum(np.hypot(np.diff(gt[:, 0]), np.diff(gt[:, 1]))))
        out.append((float(np.sqrt(np.mean(err**2))), float(100 * err[-1] / max(dist, 1.0))))
    return out


def _job(args):
    variant, car, family, seed, mu, minutes = args
    return variant, car.name, family == "snow", osd_windows(simulate_drive(minutes, mu, seed, family, vehicle=car))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drives", type=int, default=4, help="dry drives per car and variant (families rotate)")
    ap.add_argument("--snow-drives", type=int, default=2, help="snow drives per car (variant 'now' only)")
    ap.add_argument("--minutes", type=float, default=5.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "sim_realism.json"))
    args = ap.parse_args(argv)
    fams = ("longitudinal", "lateral", "mixed", "mixed")
    jobs = []
    for car in CARS.values():
        for name, v in variants(car):
            jobs += [(name, v, fams[i % 4], 7000 + i, 0.9, args.minutes) for i in range(args.drives)]
        jobs += [("now", car, "snow", 7100 + i, (0.2, 0.3, 0.4, 0.5)[i % 4], args.minutes)
                 for i in range(args.snow_drives)]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(args.workers) as pool:
        results = list(pool.map(_job, jobs))
    wall = time.perf_counter() - t0
    table: dict = {}
    for variant, car, snow, wins in results:
        table.setdefault((variant, "snow" if snow else "dry"), {}).setdefault(car, []).extend(wins)

    def stats(wins):
        a = np.asarray(wins)
        return {"rmse_mean_m": float(a[:, 0].mean()), "rmse_std_m": float(a[:, 0].std()),
                "drift_mean_pct": float(a[:, 1].mean()), "n_windows": len(a)}

    rows = []
    print(f"OSD z dead-reckoned over {WINDOW_S:g} s windows (paper, real ReV-StED: dry 5.3 ± 2.1 m, "
          f"snow 5.7 ± 3.1 m); {args.drives} dry drives of {args.minutes:g} min per car and variant\n")
    print("| variant | split | " + " | ".join(CARS) + " | fleet |")
    print("|---|---|" + "---|" * (len(CARS) + 1))
    for (variant, split), per_car in table.items():
        cells = {car: stats(w) for car, w in per_car.items()}
        fleet = stats([x for w in per_car.values() for x in w])
        rows.append({"variant": variant, "split": split, "cars": cells, "fleet": fleet})
        print(f"| {variant} | {split} | " + " | ".join(
            f"{cells[c]['rmse_mean_m']:.1f} ({cells[c]['drift_mean_pct']:.2f} %)" for c in CARS) +
            f" | **{fleet['rmse_mean_m']:.1f} ± {fleet['rmse_std_m']:.1f}** ({fleet['drift_mean_pct']:.2f} %) |")
    print(f"\n{len(jobs)} drives in {wall:.0f} s; cells: mean RMSE [m] (drift)")
    info = machine_info()
    print(f"machine: {info['cpu_model']}, flags {', '.join(info['flags'])}; load {info.get('load_average')}")
    doc = {"started": time.strftime("%Y-%m-%d %H:%M:%S"), "machine": info, "args": vars(args), "rows": rows,
           "wall_s": wall}
    out = write_json(doc, args.json)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
