"""The CAN yaw rate's gain, learned from GNSS heading over many drives and kept in the calibration file.

A MEMS yaw-rate sensor reads ``(1 + k) omega_z + offset``. The offset is learned within a drive (standstill,
GNSS, the model); the gain error ``k`` (about 1 % on production sensors) is not: a 60 s outage with 1 % gain
error turns 180 deg of turning into 1.8 deg of heading error, and no onboard cue tells it (the error budget,
``benchmarks/error_budget.py``). GNSS heading does, but only in turns, and one drive has few: a fit over a
drive's first five minutes left 1.7 % on the benchmark's test drives. The gain belongs to the sensor, so this
estimator adds up the evidence of every drive and the calibration file carries it to the next.

How: while GNSS heading is fused (moving, trusted fixes), the raw CAN yaw rate is integrated (``phi``). Within
a chunk of at most ``CHUNK_S`` of continuous fixes the GNSS heading is regressed on ``[phi, t, 1]``:
heading = c phi + d t + e, with ``c = 1 / (1 + k)``, the offset's heading drift ``d`` and the start heading ``e``
free per chunk (the offset moves between and within drives). A chunk adds the information its turning gives on
``c`` (the Schur complement of ``d`` and ``e``) and its estimate; straight driving adds nothing. The estimate is the
information-weighted mean, shrunk to ``c = 1`` by the prior (``prior_std``). A chunk whose residual is far
beyond the heading noise (reversing, a jump) is dropped and counted.

The filter divides the CAN yaw-rate cue by ``1 + k`` (a known correction, as the wheel scale's GNSS estimate).
"""

from __future__ import annotations

import math

import numpy as np

CHUNK_S = 60.0  # longest chunk: the offset drifts (Gauss-Markov, ~200 s) and is one number per chunk
MIN_CHUNK_S = 10.0
MIN_CHUNK_FIXES = 20
GAP_S = 1.5  # fixes further apart end the chunk
RESIDUAL_LIMIT = 3.0  # a chunk's residual rms above this many heading sigmas is dropped
_N = 5  # regressors: phi, t, 1, r / v, r v
MAX_CONDITION = 1e12  # a chunk whose regressors are (nearly) dependent adds nothing
PRIOR_STD = 0.01  # gain error of a production sensor, one sigma (the simulator draws the same)
RESTORE_STD_FLOOR = 0.001  # a restored gain is a prior of at most this certainty (temperature, ageing)


class YawGainEstimator:
    """Accumulates GNSS-heading evidence on the CAN yaw rate's gain; :attr:`gain` is the estimate ``k``."""

    def __init__(self, heading_std_rad: float, prior_std: float = PRIOR_STD) -> None:
        self.heading_var = float(heading_std_rad) ** 2
        self.prior_info = 1.0 / prior_std ** 2
        self.info = 0.0  # information on c from the chunks [1 / 1^2]
        self.info_c = 0.0  # information-weighted sum of their c
        self.n_chunks = self.n_dropped = 0
        self.phi = 0.0  # integral of the raw CAN yaw rate [rad]
        self._sums: np.ndarray | None = None
        self._t0 = self._phi0 = self._last_t = self._last_y = self._last_phi = 0.0
        self.gain = 0.0

    # ---- evidence ---------------------------------------------------------------------------------

    def yaw_rate(self, yaw_rate_radps: float | None, dt_s: float) -> None:
        """One row's raw CAN yaw rate (None: invalid, which ends the chunk)."""
        if yaw_rate_radps is None:
            self.close_chunk()
            return
        self.phi += yaw_rate_radps * dt_s

    def heading(self, t_s: float, psi_rad: float, yaw_rate_radps: float, speed_mps: float) -> None:
        """A fused GNSS heading at ``t_s`` (the row's time, so :attr:`phi` is the integral up to it), with the row's
        yaw rate and speed (the sideslip's regressors: GNSS tells the course over ground, not the yaw)."""
        if self._sums is not None and t_s - self._last_t > GAP_S:
            self.close_chunk()
        if self._sums is None:
            self._sums = np.zeros((_N + 1, _N + 1))
            self._t0, self._phi0, y = t_s, self.phi, psi_rad
        else:  # unwrap against the gyro's prediction
            pred = self._last_y + (self.phi - self._last_phi)
            y = pred + math.remainder(psi_rad - pred, 2.0 * math.pi)
        self._last_t, self._last_y, self._last_phi = t_s, y, self.phi
        # course = yaw + sideslip; the sideslip of a steady turn ~ a r / v + b r v (kinematic, then tyres), a and b
        # per chunk: the antenna's place and the load are unknown
        row = np.array([self.phi - self._phi0, t_s - self._t0, 1.0, yaw_rate_radps / speed_mps,
                        yaw_rate_radps * speed_mps, y])
        self._sums += np.outer(row, row)
        if t_s - self._t0 >= CHUNK_S:
            self.close_chunk()

    def close_chunk(self) -> None:
        """Add the open chunk's evidence (if it has enough) and start none."""
        s, self._sums = self._sums, None
        if s is None or s[2, 2] < MIN_CHUNK_FIXES or self._last_t - self._t0 < MIN_CHUNK_S:
            return
        m, b = s[:_N, :_N], s[:_N, _N]
        if np.linalg.cond(m) > MAX_CONDITION:  # e.g. a steady turn: sideslip and heading rate not separable
            return
        inv = np.linalg.inv(m)
        coef = inv @ b
        n = s[2, 2]
        ssr = max(float(s[_N, _N] - coef @ b), 0.0)
        if ssr / max(n - _N, 1.0) > RESIDUAL_LIMIT ** 2 * self.heading_var:
            self.n_dropped += 1
            return
        info = 1.0 / (inv[0, 0] * self.heading_var)
        if not math.isfinite(info) or info <= 0.0:
            return
        self.info += info
        self.info_c += info * float(coef[0])
        self.n_chunks += 1
        self._update()

    def _update(self) -> None:
        c = (self.prior_info + self.info_c) / (self.prior_info + self.info)
        self.gain = 1.0 / c - 1.0

    @property
    def std(self) -> float:
        """One-sigma uncertainty of :attr:`gain` [1] (white heading noise assumed; a floor of the truth)."""
        return 1.0 / math.sqrt(self.prior_info + self.info)

    # ---- the calibration file ----------------------------------------------------------------------

    def state(self) -> dict:
        """What the calibration file keeps: the evidence, so the next drive adds to it."""
        return {"info": self.info, "info_c": self.info_c, "gain": self.gain, "std": self.std,
                "chunks": self.n_chunks}

    def restore(self, info: float, info_c: float) -> None:
        """Start from saved evidence, its information capped at :data:`RESTORE_STD_FLOOR`."""
        if not (math.isfinite(info) and math.isfinite(info_c) and info > 0.0):
            return
        cap = 1.0 / RESTORE_STD_FLOOR ** 2
        c = info_c / info
        self.info = min(info, cap)
        self.info_c = self.info * c
        self._update()

    def summary(self) -> dict:
        return {"yaw_rate_gain_pct": 100.0 * self.gain, "yaw_rate_gain_std_pct": 100.0 * self.std,
                "yaw_rate_gain_chunks": self.n_chunks, "yaw_rate_gain_chunks_dropped": self.n_dropped}
