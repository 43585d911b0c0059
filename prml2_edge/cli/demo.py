"""``prml2 demo``: replay a built-in simulated drive through the runtime and report pose and latency."""

from __future__ import annotations

import argparse

from prml2_edge.config import DEFAULT_STRIDE

HELP = "Replay a built-in simulated drive through the runtime and report pose and latency."
NEEDS: tuple[tuple[str, str], ...] = ()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="prml2-demo", metavar="DIR",
                        help="folder for the drive log, pose.jsonl and trajectory.png (default ./prml2-demo)")
    parser.add_argument("--seconds", type=float, default=90.0, help="drive length [s] (default 90)")
    parser.add_argument("--gnss-seconds", type=float, default=10.0,
                        help="GNSS fixes for the first N seconds, then an outage (default 10)")
    parser.add_argument("--seed", type=int, default=7, help="simulation seed (default 7)")
    parser.add_argument("--model", metavar="PATH", help="ONNX model (default: the shipped model)")
    parser.add_argument("--stride", type=int, default=DEFAULT_STRIDE,
                        help=f"a new model window every N steps (default {DEFAULT_STRIDE})")
    parser.add_argument("--threads", type=int, default=1, help="ONNX Runtime intra-op threads (default 1)")
    parser.add_argument("--no-plot", action="store_true", help="skip the PNG (drawn with matplotlib, the plot extra)")
    parser.add_argument("--summary-json", metavar="PATH", help="write the summary and metrics as JSON")


def run(args: argparse.Namespace) -> int:
    from prml2_edge.cli.runtime_app import summary_lines, write_summary_json
    from prml2_edge.errors import ConfigError
    from prml2_edge.progress import Progress
    from prml2_edge.runtime.demo import run_demo

    if not 10.0 <= args.seconds <= 3600.0:
        raise ConfigError(f"--seconds {args.seconds}: choose 10 to 3600 s")
    if not 0.0 < args.gnss_seconds < args.seconds:
        raise ConfigError(f"--gnss-seconds {args.gnss_seconds}: must be > 0 and shorter than --seconds")
    print(f"prml2 demo: simulating {args.seconds:.0f} s of driving (seed {args.seed}), encoding it with the project "
          f"DBC (GNSS for the first {args.gnss_seconds:.0f} s, then an outage), replaying it through a virtual CAN bus")
    with Progress(None, desc="replay", unit="frames") as bar:
        result = run_demo(args.out, model=args.model, seconds=args.seconds, gnss_seconds=args.gnss_seconds,
                          seed=args.seed, stride=args.stride, threads=args.threads, plot=not args.no_plot,
                          progress=bar)
    for line in summary_lines(result.summary):
        print(line)
    m = result.metrics
    print("pose track vs ground truth:")
    print(f"  GNSS-aided (first {result.gnss_seconds:.0f} s): RMSE {m['rmse_m_gnss']:.2f} m")
    for suffix, what in (("_60s", "first {:.0f} s of the outage"), ("", "whole outage ({:.0f} s)")):
        if f"rmse_m{suffix}" in m:
            print(f"  {what.format(m['duration_s' + suffix])}: RMSE {m['rmse_m' + suffix]:.2f} m, "
                  f"max {m['max_m' + suffix]:.2f} m, final {m['final_m' + suffix]:.2f} m "
                  f"over {m['distance_m' + suffix]:.0f} m (drift {m['drift_pct' + suffix]:.2f} %)")
    print("  paper, ReV-StED 60 s windows: PRML2 1.5 +- 1.2 m RMSE, 2.8 +- 2.2 m max; 1.07 % drift")
    if "coverage_2sigma_pct" in m:
        print(f"  uncertainty: errors inside the reported 1σ/2σ/3σ ellipses on {m['coverage_1sigma_pct']:.0f} / "
              f"{m['coverage_2sigma_pct']:.0f} / {m['coverage_3sigma_pct']:.0f} % of the outage's steps "
              "(consistent: 39 / 86 / 99)")
    cal = m.get("calibration_at_outage")
    if cal:
        print(f"  calibration learned while GNSS lasted: CAN yaw-rate offset {cal['yaw_rate_offset_dps']:+.3f} °/s, "
              f"wheel scale {cal['wheel_scale_pct']:+.2f} % (the drive's true yaw offset "
              f"{result.summary.get('true_yaw_offset_dps', float('nan')):+.3f} °/s)")
    print("latency per stage (this machine):")
    for line in result.latency_lines:
        print("  " + line)
    if result.plot_note:
        print(result.plot_note)
    print(f"files: {result.log_path} (replay it: prml2 replay {result.log_path}), {result.jsonl_path}"
          + (f", {result.plot_path}" if result.plot_path else ""))
    if args.summary_json:
        write_summary_json(args.summary_json, {**result.summary, "metrics": m})
    return 0
