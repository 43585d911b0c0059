"""``report.md`` (Tables 1-3 in the paper's layout, ours beside the paper's) and ``metrics.json``."""

from __future__ import annotations

import json
import math
from pathlib import Path

from prml2_edge import schema

# Paper values (ReV-StED, Sec. V). Table 1: z RMSE [v_x m/s, v_y m/s, a_x m/s^2, a_y m/s^2, omega_z as printed].
PAPER_TABLE1: dict[str, tuple[float | None, ...]] = {
    "OSD-Baseline": (0.22, None, None, 0.20, 0.43),
    "NN-VDM": (0.06, 0.03, 0.13, 0.13, 0.41),
    "DL-AVL": (0.07, 0.03, 0.16, 0.13, 0.46),
    "RNN-EKF": (0.07, 0.02, 0.13, 0.13, 0.44),
    "Backprop-KF": (0.12, 0.02, 0.31, 0.15, 0.38),
    "PRML2*": (0.03, 0.01, 0.18, 0.13, 0.24),
    "PRML2": (0.02, 0.01, 0.15, 0.12, 0.18),
}
# Table 2: 60 s dead reckoning, (RMSE mean, std, ME mean, std) [m], dry (ReV-StED) and snow.
PAPER_TABLE2: dict[str, tuple[tuple[float, ...], tuple[float, ...]]] = {
    "OSD-Baseline": ((5.3, 2.1, 9.2, 4.0), (5.7, 3.1, 9.7, 4.8)),
    "NN-VDM": ((2.9, 2.4, 5.6, 4.7), (3.7, 2.7, 7.2, 5.0)),
    "DL-AVL": ((2.5, 2.2, 5.0, 4.1), (3.8, 2.7, 7.5, 5.0)),
    "RNN-EKF": ((2.1, 1.5, 4.1, 3.1), (3.8, 2.6, 7.3, 4.9)),
    "Backprop-KF": ((2.6, 1.5, 5.2, 3.4), (3.4, 2.3, 6.0, 4.1)),
    "PRML2*": ((2.2, 1.9, 4.2, 3.6), (3.6, 2.7, 7.1, 4.9)),
    "PRML2": ((1.5, 1.2, 2.8, 2.2), (2.5, 1.8, 4.3, 3.1)),
}
# Table 3: (guard, uncertainty) -> (RMSE, ME) [m], ReV-StED, EKF always on.
PAPER_TABLE3: dict[tuple[bool, bool], tuple[float, float]] = {
    (False, False): (1.7, 2.9), (False, True): (1.5, 2.9), (True, True): (1.5, 2.8)}
PAPER_DRIFT_PCT = 1.07


def _f(v: float | None, nd: int = 2) -> str:
    return "–" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.{nd}f}"


def _pm(mean: float | None, std: float | None, nd: int = 1) -> str:
    return "–" if mean is None else f"{mean:.{nd}f} ± {_f(std, nd)}"


def _rm(d: dict, nd: int = 1) -> str:
    """``RMSE | ME`` cells of a dead-reckoning summary."""
    return (f"{_pm(d.get('rmse_mean_m'), d.get('rmse_std_m'), nd)} | "
            f"{_pm(d.get('me_mean_m'), d.get('me_std_m'), nd)}")


def _z_row(z: dict) -> list[float | None]:
    vals = [z.get(n) for n in schema.STATE_NAMES]
    if vals[4] is not None:
        vals[4] = math.degrees(vals[4])  # omega_z in deg/s
    return vals


def _paper_key(name: str) -> str | None:
    for key in PAPER_TABLE2:
        if name == key or name.lower() == key.lower() or (key == "OSD-Baseline" and name.lower().startswith("osd")):
            return key
    return None


def _ratio(d: dict) -> str:
    lo, hi = d["rmse_ratio_ci95"]
    return f"{100 * d['rmse_ratio']:.0f} % [{100 * lo:.0f}, {100 * hi:.0f}]"


