"""``prml2 demo``: a built-in drive, encoded on the fly, replayed through the real runtime.

Simulate a drive (:func:`prml2_edge.data.simulate.simulate_drive`), encode it with the project
DBC into a candump log with GNSS fixes for the first seconds only
(:func:`prml2_edge.can.encode.encode_drive_to_log`), replay the log through a python-can
virtual bus into the same :class:`~prml2_edge.runtime.pipeline.Pipeline` ``prml2 replay`` uses,
and compare the estimate with the simulator's ground truth: after the last fix the runtime
dead-reckons, the GNSS-outage case of the paper. Needs only the runtime's dependencies.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from prml2_edge import schema
from prml2_edge.config import DEFAULT_STRIDE
from prml2_edge.dead_reckoning import trajectory_metrics
from prml2_edge.runtime.pipeline import MemorySink, Pipeline, run_source
from prml2_edge.runtime.sinks import JsonlSink
from prml2_edge.runtime.source import LogReplay
from prml2_edge.schema import EkfState


@dataclass
class DemoResult:
    """What the demo measured. Errors are planar position errors [m] against ground truth."""

    log_path: Path
    jsonl_path: Path
    plot_path: Path | None
    summary: dict
    t_s: np.ndarray  # (N,) step times [s]
    estimate: np.ndarray  # (N, 3) x, y [m], psi [rad]
    truth: np.ndarray  # (N, 3)
    gnss_seconds: float
    metrics: dict = field(default_factory=dict)
    latency_lines: list[str] = field(default_factory=list)  # LatencyRecorder.report_lines()
    plot_note: str | None = None  # why no plot was drawn (matplotlib missing), one line


def align_with_truth(arrays: dict[str, np.ndarray], drive) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows matched to the drive by time: true pose (N, 3), estimated pose (N, 3), and which rows have one."""
    k = np.clip(np.rint((arrays["t_s"] - drive.t_s[0]) / schema.DT_S).astype(np.int64), 0, len(drive) - 1)
    estimate = arrays["x"][:, [EkfState.POS.start, EkfState.POS.start + 1, EkfState.YAW.start]]
    return drive.pose_gt[k].copy(), estimate, np.all(np.isfinite(estimate), axis=1)


def compare_with_truth(arrays: dict[str, np.ndarray], drive, outage_start_s: float | None = None) -> dict:
    """A replay's :class:`MemorySink` arrays against a drive's ground truth (rows matched by time).

    The outage starts at ``outage_start_s`` or, by default, at the first step flagged ``gnss_outage``
    (the drive's start when no fix was ever fused). Returns :func:`trajectory_metrics`, the coverage of
    the reported 1/2/3-sigma ellipses over the outage, and the calibration states at the outage start.
    """
    from prml2_edge.ekf.numpy_ekf import coverage_pct, mahalanobis2

    t_s = arrays["t_s"]
    truth, estimate, ok = align_with_truth(arrays, drive)
    est = estimate[:, :2]
    if outage_start_s is None:
        lost = np.flatnonzero(arrays["gnss_outage"])
        outage_start_s = float(t_s[lost[0]]) if lost.size else float(t_s[ok][0]) if ok.any() else float(t_s[0])
    out = trajectory_metrics(t_s[ok], est[ok], truth[ok, :2], outage_start_s)
    out["outage_start_s"] = outage_start_s
    in_outage = ok & (t_s >= outage_start_s)
    if "pos_cov" in arrays and in_outage.any():
        out.update(coverage_pct(mahalanobis2(est[in_outage] - truth[in_outage, :2], arrays["pos_cov"][in_outage])))
        out["final_pos_std_m"] = float(arrays["pos_std_m"][in_outage][-1])
    cal = arrays.get("cal")
    if cal is not None and in_outage.any() and np.isfinite(cal[in_outage][0]).all():
        c = cal[in_outage][0]
        out["calibration_at_outage"] = {"yaw_rate_offset_dps": math.degrees(float(c[0])),
                                        "wheel_scale_pct": 100.0 * float(c[1])}
    return out


