"""``prml2 evaluate`` end to end: tune on val, run every model on test and snow, write the report."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import replace
from functools import partial
from pathlib import Path

from prml2_edge import schema
from prml2_edge.errors import DataError
from prml2_edge.evaluation.metrics import dr_summary, paired_comparison, z_rmse
from prml2_edge.evaluation.protocol import (
    DEPLOYMENT_PREROLL_S,
    DR_WINDOW_S,
    ModelSpec,
    WindowResult,
    WindowTask,
    run_all,
    split_tasks,
)
from prml2_edge.evaluation.tuning import OSD_Q_SCALES, Tuning, tune_constant_variance, tune_osd
from prml2_edge.evaluation.unit_history import HISTORY_MINUTES
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
             calibration: str = "both", preroll_s: float = DEPLOYMENT_PREROLL_S,
             history_min: float = HISTORY_MINUTES) -> dict:
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
    history_min:
        Minutes of each simulated car's earlier drives whose GNSS heading taught its calibration file the gyro's
        gain (:mod:`~prml2_edge.evaluation.unit_history`; used by ``+cal`` models); 0: a first drive.

    Returns
    -------
    The metrics dict written to ``metrics.json``.
    """
    from prml2_edge.data.datasets import load_dataset

    t0 = time.monotonic()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    target = _ablation_target(specs, ablation)
    dataset = load_dataset(data)
    # validation windows tune the OSD baseline's noise and the ablation's constant variance; ONNX models need none
    need_val = target is not None or any(s.kind == "osd" for s in specs)
    sets = _task_sets(dataset, data, window_s, max_windows, snow, preroll_s, need_val, history_min)
    bar = Progress(_n_runs(specs, target, sets, calibration), desc="evaluate", unit="win", enabled=progress)

    def tick(res: WindowResult) -> None:
        bar.update(1)
        bar.set_postfix(f"{res.model} {res.task_key}")

    tuning = Tuning()
    tuned = [tune_osd(s, sets["val"], stride, jobs, tuning=tuning, on_done=tick) if s.kind == "osd" else s
             for s in specs]
    tuned = calibration_variants(tuned, calibration)
    if target is not None:  # Table 3 runs its variants through the same filter as the row they are compared with
        target = next(s for s in tuned if s.name == target.name)
    results = {split: run_all(tuned, tasks, stride, jobs, tick) if tasks else {s.name: [] for s in tuned}
               for split, tasks in sets.items() if split != "val"}
    abl_rows = _ablation(target, sets, results["test"], stride, jobs, tuning, tick) if target else []
    bar.close()

    metrics = _metrics(data, dataset, stride, window_s, tuning, tuned, sets, results, preroll_s)
    metrics["unit_history_min"] = history_min
    metrics["per_vehicle"] = _per_vehicle(dataset, tuned, sets, results)
    if abl_rows:
        metrics["ablation"] = {"model": target.name, "rows": abl_rows}
    if target is not None and len(tuned) > 1:  # is the reference better than each other model beyond the spread?
        metrics["paired"] = _paired(target, tuned, results)
    metrics["figures"] = _figures(out, sets, results) if plots else []
    if tum:
        metrics["tum_windows"] = _write_tum(out, sets, results)
        metrics["tum_dir"] = "tum/"
    metrics["wall_s"] = round(time.monotonic() - t0, 1)
    from prml2_edge.evaluation.report import write_report

    write_report(out, metrics)
    return metrics


def _ablation_target(specs: Sequence[ModelSpec], ablation: str | None) -> ModelSpec | None:
    """The model of Table 3 (default: the one named PRML2); unique names checked."""
    names = [s.name for s in specs]
    if len(set(names)) != len(names):
        raise ValueError(f"model names must be unique, got {names}")
    if ablation is None and "PRML2" in names:
        ablation = "PRML2"
    target = next((s for s in specs if s.name == ablation), None) if ablation else None
    if ablation and (target is None or target.kind != "onnx"):
        raise ValueError(f"--ablation {ablation!r} must name one of the ONNX models {names}")
    return target


def _task_sets(dataset, data, window_s: float, max_windows: int | None, snow: bool,
               preroll_s: float, need_val: bool = True, history_min: float = 0.0) -> dict[str, list[WindowTask]]:
    """``val``, ``test``, ``snow`` and ``deployment`` (test windows after a GNSS pre-roll) windows."""
    tasks = partial(split_tasks, dataset, window_s=window_s, max_windows=max_windows, history_min=history_min)
    sets = {"val": tasks("val") if need_val else [], "test": tasks("test")}
    if need_val and not sets["val"]:
        raise _no_windows(dataset, data, "val", window_s, "to tune the OSD baseline's noise (and the ablation) on")
    if not sets["test"]:
        raise _no_windows(dataset, data, "test", window_s, "to score the models on")
    sets["snow"] = tasks("snow") if snow else []
    sets["deployment"] = tasks("test", preroll_s=preroll_s) if preroll_s > 0 else []
    # a car no model was trained on (the benchmark's held-out vehicle): zero-shot, or after fine-tuning on its own
    sets["heldout"] = tasks("heldout") if dataset.heldout else []
    return sets