def _paired_lines(metrics: dict) -> list[str]:
    """Table 2b: the reference model against each other one, paired by window, with bootstrap intervals."""
    paired = metrics.get("paired")
    if not paired or not paired.get("test"):
        return []
    ref = paired["reference"]
    snow = paired.get("snow", {})
    lines = [f"## Table 2b: {ref} against each model, paired by window (95 % bootstrap intervals)", "",
             f"| Model | dry: RMSE − {ref}'s [m] | dry: {ref} / model | dry: {ref} lower | "
             f"snow: RMSE − {ref}'s [m] | snow: {ref} / model | snow: {ref} lower |",
             "|---|---|---|---|---|---|---|"]
    for name, d in paired["test"].items():
        s = snow.get(name)
        snow_cells = " |  | "
        if s and s.get("n_windows"):
            snow_cells = (f"{_diff(s)} | {_ratio(s)} | "
                          f"{100 * s['reference_wins']:.0f} % of {s['n_windows']}")
        lines.append(f"| {name} | {_diff(d)} | {_ratio(d)} | "
                     f"{100 * d['reference_wins']:.0f} % of {d['n_windows']} | {snow_cells} |")
    lines += ["", f"A positive difference whose interval excludes 0: {ref} is better than that model beyond the "
              "window-to-window spread; an interval containing 0: the windows cannot tell them apart.", ""]
    return lines


def _diff(d: dict) -> str:
    lo, hi = d["rmse_diff_ci95_m"]
    return f"{d['rmse_diff_mean_m']:+.1f} [{lo:+.1f}, {hi:+.1f}]"


def _cov(d: dict) -> str:
    """One cell: ``1σ / 2σ / 3σ`` coverage [%]."""
    if "coverage_1sigma_pct" not in d:
        return "–"
    return " / ".join(f"{d[f'coverage_{k}sigma_pct']:.0f}" for k in (1, 2, 3))


def _heldout_lines(metrics: dict) -> list[str]:
    """Table 2d: the held-out car (in no training, validation or tuning data), each model against OSD."""
    held = metrics.get("heldout_vehicles")
    models = {n: m["heldout"] for n, m in metrics["models"].items() if m.get("heldout")}
    if not held or not models:
        return []
    osd = next((m for n, m in models.items() if _paper_key(n) == "OSD-Baseline" and "+cal" not in n), None)
    osd_rmse = osd["dead_reckoning_60s"].get("rmse_mean_m") if osd else None
    paired = metrics.get("paired", {}).get("heldout", {})
    ref = metrics.get("paired", {}).get("reference")
    lines = [f"## Table 2d: held-out car ({', '.join(held)}), never seen in training, validation or tuning", "",
             f"| Model | RMSE [m] | ME [m] | drift [%] | / OSD RMSE | windows | RMSE − {ref or 'reference'}'s [m] |",
             "|---|---|---|---|---|---|---|"]
    for name, m in models.items():
        d = m["dead_reckoning_60s"]
        ratio = f"{d['rmse_mean_m'] / osd_rmse:.2f}" if osd_rmse and d.get("rmse_mean_m") is not None else ""
        diff = _diff(paired[name]) if name in paired and paired[name].get("n_windows") else ""
        lines.append(f"| {name} | {_pm(d.get('rmse_mean_m'), d.get('rmse_std_m'))} | "
                     f"{_pm(d.get('me_mean_m'), d.get('me_std_m'))} | "
                     f"{_pm(d.get('drift_mean_pct'), d.get('drift_std_pct'), 2)} | {ratio} | {d['n_windows']} | "
                     f"{diff} |")
    return lines + ["", "OSD's noise is tuned on the fleet's validation drives, like every other choice; "
                    "a model fine-tuned on the held-out car (`prml2 train --init`) saw only its train drives.", ""]