def truth_lines(m: dict) -> list[str]:
    """``compare_with_truth`` for the terminal."""
    if "rmse_m" not in m:
        return ["vs ground truth: no outage to compare"]
    lines = [f"vs ground truth: outage from {m['outage_start_s']:.1f} s, {m['duration_s']:.1f} s over "
             f"{m['distance_m']:.0f} m: RMSE {m['rmse_m']:.2f} m, final error {m['final_m']:.2f} m "
             f"(drift {m['drift_pct']:.2f} %), GNSS-aided RMSE {m['rmse_m_gnss']:.2f} m"]
    if "coverage_1sigma_pct" in m:
        lines.append(f"uncertainty: final ±{m['final_pos_std_m']:.1f} m; errors inside the 1σ/2σ/3σ ellipses "
                     f"{m['coverage_1sigma_pct']:.0f} / {m['coverage_2sigma_pct']:.0f} / "
                     f"{m['coverage_3sigma_pct']:.0f} % of steps (consistent: 39 / 86 / 99)")
    cal = m.get("calibration_at_outage")
    if cal:
        lines.append(f"calibration when GNSS was lost: yaw-rate offset {cal['yaw_rate_offset_dps']:+.3f} °/s, "
                     f"wheel scale {cal['wheel_scale_pct']:+.2f} %")
    return lines


def run_demo(out_dir: str | Path, model: str | Path | None = None, seconds: float = 90.0,
             gnss_seconds: float = 10.0, seed: int = 7, mu: float = 1.0, family: str = "mixed",
             stride: int = DEFAULT_STRIDE, threads: int = 1, plot: bool = True, progress=None) -> DemoResult:
    """Simulate, encode, replay and compare; files go to ``out_dir`` (log, JSON lines, PNG)."""
    from prml2_edge.can.encode import encode_drive_to_log
    from prml2_edge.data.simulate import simulate_drive

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    # Build the pipeline first: a missing model or DBC fails before any work.
    mem = MemorySink()
    jsonl_path = out_dir / "pose.jsonl"
    pipeline = Pipeline.build(model=model, threads=threads, stride=stride, mu=mu, sinks=[mem])
    drive = simulate_drive(seconds / 60.0, mu, seed, family=family, name="demo")
    log_path = out_dir / "demo_drive.log"
    encode_drive_to_log(drive, log_path, gnss_seconds=gnss_seconds)
    jsonl = JsonlSink(jsonl_path)
    pipeline.sinks.append(jsonl)
    try:
        with LogReplay(log_path) as source:
            run_source(pipeline, source, progress=progress)
    finally:
        pipeline.close()
    arrays = mem.arrays()
    t_s = arrays["t_s"]
    truth, estimate, ok = align_with_truth(arrays, drive)
    metrics = compare_with_truth(arrays, drive, drive.t_s[0] + gnss_seconds)
    plot_path = plot_note = None
    if plot:
        from prml2_edge.viz import plots

        if plots.available():
            plot_path = plot_trajectory(out_dir / "trajectory.png", estimate[ok, :2], truth[ok, :2],
                                        t_s[ok] < drive.t_s[0] + gnss_seconds, metrics)
        else:
            plot_note = plots.missing_message(str(out_dir / "trajectory.png"))
    summary = pipeline.summary()
    summary["true_yaw_offset_dps"] = math.degrees(drive.meta["sensor_errors"]["yaw_offset_radps"])
    return DemoResult(log_path, jsonl_path, plot_path, summary, t_s, estimate, truth, gnss_seconds, metrics,
                      pipeline.latency.report_lines(), plot_note)


def plot_trajectory(path: Path, est_xy: np.ndarray, gt_xy: np.ndarray, gnss_mask: np.ndarray,
                    metrics: dict) -> Path:
    """Ground truth vs estimate (GNSS-aided part and dead-reckoning part in their own colours) as PNG."""
    from prml2_edge.viz.plots import plot_demo_trajectory

    rmse = metrics.get("rmse_m")
    title = "PRML2 demo" + (f": outage RMSE {rmse:.1f} m, drift {metrics.get('drift_pct', float('nan')):.1f} %"
                            if rmse is not None else "")
    return plot_demo_trajectory(path, est_xy, gt_xy, gnss_mask, title)
