"""Offset jumps of the yaw rate, a_y and the steering, found at their step (step 5 of the stage).

A step within one row of the signal's first difference that the residual follows while the others go on as before
is an offset jump, flagged when confirmed (0.4-0.9 s after it) even inside the residual tolerance. Its size is
measured from the values around the step and the substitute is the signal less it (reported in
``AssembledRow.offset_jumps``, from which the pipeline takes back the heading the jump cost before it was found). A
confirmed step back ends the correction.

A step ``S`` (the difference at one row less the local slope, from the 5 differences either side) beyond
:attr:`~.PlausibilityConfig.jump_noise_gain` times the usual innovation, the signal's ``jump_min_*`` and 1.5
resolution steps, with the differences next to it and the slope after it as before (``jump_sharp``), is a candidate.
It is an offset jump when the raw residual's mean over ``jump_after_s`` (from the signal's ``jump_lag*_s`` after the
step) moved from its mean over ``jump_before_s`` before by ``S`` within ``jump_match``, the residual steady on both
sides (``jump_steady``) and, for the steering, the others' prediction going on along its trend
(``jump_others_still``): a real change of the car's motion moves the others with it, a bump is gone by then.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from .checks import Check
from .config import AY, SIGNAL_UNITS, SW, YAW, PlausibilityConfig
from .models import median


def _mean_at(pts: list[tuple[int, float]]) -> float:
    return sum(v for _, v in pts) / len(pts)


def _trend_at(pts: list[tuple[int, float]], k: float) -> float:
    """The straight line through ``(row, value)`` points (least squares), at row ``k``."""
    n = len(pts)
    km = sum(a for a, _ in pts) / n
    vm = sum(v for _, v in pts) / n
    sxx = sum((a - km) ** 2 for a, _ in pts)
    b = sum((a - km) * (v - vm) for a, v in pts) / sxx if sxx > 0 else 0.0
    return vm + b * (k - km)


class JumpDetector:
    """Step detector of one signal (``YAW``, ``AY`` or ``SW``): its first differences, their usual innovation, the
    raw residuals and values around a candidate step."""

    def __init__(self, signal: int, cfg: PlausibilityConfig, dt_s: float) -> None:
        self.signal = signal
        self.cfg = cfg
        self.dt_s = dt = dt_s
        lag = {YAW: cfg.jump_lag_s, AY: cfg.jump_lag_ay_s, SW: cfg.jump_lag_steer_s}[signal]
        # rows from the step to the residual's window after it, that window's length and the one before it
        self.lag, self.after, self.before = (int(round(lag / dt)), int(round(cfg.jump_after_s / dt)),
                                             int(round(cfg.jump_before_s / dt)))
        self.min_step = {YAW: cfg.jump_min_yaw_radps, AY: cfg.jump_min_ay_mps2, SW: cfg.jump_min_steer_rad}[signal]
        self.last_x = math.nan
        self.d1: deque = deque(maxlen=6)
        self.noise = 0.0  # EMA of |first difference - local slope|
        self.noise_n = 0
        self.resid: deque = deque(maxlen=96)  # (row number, raw residual, prediction)
        self.values: deque = deque(maxlen=64)  # (row number, value)
        self.n = 0
        self.cand: list | None = None  # [row number, t, step, pre-step differences, post-step differences, S]

    def restart(self) -> None:
        """After a gap in the stream: differences, windows and candidate start again (the noise level stays)."""
        self.last_x = math.nan
        self.d1.clear()
        self.resid.clear()
        self.values.clear()
        self.cand = None

    def row(self, xi: float, r: float | None, p: float | None, moving: bool, t: float,
            res: float) -> tuple[float, float, float] | None:
        """One row: value ``xi``, raw residual ``r`` and the others' prediction ``p`` (None: not checked), the
        signal's resolution ``res``. ``(offset, std, t of the step)`` of an offset jump confirmed now, else None."""
        cfg = self.cfg
        self.n += 1
        n = self.n
        if r is not None and p is not None:
            self.resid.append((n, r, p))
        d = xi - self.last_x if math.isfinite(self.last_x) else math.nan
        self.last_x = xi
        self.values.append((n, xi))
        if not math.isfinite(d):
            return None
        found = None
        cand = self.cand
        if cand is not None:
            if cand[5] is None:
                if not self._sharp(cand, d, res):
                    self.cand = None
                    self.d1.append(d)
                    return None
            elif n - cand[0] >= self.lag + self.after:
                self.cand = None
                found = self._confirm(cand, res)
        d1 = self.d1
        if self.cand is None and moving and self.noise_n >= 50 and len(d1) == d1.maxlen:
            hist = list(d1)[-5:]
            inn = d - median(hist)
            if abs(inn) > max(cfg.jump_noise_gain * self.noise, self.min_step, 1.5 * res):
                self.cand = [n, t, d, hist, [], None]
            else:
                self.noise += (min(abs(inn), 4.0 * self.noise) - self.noise) * self.dt_s / 5.0
        elif self.cand is None and len(d1) == d1.maxlen:
            inn = abs(d - median(list(d1)[-5:]))
            self.noise_n += 1
            self.noise += (inn - self.noise) / min(self.noise_n, 250) if self.noise_n < 50 else \
                (min(inn, 4.0 * self.noise) - self.noise) * self.dt_s / 5.0
        d1.append(d)
        return found

    def _sharp(self, cand: list, d: float, res: float) -> bool:
        """The candidate's next difference ``d``; with 5 of them its step ``S`` against the local slope. False when
        the step is not one row's (the candidate is dropped)."""
        cand[4].append(d)
        if len(cand[4]) == 5:
            slope = 0.5 * (median(cand[3]) + median(cand[4]))
            cand[5] = cand[2] - slope
            # an offset jumps within one row; the driver's fastest steering, a bump, take several
            # and the signal goes on at the rate it had (a driver's step starts a ramp)
            if max(abs(cand[3][-1] - slope), abs(cand[4][0] - slope), abs(cand[4][1] - slope),
                   abs(median(cand[4]) - median(cand[3]))) > self.cfg.jump_sharp * abs(cand[5]) + res:
                return False
        return True

    def _confirm(self, cand: list, res: float) -> tuple[float, float, float] | None:
        """The residual's windows before and after the candidate's step: did it move by the step, and stay steady?"""
        cfg = self.cfg
        lag, after, before = self.lag, self.after, self.before
        step = cand[5]
        win_pre = [e for e in self.resid if cand[0] - before <= e[0] < cand[0]]
        win_post = [e for e in self.resid if cand[0] + lag <= e[0] < cand[0] + lag + after]
        pre, post = [e[1] for e in win_pre], [e[1] for e in win_post]
        p_pre, p_post = [(e[0], e[2]) for e in win_pre], [(e[0], e[2]) for e in win_post]
        # steering: the others went on as they were going (a driver's steering step turns the car after it)
        still = self.signal != SW or (len(p_pre) >= 3 and bool(p_post) and abs(
            _mean_at(p_post) - _trend_at(p_pre, sum(k for k, _ in p_post) / len(p_post)))
            < cfg.jump_others_still * abs(step))
        if not (still and len(pre) >= before // 2 and len(post) >= after // 2):
            return None
        m0, m1 = sum(pre) / len(pre), sum(post) / len(post)
        shift = m1 - m0
        # an offset leaves the residual as steady as it was; a response settling (the car catching
        # up with a fast steering input) moves it
        var0 = sum((a - m0) ** 2 for a in pre) / len(pre)
        var1 = sum((a - m1) ** 2 for a in post) / len(post)
        lim = (cfg.jump_steady * step) ** 2 + 0.25 * res * res  # (a coarse signal's quantisation)
        steady = var0 <= lim and var1 <= lim + 2.0 * var0
        if steady and shift * step > 0 and \
                abs(shift - step) < cfg.jump_match * abs(step) + 2.0 * math.sqrt(var0 + var1):
            return self._measure(cand, step, shift, pre, post, m0, m1, res)
        return None

    def _measure(self, cand, step, shift, pre, post, m0, m1, res) -> tuple[float, float, float] | None:
        """``(offset, std, t of the step)``: from the values around the step, else the step and the residual's
        shift weighted by their variances. None when the values do not see the step."""
        fit = self.step_fit(cand[0])
        if fit is not None:
            # the values around the step measure it best (the residual carries the others' noise); they must see the
            # step too (a coarse signal's difference wobbles by a step: the values around it do not)
            if abs(fit[0] - step) > self.cfg.jump_match * abs(step) + res \
                    or abs(fit[0]) < max(self.min_step, 1.5 * res):
                return None
            offset, sd_fit = fit
            return offset, math.hypot(sd_fit, res / math.sqrt(12.0)), cand[1]
        var_d = 2.0 * self.noise ** 2 + res * res / 3.0
        var_s = (sum((a - m0) ** 2 for a in pre) / len(pre) / max(len(pre) / 5.0, 1.0)
                 + sum((a - m1) ** 2 for a in post) / len(post) / max(len(post) / 5.0, 1.0))
        w = var_s / (var_d + var_s) if var_d + var_s > 0 else 1.0
        std = math.sqrt(var_d * var_s / (var_d + var_s)) if var_d + var_s > 0 else 0.0
        return w * step + (1.0 - w) * shift, std, cand[1]

    def step_fit(self, k0: int, half: int = 15) -> tuple[float, float] | None:
        """``(step, std)`` at row ``k0`` from the values around it: a quadratic in time plus a step, least squares."""
        pts = [(k - k0, v) for k, v in self.values if -half <= k - k0 < half]
        if len(pts) < half or sum(1 for tau, _ in pts if tau < 0) < 4 or sum(1 for tau, _ in pts if tau >= 0) < 4:
            return None
        tau = np.array([p_[0] for p_ in pts], dtype=float)
        a = np.column_stack([np.ones_like(tau), tau, tau * tau, (tau >= 0).astype(float)])
        y = np.array([p_[1] for p_ in pts])
        coef, *_ = np.linalg.lstsq(a, y, rcond=None)
        dof = len(pts) - 4
        s2 = float(np.sum((y - a @ coef) ** 2)) / dof if dof > 0 else 0.0
        return float(coef[3]), math.sqrt(s2 * float(np.linalg.inv(a.T @ a)[3, 3]))


def take_offset(c: Check, i: int, found: tuple[float, float, float], res: float, match: float, xi: float,
                p: float | None) -> tuple[int, float, float, float] | None:
    """An offset jump of signal ``i`` confirmed: correct its check ``c`` by it (on top of one found before, or
    ending that one when it stepped back) and say why. ``(i, offset, std, t of the step)`` to report, or None."""
    if c.flagged and c.reason.startswith(("stuck", "dropout")):
        return None  # a dead value, not an offset: the others' prediction stays its substitute
    if xi == 0.0:
        return None
    offset, std, t_step = found
    before = c.offset
    c.offset, c.offset_std = offset, std
    c.offset_resid, c.offset_over_s = 0.0, 0.0
    if before:
        if c.offset * before < 0 and abs(c.offset + before) < match * abs(before) + res:
            c.offset = 0.0  # it stepped back: the correction ends, the flag clears as usual
            c.reason += f"; stepped back at {t_step:.2f} s"
            return None
        c.offset += before  # a second jump on top of the first
    unit, k = SIGNAL_UNITS[i]
    ref = f"{p * k:.2f}" if p is not None else "?"
    c.reason = (f"offset: jumped by {c.offset * k:+.2f} {unit} at {t_step:.2f} s (reads {xi * k:.2f} where the "
                f"others say {ref}); replaced by the value less the jump")
    return i, c.offset - before, c.offset_std, t_step