def _vehicle_lines(metrics: dict) -> list[str]:
    """Per car and split: each model's 60 s RMSE, drift and coverage, and its RMSE over OSD's on the same windows."""
    per = metrics.get("per_vehicle") or {}
    if not per:
        return []
    lines = ["## Per vehicle: on which car each model helps", "",
             "Ratio: the model's mean 60 s RMSE over OSD-Baseline's on the same car's windows (below 1: better "
             "than integrating the raw cues).", "",
             "| split | car | model | windows | RMSE [m] | drift [%] | / OSD RMSE | 1σ / 2σ / 3σ [%] |",
             "|---|---|---|---|---|---|---|---|"]
    for split, cars in per.items():
        for car, models in cars.items():
            osd = next((d for n, d in models.items() if _paper_key(n) == "OSD-Baseline" and "+cal" not in n), {})
            for name, d in models.items():
                if not d.get("n_windows"):
                    continue
                ratio = f"{d['rmse_mean_m'] / osd['rmse_mean_m']:.2f}" if osd.get("rmse_mean_m") else ""
                lines.append(f"| {split} | {car} | {name} | {d['n_windows']} | "
                             f"{_pm(d.get('rmse_mean_m'), d.get('rmse_std_m'))} | "
                             f"{_pm(d.get('drift_mean_pct'), d.get('drift_std_pct'), 2)} | {ratio} | {_cov(d)} |")
    return lines + [""]


def _deployment_lines(metrics: dict) -> list[str]:
    """Table 2c: the deployment protocol (GNSS pre-roll, then the outage) and the uncertainty's coverage."""
    pre = metrics.get("deployment_preroll_s")
    lines = ["## Table 2c: uncertainty coverage and the deployment protocol", "",
             "Coverage: share of steps [%] whose 2D position error lies inside the reported 1σ / 2σ / 3σ "
             "ellipse (a consistent filter: 39 / 86 / 99 %).", ""]
    if pre:
        lines += [f"Deployment: each test window preceded by {pre:g} s of GNSS-aided driving (10 Hz fixes, σ 1.5 m, "
                  "heading σ 2° while moving), then the 60 s outage; errors over the outage only. "
                  "`+cal`: the filter's calibration states and raw cues on.", ""]
    lines += ["| Model | paper-protocol coverage 1σ / 2σ / 3σ | deployment RMSE | deployment drift [%] "
              "| deployment coverage 1σ / 2σ / 3σ | yaw offset at outage [°/s] | wheel scale at outage [%] |",
              "|---|---|---|---|---|---|---|"]
    for name, m in metrics["models"].items():
        d = m["test"]["dead_reckoning_60s"]
        dep = m.get("deployment", {})
        dd = dep.get("dead_reckoning_60s", {"n_windows": 0})
        cal = dep.get("calibration_at_outage", {})
        off = _f(cal.get("yaw_rate_offset_dps_mean"), 3) if cal else ""
        scale = _f(cal.get("wheel_scale_pct_mean"), 2) if cal else ""
        dep_s = (f"{_pm(dd.get('rmse_mean_m'), dd.get('rmse_std_m'))} | "
                 f"{_pm(dd.get('drift_mean_pct'), dd.get('drift_std_pct'), 2)} | {_cov(dd)}"
                 if dd.get("n_windows") else "– | – | –")
        lines.append(f"| {name} | {_cov(d)} | {dep_s} | {off} | {scale} |")
    return lines + [""]


def _split_note(metrics: dict) -> str:
    if metrics.get("split_by_drive"):
        return "whole test drives of the fleet's cars, none of them in training or validation"
    return "last 20 % of every dry drive"


