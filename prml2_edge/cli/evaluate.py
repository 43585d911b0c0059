"""``prml2 evaluate``: evaluate models with the paper's protocol (z RMSE, 60 s dead reckoning)."""

from __future__ import annotations

import argparse
from pathlib import Path

from prml2_edge.errors import Prml2Error

HELP = "Evaluate models with the paper's protocol (z RMSE, 60 s dead reckoning)."
NEEDS: tuple[tuple[str, str], ...] = ()  # torch-free: ONNX models and the NumPy OSD baseline


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, metavar="DIR", help="dataset folder (prml2 simulate / ReV-StED)")
    parser.add_argument("--models", nargs="+", required=True, metavar="SPEC",
                        help="osd | NAME=osd | NAME=PATH.onnx | PATH.onnx (e.g. OSD-Baseline=osd "
                             "PRML2*=runs/onnx/prml2_star.onnx PRML2=export/default/prml2_edge.onnx)")
    parser.add_argument("--out", required=True, metavar="REPORT", help="output folder (report.md, metrics.json, PNG, "
                                                                      "tum/)")
    parser.add_argument("--stride", type=int, default=1,
                        help="streaming stride [samples] (default 1: method.md's protocol; the runtime's default is 5)")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    parser.add_argument("--ablation", metavar="NAME", default=None,
                        help="ONNX model for the Table 3 ablation (default: the one named PRML2, if any)")
    parser.add_argument("--max-windows", type=int, default=None, metavar="N",
                        help="at most N 60 s windows per drive segment (quick runs; default all)")
    parser.add_argument("--window-s", type=float, default=60.0, help="dead-reckoning window [s] (paper: 60)")
    parser.add_argument("--no-snow", action="store_true", help="skip the snow (low-mu) drives")
    parser.add_argument("--no-tum", action="store_true", help="do not write TUM trajectory files")
    parser.add_argument("--no-plots", action="store_true", help="do not write PNG figures")
    parser.add_argument("--calibration", choices=("off", "on", "both"), default="both",
                        help="the filter's self-calibration (calibration states, raw yaw-rate and wheel cues): "
                             "off, on (every learned model; the OSD baseline stays the paper's), or both side "
                             "by side as NAME and 'NAME +cal' (default both)")
    parser.add_argument("--preroll-s", type=float, default=30.0, metavar="S",
                        help="deployment protocol: every test window also after S s of GNSS-aided driving "
                             "(10 Hz fixes, 1.5 m); 0 skips it (default 30)")
    parser.add_argument("--unit-history-min", type=float, default=20.0, metavar="MIN",
                        help="minutes of each simulated car's earlier drives whose GNSS heading taught its "
                             "calibration file the gyro's gain, used by the '+cal' filter; 0: every drive a first "
                             "drive (default 20)")


def run(args: argparse.Namespace) -> int:
    from prml2_edge.evaluation.run import evaluate, parse_model_arg

    if args.stride < 1 or args.jobs < 1:
        raise Prml2Error("--stride and --jobs must be >= 1")
    specs = [parse_model_arg(m) for m in args.models]
    for s in specs:
        if s.path and not Path(s.path).is_file():
            raise Prml2Error(f"{s.name}: model file {s.path} not found")
    metrics = evaluate(args.data, specs, args.out, stride=args.stride, jobs=args.jobs, ablation=args.ablation,
                       max_windows=args.max_windows, snow=not args.no_snow, tum=not args.no_tum,
                       plots=not args.no_plots, window_s=args.window_s, calibration=args.calibration,
                       preroll_s=args.preroll_s, history_min=args.unit_history_min)
    print(f"{'model':<28} {'dry RMSE [m]':>14} {'dry ME [m]':>12} {'drift %':>8} {'snow RMSE [m]':>14} "
          f"{'deploy RMSE':>12} {'deploy drift %':>15} {'2σ / 3σ %':>12}")
    for name, m in metrics["models"].items():
        d = m["test"]["dead_reckoning_60s"]
        s = m.get("snow", {}).get("dead_reckoning_60s", {})
        dep = m.get("deployment", {}).get("dead_reckoning_60s", {})
        snow = f"{s['rmse_mean_m']:.2f}" if s.get("n_windows") else "-"
        drift = d.get("drift_mean_pct")
        dep_rmse = f"{dep['rmse_mean_m']:.2f}" if dep.get("n_windows") else "-"
        dep_drift = f"{dep['drift_mean_pct']:.2f}" if dep.get("drift_mean_pct") is not None else "-"
        cov = dep if dep.get("n_windows") else d
        cover = (f"{cov['coverage_2sigma_pct']:.0f} / {cov['coverage_3sigma_pct']:.0f}"
                 if "coverage_2sigma_pct" in cov else "-")
        print(f"{name:<28} {d['rmse_mean_m']:>14.2f} {d['me_mean_m']:>12.2f} "
              f"{(f'{drift:.2f}' if drift is not None else '-'):>8} {snow:>14} {dep_rmse:>12} {dep_drift:>15} "
              f"{cover:>12}")
    print(f"report: {Path(args.out) / 'report.md'} ({metrics['wall_s']:.0f} s)")
    return 0
