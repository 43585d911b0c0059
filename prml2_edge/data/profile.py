"""Onboard sensor profile: the statistics that tell a real CAN recording from a naive simulation.

Per signal, measured in its ReV-StED unit (km/h, deg, deg/s, m/s^2, bar) so that the
numbers read like the CSV: quantisation step, sample-and-hold (run) lengths of equal
consecutive values, the share of samples that change, and the value range. Used by
``benchmarks/sensor_profile.py`` and by the real-versus-simulated test.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from prml2_edge import schema


@dataclass(frozen=True)
class SignalProfile:
    """Statistics of one signal (ReV-StED unit)."""

    name: str
    column: str
    unit: str
    step: float  # smallest difference between distinct values
    hold_median: float  # samples a value is held (runs of equal consecutive values)
    hold_p90: float
    hold_mean: float
    change_fraction: float  # share of samples that differ from the previous one
    p5: float
    p95: float
    minimum: float
    maximum: float

    def as_dict(self) -> dict:
        return asdict(self)


def quantisation_step(x: np.ndarray, decimals: int = 4) -> float:
    """Smallest positive difference between distinct values, after rounding to ``decimals``.

    Values in the ReV-StED sample are rounded to 3 decimals, so a step of 0.0625 km/h
    shows as 0.062 or 0.063; rounding the result to 3 significant digits absorbs that.
    """
    u = np.unique(np.round(x[np.isfinite(x)], decimals))
    if len(u) < 2:
        return float("nan")
    d = np.diff(u)
    d = d[d > 10.0 ** (-decimals) * 0.5]
    return float(np.min(d)) if len(d) else float("nan")


def hold_lengths(x: np.ndarray) -> np.ndarray:
    """Lengths of the inner runs of equal consecutive values (first and last run excluded)."""
    change = np.flatnonzero(np.diff(x) != 0)
    return np.diff(change)


def signal_profile(onboard_si: np.ndarray, moving_only: bool = True) -> list[SignalProfile]:
    """Profile each of the 9 signals of ``onboard_si`` ((N, 9), canonical order, SI).

    With ``moving_only`` the rows where the mean wheel speed is below 1 m/s are left out
    (the real sample has no standstill), splitting runs at the gaps.
    """
    if onboard_si.ndim != 2 or onboard_si.shape[1] != schema.NUM_SIGNALS:
        raise ValueError(f"onboard must be (N, {schema.NUM_SIGNALS}), got {onboard_si.shape}")
    wheel_idx = [schema.SIGNAL_BY_NAME[n].index for n in schema.WHEEL_SPEED_NAMES]
    keep = np.ones(len(onboard_si), dtype=bool)
    if moving_only:
        keep = onboard_si[:, wheel_idx].mean(axis=1) >= 1.0
    # contiguous kept segments
    edges = np.diff(np.concatenate(([0], keep.astype(np.int8), [0])))
    segs = list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True))
    out = []
    for sig in schema.SIGNALS:
        x_all = onboard_si[:, sig.index] / sig.revsted_scale
        x = x_all[keep]
        holds = np.concatenate([hold_lengths(x_all[a:b]) for a, b in segs] or [np.zeros(0)])
        changes = sum(int(np.count_nonzero(np.diff(x_all[a:b]))) for a, b in segs)
        pairs = sum(max(0, b - a - 1) for a, b in segs)
        out.append(SignalProfile(
            name=sig.name, column=sig.revsted_column, unit=sig.revsted_unit,
            step=float(np.round(quantisation_step(x), 3)) if len(x) > 1 else float("nan"),
            hold_median=float(np.median(holds)) if len(holds) else float("nan"),
            hold_p90=float(np.percentile(holds, 90)) if len(holds) else float("nan"),
            hold_mean=float(np.mean(holds)) if len(holds) else float("nan"),
            change_fraction=changes / pairs if pairs else float("nan"),
            p5=float(np.percentile(x, 5)), p95=float(np.percentile(x, 95)),
            minimum=float(np.min(x)), maximum=float(np.max(x)),
        ))
    return out


def speedometer_ratio(onboard_si: np.ndarray) -> float:
    """Mean speedometer reading over mean wheel speed on moving rows (> 1 m/s)."""
    wheel_idx = [schema.SIGNAL_BY_NAME[n].index for n in schema.WHEEL_SPEED_NAMES]
    wheels = onboard_si[:, wheel_idx].mean(axis=1)
    moving = wheels > 1.0
    speedo = onboard_si[moving, schema.SIGNAL_BY_NAME["speedometer_mps"].index]
    return float(np.mean(speedo) / np.mean(wheels[moving]))


def compare_profiles(real: list[SignalProfile], sim: list[SignalProfile]) -> list[dict]:
    """Row per signal comparing a real and a simulated profile, with pass/fail per criterion.

    Criteria: quantisation steps equal (within 2 %); median hold lengths within a factor
    of 3; p5-p95 spans within a factor of 10 ("same order"). The real sample contains no
    braking event, so for brake pressure the idle level (p5) is compared instead of the span.
    """
    rows = []
    for r, s in zip(real, sim, strict=True):
        step_ok = abs(s.step - r.step) <= 0.02 * r.step
        hold_ratio = s.hold_median / r.hold_median
        hold_ok = 1 / 3 <= hold_ratio <= 3
        if r.name == "brake_pressure_bar":
            range_ratio = (s.p5 + 0.5) / (r.p5 + 0.5)  # idle pressure, offset so 0 bar cannot divide
        else:
            range_ratio = (s.p95 - s.p5) / max(r.p95 - r.p5, 1e-9)
        range_ok = 0.1 <= range_ratio <= 10
        rows.append({"signal": r.name, "column": r.column, "unit": r.unit,
                     "step_real": r.step, "step_sim": s.step, "step_ok": step_ok,
                     "hold_median_real": r.hold_median, "hold_median_sim": s.hold_median,
                     "hold_p90_real": r.hold_p90, "hold_p90_sim": s.hold_p90, "hold_ok": hold_ok,
                     "change_real": r.change_fraction, "change_sim": s.change_fraction,
                     "range_real": [r.p5, r.p95], "range_sim": [s.p5, s.p95], "range_ratio": range_ratio,
                     "range_ok": range_ok})
    return rows