def render_report(metrics: dict) -> str:
    """Markdown of Tables 1-3 with the paper's values beside ours."""
    models = metrics["models"]
    lines = [f"# PRML2 evaluation on `{metrics['data']}`", "",
             f"Streaming inference through `StreamingLocalizer.run_arrays` (stride {metrics['stride']}), "
             f"NumPy EKF, GNSS off; {metrics['window_s']:g} s non-overlapping dead-reckoning windows from the true "
             f"pose. "
             f"Dry = test split ({_split_note(metrics)}); snow = whole low-μ drives, models trained on dry "
             f"data only. Noise tuned on the validation split only (see *Tuning*).", ""]
    # Table 1
    lines += ["## Table 1: z RMSE on the test split (ω_z in deg/s)", "",
              "| Model | v_x [m/s] | v_y [m/s] | a_x [m/s²] | a_y [m/s²] | ω_z [°/s] | samples "
              "| paper v_x / v_y / a_x / a_y / ω_z |",
              "|---|---|---|---|---|---|---|---|"]
    for name, m in models.items():
        z = m["test"]["z_rmse"]
        paper = PAPER_TABLE1.get(_paper_key(name) or "", None)
        paper_s = " / ".join(_f(v) for v in paper) if paper else ""
        lines.append(f"| {name} | " + " | ".join(_f(v, 3) for v in _z_row(z)) + f" | {m['test']['z_samples']} | "
                     f"{paper_s} |")
    lines += ["", "A dash: the model does not estimate the quantity (OSD-Baseline: v_y, a_x).", ""]
    # Table 2
    lines += [f"## Table 2: horizontal position error [m] over {metrics['window_s']:g} s dead reckoning "
              "(mean ± std over windows)", "",
              "| Model | dry RMSE | dry ME | dry drift [%] | dry windows | snow RMSE | snow ME | snow windows "
              "| paper dry RMSE / ME | paper snow RMSE / ME |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for name, m in models.items():
        d, s = m["test"]["dead_reckoning_60s"], m.get("snow", {}).get("dead_reckoning_60s", {"n_windows": 0})
        pk = _paper_key(name)
        pd_, ps = PAPER_TABLE2[pk] if pk else (None, None)
        paper_d = f"{pd_[0]} ± {pd_[1]} / {pd_[2]} ± {pd_[3]}" if pd_ else ""
        paper_s = f"{ps[0]} ± {ps[1]} / {ps[2]} ± {ps[3]}" if ps else ""
        lines.append(
            f"| {name} | {_rm(d)}"
            f" | {_pm(d.get('drift_mean_pct'), d.get('drift_std_pct'), 2)} | {d['n_windows']}"
            f" | {_rm(s)}"
            f" | {s['n_windows']} | {paper_d} | {paper_s} |")
    lines += ["", f"Translational drift: final position error / distance travelled over 60 s (paper, PRML2: "
              f"{PAPER_DRIFT_PCT} %).", ""]
    lines += _paired_lines(metrics)
    lines += _deployment_lines(metrics)
    lines += _heldout_lines(metrics)
    lines += _vehicle_lines(metrics)
    # Table 3
    abl = metrics.get("ablation")
    if abl:
        lines += [f"## Table 3: ablation of {abl['model']} on the test split (dry)", "",
                  "| Physics guard | Uncertainty | EKF (Reg) | RMSE [m] | ME [m] | windows | paper RMSE / ME |",
                  "|---|---|---|---|---|---|---|"]
        for row in abl["rows"]:
            d = row["dead_reckoning_60s"]
            paper = PAPER_TABLE3.get((row["guard"], row["uncertainty"]))
            lines.append(f"| {'✓' if row['guard'] else ''} | {'✓' if row['uncertainty'] else ''} | ✓ | "
                         f"{_rm(d, 2)}"
                         f" | {d['n_windows']} | {f'{paper[0]} / {paper[1]}' if paper else ''} |")
        fire = metrics["models"].get(abl["model"], {}).get("test", {}).get("dead_reckoning_60s", {})
        lines += ["", f"Guard fire rate of {abl['model']} on these windows: "
                  f"{100 * (fire.get('guard_fire_rate') or 0.0):.3f} % of used predictions."]
        lines += ["", "Guard off: no friction-circle bound on (a_x, a_y) (speed and yaw-rate bounds stay); "
                  "uncertainty off: constant variances = the model's z residual MSE on the validation split.", ""]
    # Tuning and figures
    lines += ["## Tuning (validation split only)", "", "```json", json.dumps(metrics.get("tuning", {}), indent=1),
              "```", "", "## Figures", ""]
    for fig in metrics.get("figures", []):
        lines.append(f"![{fig}]({fig})")
    lines += ["", f"TUM trajectories (estimate and ground truth per window): `{metrics.get('tum_dir', 'tum/')}`", ""]
    return "\n".join(lines)


def _clean(obj: object) -> object:
    """Non-finite floats become None (strict JSON)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_clean(v) for v in obj]
    return obj


def write_report(out_dir: Path, metrics: dict) -> tuple[Path, Path]:
    """Write ``report.md`` and ``metrics.json`` into ``out_dir``; returns both paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    mpath = out_dir / "metrics.json"
    mpath.write_text(json.dumps(_clean(metrics), indent=1, allow_nan=False, default=str))
    rpath = out_dir / "report.md"
    rpath.write_text(render_report(metrics))
    return rpath, mpath
