"""Onboard sensor profile: the real ReV-StED sample versus simulated drives.

Measures, per signal, quantisation step, hold (run) lengths, change share and value range
on ``OBD_Sample.csv`` and on simulated drives (fixed seeds), prints a markdown table and
writes JSON. Usage::

    .venv/bin/python benchmarks/sensor_profile.py [--shared ../shared] [--minutes 10] [--json PATH]

The JSON goes to ``benchmarks/results/sensor_profile.json`` unless ``--json`` says otherwise.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

from prml2_edge.bench.machine import provenance
from prml2_edge.data.profile import compare_profiles, signal_profile, speedometer_ratio
from prml2_edge.data.revsted import load_drive
from prml2_edge.data.simulate import simulate_drive

REPO = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shared", default=str(REPO.parent / "shared"), help="the shared folder with data/revsted")
    ap.add_argument("--minutes", type=float, default=10.0, help="simulated minutes (mixed family, mu 1.0)")
    ap.add_argument("--seeds", default="7,8,9", help="comma-separated simulator seeds")
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "sensor_profile.json"),
                    help="JSON output path")
    args = ap.parse_args(argv)

    real = load_drive(Path(args.shared) / "data" / "revsted" / "OBD_Sample.csv")
    seeds = [int(s) for s in args.seeds.split(",")]
    t0 = time.perf_counter()
    sims = [simulate_drive(args.minutes, 1.0, seed, "mixed") for seed in seeds]
    sim_s = time.perf_counter() - t0
    sim_onboard = np.concatenate([d.onboard for d in sims])
    # profile each simulated drive separately (holds must not run across drives), then pool the medians
    rows_per_seed = [compare_profiles(signal_profile(real.onboard), signal_profile(d.onboard)) for d in sims]
    rows = rows_per_seed[0]
    for k, row in enumerate(rows):
        for key in ("hold_median_sim", "hold_p90_sim", "change_sim", "range_ratio"):
            row[key] = float(np.median([r[k][key] for r in rows_per_seed]))
        for key in ("step_ok", "hold_ok", "range_ok"):
            row[key] = all(r[k][key] for r in rows_per_seed)
    ratio_real, ratio_sim = speedometer_ratio(real.onboard), speedometer_ratio(sim_onboard)

    print(f"Onboard sensor profile: OBD_Sample.csv (20 s) vs {len(seeds)} simulated mixed drives of "
          f"{args.minutes:g} min (seeds {args.seeds}; holds: median over seeds, ranges: first seed); "
          "moving samples only\n")
    print("| signal | unit | step real / sim | hold median real / sim | hold p90 real / sim "
          "| changing samples real / sim | p5..p95 real | p5..p95 sim | ok |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        ok = "yes" if r["step_ok"] and r["hold_ok"] and r["range_ok"] else "NO"
        print(f"| {r['column']} | {r['unit']} | {r['step_real']:g} / {r['step_sim']:g} "
              f"| {r['hold_median_real']:g} / {r['hold_median_sim']:g} "
              f"| {r['hold_p90_real']:g} / {r['hold_p90_sim']:g} "
              f"| {r['change_real']:.2f} / {r['change_sim']:.2f} "
              f"| {r['range_real'][0]:.2f}..{r['range_real'][1]:.2f} "
              f"| {r['range_sim'][0]:.2f}..{r['range_sim'][1]:.2f} "
              f"| {ok} |")
    print(f"\nspeedometer / mean wheel speed: real {ratio_real:.3f}, sim {ratio_sim:.3f}")
    print(f"simulation time: {sim_s:.1f} s for {len(seeds) * args.minutes:g} min")
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({
        "rows": rows, "speedometer_ratio": {"real": ratio_real, "sim": ratio_sim}, "seeds": seeds,
        "minutes": args.minutes, "simulate_s": sim_s,
        "machine": {"python": sys.version.split()[0], "platform": platform.platform(), "numpy": np.__version__,
                    **provenance()},
    }, indent=1) + "\n")
    print(f"wrote {out}")
    return 0 if all(r["step_ok"] and r["hold_ok"] and r["range_ok"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
