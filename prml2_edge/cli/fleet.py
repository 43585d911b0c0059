"""``prml2 fleet``: replay many CAN logs on a Dask cluster, one task per log; per-log outputs and one summary."""

from __future__ import annotations

import argparse

from prml2_edge.config import DEFAULT_STRIDE, DRIVEN_AXLES

HELP = "Replay many recorded CAN logs on a Dask cluster (local by default), one task per log, resumable."
NEEDS: tuple[tuple[str, str], ...] = (("distributed", "fleet"),)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("logs", nargs="+", metavar="LOG", help="CAN logs (.log, .asc, .blf, .trc, .csv)")
    parser.add_argument("--out", required=True, metavar="DIR",
                        help="output folder: logs/<name>/pose.tum and summary.json per log, fleet_summary.csv/.json")
    parser.add_argument("--address", metavar="TCP://HOST:PORT",
                        help="an existing Dask scheduler (its workers need prml2-edge, the logs and DIR on a shared "
                             "path); default: a local cluster on 127.0.0.1")
    parser.add_argument("--workers", type=int, default=None,
                        help="local cluster: worker processes, one log each at a time (default: this machine's CPUs)")
    g = parser.add_argument_group("vehicle and model (as for prml2 replay)")
    g.add_argument("--map", metavar="NAME|PATH", default="prml2_onboard", help="signal map (default prml2_onboard)")
    g.add_argument("--dbc", metavar="PATH", help="DBC file (default: the one the map names)")
    g.add_argument("--model", metavar="PATH", help="ONNX model (default: the shipped model)")
    g.add_argument("--mu", type=float, default=1.0, help="road friction for the physics guard (default 1.0)")
    g.add_argument("--driven-axle", choices=DRIVEN_AXLES, default="front",
                   help="the cars' driven axle: front (FWD, default), rear (RWD) or all (AWD)")
    g.add_argument("--steering-ratio", type=float, default=15.0,
                   help="steering wheel angle over road wheel angle (default 15)")
    g.add_argument("--stride", type=int, default=DEFAULT_STRIDE,
                   help=f"a new model window every N 50 Hz steps (default {DEFAULT_STRIDE})")
    g.add_argument("--stale-periods", type=float, default=3.0, help="signal staleness in periods (default 3)")
    g.add_argument("--no-calibration", action="store_true", help="the paper's filter (no calibration states)")
    g.add_argument("--initial-pose", metavar="X,Y,HEADING_DEG",
                   help="start pose of every log (default: each log's first GNSS fix)")


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from prml2_edge.errors import ConfigError, DataError
    from prml2_edge.fleet import run_fleet, table_lines
    from prml2_edge.progress import Progress
    from prml2_edge.runtime.initial_pose import InitialPose

    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {args.workers}")
    if args.workers is not None and args.address:
        raise ConfigError("--workers sizes the local cluster; an existing cluster (--address) has its own")
    if not args.steering_ratio > 0:
        raise ConfigError(f"--steering-ratio must be > 0, got {args.steering_ratio}")
    if args.stride < 1:
        raise ConfigError(f"--stride must be >= 1, got {args.stride}")
    model = str(Path(args.model).resolve()) if args.model else None
    if model is not None and not Path(model).is_file():
        raise ConfigError(f"{args.model}: model file not found")
    build = {"map": args.map, "dbc": str(Path(args.dbc).resolve()) if args.dbc else None, "model": model,
             "threads": 1, "stride": args.stride, "mu": args.mu, "stale_periods": args.stale_periods,
             "driven_axle": args.driven_axle, "steering_ratio": args.steering_ratio,
             "calibration": not args.no_calibration,
             "initial_pose": InitialPose.parse(args.initial_pose) if args.initial_pose else None}
    # Set-up errors (map, DBC, model) once here, in one line, rather than once per log on the cluster.
    from prml2_edge.runtime.pipeline import Pipeline

    Pipeline.build(**build)
    logs = [str(Path(p).resolve()) for p in args.logs]
    where = args.address or f"a local cluster of {args.workers or 'all'} worker(s) on 127.0.0.1"
    print(f"fleet: {len(logs)} logs on {where} -> {args.out}")
    with Progress(len(logs), desc="fleet", unit="logs") as bar:
        results, totals = run_fleet(logs, args.out, build, address=args.address, workers=args.workers, progress=bar)
    for line in table_lines(results, totals):
        print(line)
    print(f"wrote {Path(args.out) / 'fleet_summary.csv'} and fleet_summary.json")
    if totals["failed"]:
        raise DataError(f"{totals['failed']} of {totals['logs']} logs failed (reasons above and in "
                        f"{Path(args.out) / 'fleet_summary.csv'}); the others finished")
    return 0
