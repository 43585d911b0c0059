"""``prml2 evaluate`` end to end: tune on val, run every model on test and snow, write the report."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from prml2_edge.evaluation.metrics import dr_summary, paired_comparison, z_rmse
from prml2_edge.evaluation.protocol import (
    DEPLOYMENT_PREROLL_S,
    DR_WINDOW_S,
    OSD_Q_SCALES,
    ModelSpec,
    Tuning,
    WindowResult,
    WindowTask,
    run_all,
    split_tasks,
    tune_constant_variance,
    tune_osd,
)
from prml2_edge.progress import Progress

log = logging.getLogger(__name__)


def parse_model_arg(text: str) -> ModelSpec:
    """``osd`` / ``NAME=osd`` (the OSD baseline) or ``NAME=PATH.onnx`` / ``PATH.onnx`` (name: file stem)."""
    name, sep, value = text.partition("=")
    if not sep:
        name, value = "", text
    if value.lower() in ("osd", "osd-baseline"):
        return ModelSpec(name or "OSD-Baseline", "osd")
    if not value.endswith(".onnx"):
        raise ValueError(f"--models entry {text!r}: want osd, NAME=osd, NAME=PATH.onnx or PATH.onnx")
    return ModelSpec(name or Path(value).stem, "onnx", value)


def _summaries(results: dict[str, list[WindowResult]], tasks: Sequence[WindowTask]) -> dict[str, dict]:
    out = {}
    for name, res in results.items():
        z, n = z_rmse(res, tasks)
        out[name] = {"z_rmse": z, "z_samples": n, "dead_reckoning_60s": dr_summary(res)}
    return out


def evaluate(data: str | Path, specs: Sequence[ModelSpec], out_dir: str | Path, *, stride: int = 1, jobs: int = 1,
             ablation: str | None = None, max_windows: int | None = None, snow: bool = True, tum: bool = True,
             plots: bool = True, progress: bool | None = None, window_s: float = DR_WINDOW_S,
             calibration: str = "both", preroll_s: float = DEPLOYMENT_PREROLL_S) -> dict:
    """Run the protocol and write ``report.md``, ``metrics.json``, PNG figures and TUM files to ``out_dir``.

    Parameters
    ----------
    data:
        Dataset folder (``prml2 simulate`` output or ReV-StED-schema files with a manifest).
    specs:
        Methods to evaluate; OSD specs are tuned on val (variances, ``Q`` scale).
    ablation:
        Name of the ONNX model for Table 3 (default: one named ``PRML2`` if present, else none).
    window_s:
        Dead-reckoning window [s] (the paper: 60).
    calibration:
        ``off`` (the paper's filter), ``on`` (calibration states and raw cues) or ``both``: every model
        twice, the second named ``NAME +cal``, in the same run.
    preroll_s:
        Deployment protocol: each test window is also run after this much GNSS-aided driving
        (10 Hz fixes, 1.5 m); 0 skips it.
    max_windows:
        At most this many 60 s windows per drive segment (None: all), for quick runs.

    Returns
    -------
    The metrics dict written to ``metrics.json``.
    """
    from prml2_edge.data.datasets import load_dataset

    t0 = time.monotonic()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = [s.name for s in specs]
    if len(set(names)) != len(names):
        raise ValueError(f"model names must be unique, got {names}")
    if ablation is None and "PRML2" in names:
        ablation = "PRML2"
    target = next((s for s in specs if s.name == ablation), None) if ablation else None
    if ablation and (target is None or target.kind != "onnx"):
        raise ValueError(f"--ablation {ablation!r} must name one of the ONNX models {names}")

    dataset = load_dataset(data)
    val = split_tasks(dataset, "val", window_s, max_windows=max_windows)
    test = split_tasks(dataset, "test", window_s, max_windows=max_windows)
    snow_tasks = split_tasks(dataset, "snow", window_s, max_windows=max_windows) if snow else []
    if not val:
        raise ValueError(f"{data}: no {window_s:g} s validation windows to tune the noise on")
    if not test:
        raise ValueError(f"{data}: no {window_s:g} s test windows (need dry drives with ground truth)")
    deployment = split_tasks(dataset, "test", window_s, max_windows=max_windows, preroll_s=preroll_s) \
        if preroll_s > 0 else []
    n_osd = sum(s.kind == "osd" for s in specs)
    n_var = len(specs) * (2 if calibration == "both" else 1)
    total = (len(val) * (1 + len(OSD_Q_SCALES)) * n_osd + (len(val) if target else 0)
             + n_var * (len(test) + len(snow_tasks) + len(deployment)) + (2 * len(test) if target else 0))
    bar = Progress(total, desc="evaluate", unit="win", enabled=progress)

    def tick(res: WindowResult) -> None:
        bar.update(1)
        bar.set_postfix(f"{res.model} {res.task_key}")

    tuning = Tuning()
    tuned = [tune_osd(s, val, stride, jobs, tuning=tuning, on_done=tick) if s.kind == "osd" else s for s in specs]
    tuned = calibration_variants(tuned, calibration)
    const_var = tune_constant_variance(target, val, stride, jobs, tuning, on_done=tick) if target else None

    test_res = run_all(tuned, test, stride, jobs, tick)
    snow_res = run_all(tuned, snow_tasks, stride, jobs, tick) if snow_tasks else {s.name: [] for s in tuned}
    dep_res = run_all(tuned, deployment, stride, jobs, tick) if deployment else {}
    abl_rows = []
    if target is not None:
        variants = [replace(target, name=f"{target.name} (no guard, no uncertainty)", guard=False,
                            const_var=const_var),
                    replace(target, name=f"{target.name} (no guard)", guard=False)]
        abl_res = run_all(variants, test, stride, jobs, tick)
        for spec, (g, u) in zip(variants, ((False, False), (False, True)), strict=True):
            abl_rows.append({"guard": g, "uncertainty": u, "name": spec.name,
                             "dead_reckoning_60s": dr_summary(abl_res[spec.name])})
        abl_rows.append({"guard": True, "uncertainty": True, "name": target.name,
                         "dead_reckoning_60s": dr_summary(test_res[target.name])})
    bar.close()

    test_sum = _summaries(test_res, test)
    snow_sum = _summaries(snow_res, snow_tasks) if snow_tasks else {}
    metrics: dict = {
        "data": str(data), "dataset_fingerprint": dataset.fingerprint, "stride": stride,
        "window_s": window_s, "models": {}, "tuning": tuning.notes,
        "specs": {s.name: {"kind": s.kind, "path": s.path, "q_scale": s.q_scale, "calibration": s.calibration,
                           "const_var": list(s.const_var) if s.const_var else None} for s in tuned},
        "deployment_preroll_s": preroll_s if deployment else None,
    }
    for s in tuned:
        metrics["models"][s.name] = {"test": test_sum[s.name]}
        if snow_tasks:
            metrics["models"][s.name]["snow"] = snow_sum[s.name]
        if deployment:
            metrics["models"][s.name]["deployment"] = {"dead_reckoning_60s": dr_summary(dep_res[s.name]),
                                                       **calibration_summary(dep_res[s.name])}
    if abl_rows:
        metrics["ablation"] = {"model": target.name, "rows": abl_rows}
    if target is not None and len(tuned) > 1:  # is the reference better than each other model beyond the spread?
        paired: dict = {"reference": target.name}
        for split, res in (("test", test_res), ("snow", snow_res), ("deployment", dep_res)):
            if res.get(target.name):
                paired[split] = {s.name: paired_comparison(res[target.name], res[s.name])
                                 for s in tuned if s.name != target.name and res.get(s.name)}
        metrics["paired"] = paired

    figures = []
    if plots:
        from prml2_edge.evaluation.plots import plot_drift, plot_error_histograms, plot_trajectories

        examples = test[:: max(1, len(test) // 3)][:3] + snow_tasks[:1]
        figures.append(plot_trajectories(out / "trajectories.png", examples,
                                         {k: v + snow_res.get(k, []) for k, v in test_res.items()}).name)
        figures.append(plot_drift(out / "drift_dry.png", test_res, "dry test").name)
        if snow_tasks:
            figures.append(plot_drift(out / "drift_snow.png", snow_res, "snow").name)
        figures.append(plot_error_histograms(out / "z_error_histograms.png", test_res, test).name)
    metrics["figures"] = figures
    if tum:
        from prml2_edge.evaluation.tum import write_tum

        for tasks, results in ((test, test_res), (snow_tasks, snow_res)):
            by_key = {t.key: t for t in tasks}
            for t in tasks:
                write_tum(out / "tum" / "groundtruth" / _tum_name(t), t.t_s, t.pose_gt)
            for name, res in results.items():
                for r in res:
                    write_tum(out / "tum" / _safe(name) / _tum_name(by_key[r.task_key]), by_key[r.task_key].t_s,
                              r.pose)
        metrics["tum_dir"] = "tum/"
    metrics["wall_s"] = round(time.monotonic() - t0, 1)
    from prml2_edge.evaluation.report import write_report

    write_report(out, metrics)
    return metrics


CALIBRATION_CHOICES = ("off", "on", "both")


def calibration_variants(specs: Sequence[ModelSpec], calibration: str) -> list[ModelSpec]:
    """``off``: as given; ``on``: every spec with the calibration states; ``both``: each twice (``NAME +cal``)."""
    if calibration not in CALIBRATION_CHOICES:
        raise ValueError(f"calibration must be one of {', '.join(CALIBRATION_CHOICES)}, got {calibration!r}")
    if calibration == "off":
        return list(specs)
    if calibration == "on":
        return [replace(s, calibration=True) for s in specs]
    return [v for s in specs for v in (s, replace(s, name=f"{s.name} +cal", calibration=True))]


def calibration_summary(results: Sequence[WindowResult]) -> dict:
    """Mean calibration states at the outage start (after the GNSS pre-roll), in report units."""
    import math

    import numpy as np

    cal = np.array([r.cal for r in results if r.cal is not None and np.isfinite(r.cal).all()])
    if not cal.size:
        return {}
    return {"calibration_at_outage": {"yaw_rate_offset_dps_mean": math.degrees(float(cal[:, 0].mean())),
                                      "wheel_scale_pct_mean": 100.0 * float(cal[:, 1].mean())}}


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else ("star" if c == "*" else "_") for c in name)


def _tum_name(task: WindowTask) -> str:
    return f"{task.split}_{_safe(task.drive)}_{task.start:07d}.txt"
