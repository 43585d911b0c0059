"""``prml2 simulate``: simulate drives and write ReV-StED-schema CSV files.

One drive: ``prml2 simulate --out DIR --minutes M --mu MU --seed S [--family F]``
(writes ``DIR/drives/<name>.csv`` and a manifest, so DIR is a dataset). A dataset:
``prml2 simulate --recipe benchmark|small --out DIR [--workers 2]``.
"""

from __future__ import annotations

import argparse

HELP = "Simulate drives and write ReV-StED-schema CSV files."
NEEDS: tuple[tuple[str, str], ...] = ()
FAMILIES = ("longitudinal", "lateral", "mixed", "snow", "highway")  # mirrors prml2_edge.data.simulate.FAMILIES


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, help="output folder (becomes a dataset: drives/*.csv + manifest.json)")
    parser.add_argument("--recipe", help="write a whole dataset: 'benchmark' (a fleet of 5 cars with their own "
                        "train/val/test/snow drives and a held-out 6th car; ~3.8 h) or 'small' (10 min, a drive "
                        "per split: enough for train and evaluate, for quick tries)")
    parser.add_argument("--minutes", type=float, default=5.0, help="duration of a single drive [min] (default 5)")
    parser.add_argument("--mu", type=float, default=1.0, help="friction coefficient (1.0 dry; snow 0.2-0.5)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (same seed, same drive)")
    parser.add_argument("--family", choices=FAMILIES, default=None,
                        help="manoeuvre family (default: mixed, or snow when mu <= 0.5)")
    parser.add_argument("--name", default=None, help="drive name (default sim_<family>_s<seed>)")
    parser.add_argument("--vehicle", default="reference",
                        help="single drive: car of the simulated fleet (default reference; see docs/data.md)")
    parser.add_argument("--workers", type=int, default=2, help="worker processes for --recipe (default 2)")
    parser.add_argument("--yaw-offset-dps", type=float, default=None, metavar="DEG_S",
                        help="single drive: this CAN yaw-rate offset [deg/s] instead of a random one")
    parser.add_argument("--wheel-scale-pct", type=float, default=None, metavar="PCT",
                        help="single drive: every wheel reads this much fast [%%] (rolling-radius error) instead "
                             "of random per-wheel errors")


def run(args: argparse.Namespace) -> int:
    import math
    import time

    from prml2_edge.data.datasets import generate_dataset, load_dataset
    from prml2_edge.errors import ConfigError

    t0 = time.monotonic()
    if args.recipe:
        out = generate_dataset(args.out, args.recipe, workers=args.workers, progress=True)
    else:
        if args.minutes <= 0:
            raise ConfigError(f"--minutes must be > 0, got {args.minutes}")
        family = args.family or ("snow" if args.mu <= 0.5 else "mixed")
        name = args.name or f"sim_{family}_s{args.seed}"
        role = "snow" if family == "snow" else "dry"
        errors = {}
        if args.yaw_offset_dps is not None:
            errors["yaw_offset_radps"] = math.radians(args.yaw_offset_dps)
        if args.wheel_scale_pct is not None:
            errors["wheel_radius_error"] = args.wheel_scale_pct / 100.0
        drive_spec = {"name": name, "family": family, "mu": args.mu, "seed": args.seed, "minutes": args.minutes,
                      "role": role, "vehicle": args.vehicle}
        if errors:
            drive_spec["sensor_errors"] = errors
        recipe = {"name": "single", "drives": [drive_spec]}
        out = generate_dataset(args.out, recipe, workers=1, progress=True)
    ds = load_dataset(out)
    minutes = sum(len(d) for d in ds.drives) / 50.0 / 60.0
    print(f"wrote {len(ds.drives)} drive(s), {minutes:.1f} min at 50 Hz, to {out} "
          f"(fingerprint {ds.fingerprint[:12]}, {time.monotonic() - t0:.1f} s)")
    for d in ds.drives:
        print(f"  {d.path}")
    return 0