def _no_windows(dataset, data, split: str, window_s: float, purpose: str) -> DataError:
    """One line: no ``window_s`` window fits in ``split``, how long its segments are, and how to get windows."""
    seconds = [(b - a) * schema.DT_S for drive, a, b in dataset.segments(split) if drive.has_ground_truth]
    found = (f"its longest segment with ground truth is {max(seconds):.1f} s" if seconds
             else "it has no dry drive with ground truth")
    share = {"val": "10", "test": "20"}[split]
    return DataError(f"{data}: no {window_s:g} s {split} windows {purpose}: {found}, and a window needs {window_s:g} "
                     f"s after the model's {schema.WINDOW_LEN * schema.DT_S:g} s of history; give drives a split of "
                     f"their own (\"split\": \"{split}\" in the recipe, as --recipe small and benchmark do) or "
                     f"record longer ones (a drive without a split gives {share} % to {split}), or score shorter "
                     "windows with --window-s")


def _n_runs(specs: Sequence[ModelSpec], target: ModelSpec | None, sets: dict, calibration: str) -> int:
    """Window runs of the whole evaluation (the progress bar's total)."""
    n_val = len(sets["val"])
    n_osd = sum(s.kind == "osd" for s in specs)
    n_var = len(specs) * (2 if calibration == "both" else 1)
    return (n_val * (1 + len(OSD_Q_SCALES)) * n_osd + (n_val if target else 0)
            + n_var * (len(sets["test"]) + len(sets["snow"]) + len(sets["deployment"]) + len(sets["heldout"]))
            + (2 * len(sets["test"]) if target else 0))


def _ablation(target: ModelSpec, sets: dict, test_res: dict, stride: int, jobs: int, tuning: Tuning,
              tick) -> list[dict]:
    """Table 3: the target without the guard, and without guard and learned uncertainty, on test."""
    const_var = tune_constant_variance(target, sets["val"], stride, jobs, tuning, on_done=tick)
    variants = [replace(target, name=f"{target.name} (no guard, no uncertainty)", guard=False, const_var=const_var),
                replace(target, name=f"{target.name} (no guard)", guard=False)]
    abl_res = run_all(variants, sets["test"], stride, jobs, tick)
    rows = [{"guard": g, "uncertainty": u, "name": spec.name, "dead_reckoning_60s": dr_summary(abl_res[spec.name])}
            for spec, (g, u) in zip(variants, ((False, False), (False, True)), strict=True)]
    rows.append({"guard": True, "uncertainty": True, "name": target.name,
                 "dead_reckoning_60s": dr_summary(test_res[target.name])})
    return rows


def _metrics(data, dataset, stride: int, window_s: float, tuning: Tuning, tuned: Sequence[ModelSpec], sets: dict,
             results: dict, preroll_s: float) -> dict:
    """The per-model tables of ``metrics.json`` (test, snow, deployment, heldout)."""
    test_sum = _summaries(results["test"], sets["test"])
    snow_sum = _summaries(results["snow"], sets["snow"]) if sets["snow"] else {}
    held_sum = _summaries(results["heldout"], sets["heldout"]) if sets["heldout"] else {}
    metrics: dict = {
        "data": str(data), "dataset_fingerprint": dataset.fingerprint, "stride": stride,
        "window_s": window_s, "models": {}, "tuning": tuning.notes,
        "specs": {s.name: {"kind": s.kind, "path": s.path, "q_scale": s.q_scale, "calibration": s.calibration,
                           "const_var": list(s.const_var) if s.const_var else None} for s in tuned},
        "deployment_preroll_s": preroll_s if sets["deployment"] else None,
        "heldout_vehicles": dataset.heldout,
        "split_by_drive": all("split" in d for d in dataset.manifest["drives"]),
    }
    for s in tuned:
        metrics["models"][s.name] = {"test": test_sum[s.name]}
        if sets["snow"]:
            metrics["models"][s.name]["snow"] = snow_sum[s.name]
        if sets["heldout"]:
            metrics["models"][s.name]["heldout"] = held_sum[s.name]
        if sets["deployment"]:
            dep = results["deployment"][s.name]
            metrics["models"][s.name]["deployment"] = {"dead_reckoning_60s": dr_summary(dep),
                                                       **calibration_summary(dep)}
    return metrics


