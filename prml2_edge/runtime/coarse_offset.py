"""A coarse gyro's offset from the intervals its readings allow (issue 26): a likelihood over a grid of ``b``.

A gyro rounded to a step of ``s`` (the ReV-StED car's 1.28 deg/s) reads ``r`` while its true rate plus its offset
``b`` lies within ``r ± s / 2``. On a straight it reads 0 whatever ``b`` within half a step, so a block mean of gyro
less the cues measures the rounding of the road's gentle curves, not ``b``, and a Gaussian over blocks grows surer
without growing righter (docs/ablation.md). What each run of one reading does tell is an interval::

    r − s/2 − min(ω) ≤ b ≤ r + s/2 − max(ω)

with ``ω`` the true rate over the run, told by the cues (``a_y / v`` less its offset ``c``, which the cue estimator
learns from the cues' differences). Over minutes the runs' intervals, at different rates, close in on ``b``; where the
reading steps, the two runs either side meet at the crossing. :class:`CoarseOffset` multiplies those intervals,
each softened only by the white noise of the gyro and of the smoothed cue and mixed with a small outlier share (a
bend whose sideslip the cue misreads: one wrong run cannot collapse the posterior), into a likelihood over a grid of
``b``, and blurs it once by the cue's common error (softening every run by it instead would, multiplied, peak the
posterior in the middle of the allowed range). It hands its mean and variance to :class:`~.cue_offset.CueOffset` in
place of the Gaussian ``b``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from prml2_edge import schema

_Z = np.linspace(-8.0, 8.0, 16001)
_PHI = np.array([0.5 * (1.0 + math.erf(z / math.sqrt(2.0))) for z in _Z])  # the standard normal CDF, tabled
@dataclass(frozen=True)
class CoarseOffsetConfig:
    """The grid likelihood's settings (SI units), set on the reference car's validation drives (docs/ablation.md)."""

    smooth_rows: int = 10  # the cue's rate averaged over this many rows before its run's extremes are taken
    # the cue's error that does not average out (sideslip, road, c): common to the runs, so it blurs their
    # intersection once instead of softening each run's edges (which, multiplied, would peak in the middle)
    slow_std_radps: float = 0.05 * schema.DEG_TO_RAD
    gyro_noise_radps: float = 0.06 * schema.DEG_TO_RAD  # the gyro's white noise before its rounding
    outlier_share: float = 0.05  # each run's likelihood mixed with this much of "the run says nothing"
    grid_step_radps: float = 0.005 * schema.DEG_TO_RAD
    min_run_rows: int = 3  # a run of one reading this short (after smoothing) is left out


class CoarseOffset:
    """The posterior over ``b`` on a grid from the prior ``N(0, prior_std²)``; :meth:`block` once per block of
    straight rows."""

    def __init__(self, prior_std_radps: float, config: CoarseOffsetConfig | None = None) -> None:
        self.config = config or CoarseOffsetConfig()
        self.prior_std = float(prior_std_radps)
        half = 4.0 * self.prior_std
        n = 2 * int(math.ceil(half / self.config.grid_step_radps)) + 1
        self.grid = np.linspace(-half, half, n)
        self.reset()

    def reset(self) -> None:
        self.loglik = np.zeros_like(self.grid)  # the runs' intervals, each softened by its own noise only
        self.blur_std = self.config.slow_std_radps  # the common error, at the last block
        self.runs = 0

    def block(self, readings: np.ndarray, rate: np.ndarray, step_radps: float, rate_std_radps: float) -> int:
        """One block of consecutive straight rows: the gyro's ``readings`` and the cues' ``rate`` per row [rad/s],
        the gyro's resolution ``step_radps`` and the rate's slow uncertainty beyond the configured one (its offset's
        sigma) [rad/s]. Returns the runs of one reading it used."""
        cfg = self.config
        k = cfg.smooth_rows
        if len(readings) < k + cfg.min_run_rows - 1:
            return 0
        smooth = np.convolve(rate, np.ones(k) / k, mode="valid")
        # the smoothed rate's own noise (from the rows' first differences: the rate itself hardly moves in a row)
        noise = float(np.std(np.diff(rate))) / math.sqrt(2.0 * k)
        r = np.asarray(readings[k - 1:], dtype=np.float64)
        half = 0.5 * step_radps
        s = math.hypot(cfg.gyro_noise_radps, noise)
        self.blur_std = math.hypot(cfg.slow_std_radps, rate_std_radps)
        used = 0
        cuts = np.flatnonzero(np.diff(r)) + 1
        for run_r, run_w in zip(np.split(r, cuts), np.split(smooth, cuts), strict=True):
            if len(run_r) < cfg.min_run_rows:
                continue
            # a run's extremes of a noisy rate lie beyond the true rate's by about this (the expected maximum of
            # its independent stretches): taken back, so that the noise does not narrow the interval
            reach = noise * math.sqrt(2.0 * math.log(len(run_r) / k + 1.0))
            hi = (run_r[0] + half - float(run_w.max()) + reach - self.grid) / s
            lo = (run_r[0] - half - float(run_w.min()) - reach - self.grid) / s
            lik = np.interp(hi, _Z, _PHI) - np.interp(lo, _Z, _PHI)
            self.loglik += np.log(cfg.outlier_share + (1.0 - cfg.outlier_share) * np.maximum(lik, 0.0))
            used += 1
        self.runs += used
        return used

    @property
    def offset(self) -> tuple[float, float]:
        """``(b, its standard deviation)`` [rad/s]: the posterior's mean and spread (the prior times the runs'
        likelihood blurred by the common error)."""
        lik = np.exp(self.loglik - self.loglik.max())
        # (a blur wider than the grid is cut to it: np.convolve's 'same' would return the longer of the two)
        half = min(int(math.ceil(4.0 * self.blur_std / self.config.grid_step_radps)), (len(self.grid) - 1) // 2)
        if half:
            kernel = np.exp(-0.5 * np.square(np.arange(-half, half + 1) * self.config.grid_step_radps / self.blur_std))
            lik = np.convolve(lik, kernel / kernel.sum(), mode="same")
        p = lik * np.exp(-0.5 * np.square(self.grid / self.prior_std))
        p /= p.sum()
        mean = float(p @ self.grid)
        return mean, math.sqrt(max(float(p @ np.square(self.grid - mean)), 0.0))
