"""How much a model's own variance understates its slow error, measured on the validation split.

A model predicts one variance per step, and the EKF takes each step's error as independent of the
next. The model's errors are not: they are smooth over seconds (a window's worth of the same input
moves by one sample per step). For the ``N`` steps of a ``T``-second stretch, independent errors
would give ``E[mean(e)^2] = mean(sigma^2) / N``; the measured ratio of the two,

    inflation = sum over stretches of mean(e)^2  /  sum over stretches of mean(sigma^2) / N,

is the factor by which the variance must grow for the EKF to weigh a ``T``-second mean of the model
as much as it is worth. At ``T`` = 5 s (the model's window) the shipped model's omega_z needs about
100x: next to a 50 Hz yaw-rate sensor whose errors average out, the filter trusted the model's slow
yaw-rate error and integrated it into heading (issue 26). The inflation is stored in the exported
model's metadata (``error_model``) and the runtime's calibrated filter applies it to omega_z, the
state a raw cue measures beside the model (:attr:`LocalizerConfig.model_omega_var_inflation`).

:func:`consistency` gives the same ratio for several stretch lengths and for the raw yaw-rate cue
(its stated noise against its error), the whiteness check ``benchmarks/cue_consistency.py`` prints.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from prml2_edge import schema

WINDOW_S = 5.0  # the stretch whose mean error the inflation makes consistent: the model's 5 s window
MIN_STRETCHES = 4  # fewer give no usable ratio


def mean_error_ratio(errors: Sequence[np.ndarray], variances: Sequence[np.ndarray], window_s: float = WINDOW_S,
                     dt_s: float = schema.DT_S) -> tuple[np.ndarray, int]:
    """``(ratio (k,), stretches)``: measured over stated variance of ``window_s`` means of the errors.

    ``errors`` and ``variances``: per drive window, (n, k) arrays of one step each (NaN rows skipped;
    consecutive steps of one window are cut into non-overlapping stretches of ``window_s``).
    """
    n = max(1, int(round(window_s / dt_s)))
    num = den = None
    count = 0
    for e, v in zip(errors, variances, strict=True):
        e, v = np.asarray(e, dtype=np.float64), np.asarray(v, dtype=np.float64)
        ok = np.all(np.isfinite(e), axis=1) & np.all(np.isfinite(v), axis=1)
        e, v = e[ok], v[ok]
        k = len(e) // n
        if k == 0:
            continue
        em = e[: k * n].reshape(k, n, -1).mean(axis=1)
        vm = v[: k * n].reshape(k, n, -1).mean(axis=1) / n
        num = (em**2).sum(axis=0) if num is None else num + (em**2).sum(axis=0)
        den = vm.sum(axis=0) if den is None else den + vm.sum(axis=0)
        count += k
    if num is None:
        return np.full(np.asarray(errors[0]).shape[-1] if len(errors) else schema.NUM_STATES, np.nan), 0
    return num / np.maximum(den, 1e-30), count


def fit_inflation(errors: Sequence[np.ndarray], variances: Sequence[np.ndarray], window_s: float = WINDOW_S,
                  source: str = "") -> dict:
    """The ``error_model`` metadata entry: ``var_inflation`` (5,) (floored at 1), and what it was measured on."""
    ratio, count = mean_error_ratio(errors, variances, window_s)
    if count < MIN_STRETCHES or not np.all(np.isfinite(ratio)):
        raise ValueError(f"{count} stretches of {window_s:g} s with model output and ground truth; "
                         f"need at least {MIN_STRETCHES}")
    return {"var_inflation": [round(float(max(r, 1.0)), 3) for r in ratio], "window_s": float(window_s),
            "stretches": int(count), "source": source}


def consistency(errors: Sequence[np.ndarray], variances: Sequence[np.ndarray],
                windows_s: Sequence[float] = (0.02, 1.0, 5.0, 20.0)) -> dict[float, list[float]]:
    """``{T: ratio per column}``: 1 at every ``T`` for errors as white as their stated variance says."""
    return {float(t): [float(r) for r in mean_error_ratio(errors, variances, t)[0]] for t in windows_s}


def model_errors(results, tasks) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per window: the consumed model z minus the truth (n, 5) and the model's variance (n, 5), from
    :class:`~prml2_edge.evaluation.protocol.WindowResult` objects and their tasks (same order)."""
    gt = {t.key: t.z_gt for t in tasks}
    errs, vars_ = [], []
    for r in results:
        if r.z_var is None:
            raise ValueError(f"{r.task_key}: no model variances recorded")
        errs.append(r.z - gt[r.task_key])
        vars_.append(r.z_var)
    return errs, vars_


def measure(model_path: str, dataset, split: str = "val", max_windows: int | None = None, jobs: int = 1) -> dict:
    """Run the exported model at ``model_path`` over ``split``'s 60 s windows (streaming, no calibration) and
    fit its ``error_model`` entry. A model that reads a_y and steering less the car's offsets reads them so here too,
    less the simulated offsets with the residual the runtime's estimator leaves (``data.cue_debias``)."""
    from prml2_edge.evaluation.protocol import ModelSpec, build_model, run_all, split_tasks

    spec = ModelSpec("model", "onnx", str(model_path))
    if build_model(spec).metadata.reads_debiased_cues:
        from prml2_edge.data.cue_debias import debiased_dataset

        dataset = debiased_dataset(dataset)
    tasks = split_tasks(dataset, split, max_windows=max_windows)
    if not tasks:
        raise ValueError(f"the {split} split has no 60 s window with ground truth")
    results = run_all([spec], tasks, jobs=jobs)["model"]
    errs, vars_ = model_errors(results, tasks)
    fp = getattr(dataset, "fingerprint", "") or ""
    return fit_inflation(errs, vars_, source=f"{split} split of dataset {fp[:12]}, {len(tasks)} windows of 60 s")