def _per_vehicle(dataset, tuned: Sequence[ModelSpec], sets: dict, results: dict) -> dict:
    """``{split: {car: {model: dr_summary}}}`` for test, snow, deployment and heldout: on which car each model
    helps."""
    vehicle_of = dict(zip((d["name"] for d in dataset.manifest["drives"]), dataset.vehicles(), strict=True))
    out: dict = {}
    for split in ("test", "snow", "deployment", "heldout"):
        car_of = {t.key: vehicle_of.get(t.drive, "reference") for t in sets.get(split) or []}
        by_car: dict = {}
        for car in sorted(set(car_of.values())):
            by_car[car] = {s.name: dr_summary([r for r in results[split].get(s.name, [])
                                               if car_of.get(r.task_key) == car]) for s in tuned}
        if by_car:
            out[split] = by_car
    return out


def _paired(target: ModelSpec, tuned: Sequence[ModelSpec], results: dict) -> dict:
    """Table 2b: the reference against every other model, window by window, per split."""
    paired: dict = {"reference": target.name}
    for split in ("test", "snow", "deployment", "heldout"):
        res = results[split]
        if res.get(target.name):
            paired[split] = {s.name: paired_comparison(res[target.name], res[s.name])
                             for s in tuned if s.name != target.name and res.get(s.name)}
    return paired


def _figures(out: Path, sets: dict, results: dict) -> list[str]:
    """The evaluation's PNG figures (:mod:`prml2_edge.viz.plots`); none, with one line, without matplotlib."""
    from prml2_edge import schema
    from prml2_edge.evaluation.metrics import drift_curves, z_errors
    from prml2_edge.viz import plots

    if not plots.available():
        log.warning(plots.missing_message("figures"))
        return []
    test, snow_tasks = sets["test"], sets["snow"]
    test_res, snow_res = results["test"], results["snow"]
    examples = test[:: max(1, len(test) // 3)][:3] + snow_tasks[:1]
    by_model = {k: v + snow_res.get(k, []) for k, v in test_res.items()}
    panels = []
    for task in examples:
        origin = task.pose_gt[0, :2]
        estimates = {}
        for name, res in by_model.items():
            match = [r for r in res if r.task_key == task.key]
            if match:
                estimates[name] = match[0].pose[:, :2] - origin
        panels.append({"title": f"{task.drive} ({task.split}) t0={task.t_s[0]:.0f} s",
                       "truth": task.pose_gt[:, :2] - origin, "estimates": estimates})
    figures = [plots.plot_trajectories(out / "trajectories.png", panels).name,
               plots.plot_drift(out / "drift_dry.png", {k: drift_curves(v) for k, v in test_res.items() if v},
                                "dry test").name]
    if snow_tasks:
        figures.append(plots.plot_drift(out / "drift_snow.png", {k: drift_curves(v) for k, v in snow_res.items() if v},
                                        "snow").name)
    errors = {name: z_errors(res, test) for name, res in test_res.items() if res}
    figures.append(plots.plot_error_histograms(out / "z_error_histograms.png", errors, schema.STATE_NAMES).name)
    return figures


def _write_tum(out: Path, sets: dict, results: dict) -> dict[str, list[dict]]:
    """TUM files of every window (estimate per model, ground truth) under ``out/tum``; returns their index
    per model: the files and each window's position RMSE as the report computes it (what evo_ape should give)."""
    from prml2_edge.evaluation.tum import write_tum

    index: dict[str, list[dict]] = {}
    for split in ("test", "snow", "heldout"):
        tasks = sets[split]
        by_key = {t.key: t for t in tasks}
        for t in tasks:
            write_tum(out / "tum" / "groundtruth" / _tum_name(t), t.t_s, t.pose_gt)
        for name, res in results[split].items():
            for r in res:
                task = by_key[r.task_key]
                path = write_tum(out / "tum" / _safe(name) / _tum_name(task), task.t_s, r.pose)
                index.setdefault(name, []).append({
                    "window": r.task_key, "estimate": path.relative_to(out).as_posix(),
                    "groundtruth": f"tum/groundtruth/{_tum_name(task)}", "rmse_m": r.rmse_m})
    return index


CALIBRATION_CHOICES = ("off", "on", "both")


def calibration_variants(specs: Sequence[ModelSpec], calibration: str) -> list[ModelSpec]:
    """``off``: as given; ``on``: every model spec with the calibration states, the OSD baseline as given (it is
    the paper's model-free reference of every ratio; through the calibrating filter its raw cues would be fused
    twice); ``both``: each twice (``NAME +cal``)."""
    if calibration not in CALIBRATION_CHOICES:
        raise ValueError(f"calibration must be one of {', '.join(CALIBRATION_CHOICES)}, got {calibration!r}")
    if calibration == "off":
        return list(specs)
    if calibration == "on":
        return [s if s.kind == "osd" else replace(s, calibration=True) for s in specs]
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
