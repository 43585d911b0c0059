"""The relations' learned models (recursive least squares with forgetting, exponential averages) and the robust
statistics the checks take their references with (median, weighted median), in plain floats, one row at a time."""

from __future__ import annotations

import math


def _dot(a: list[float], b: list[float]) -> float:
    """``sum(a_i b_i)`` with the additions in the order of ``sum()`` on CPython 3.11 (from 0, left to right),
    unrolled for the 2 and 3 parameters of :class:`Rls` (the generator expression was most of its cost)."""
    if len(a) == 2:
        return 0.0 + a[0] * b[0] + a[1] * b[1]
    return 0.0 + a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


class Rls:
    """Recursive least squares with exponential forgetting, in plain floats (2 or 3 parameters)."""

    def __init__(self, theta: list[float], prior_std: list[float], forget: float) -> None:
        self.theta = list(theta)
        n = len(theta)
        if n not in (2, 3):
            raise ValueError(f"Rls takes 2 or 3 parameters, got {n}")
        self.P = [[(prior_std[i] ** 2 if i == j else 0.0) for j in range(n)] for i in range(n)]
        self.max_var = [sd * sd for sd in prior_std]
        self.forget = forget
        self.n = 0

    def update(self, phi: list[float], y: float, noise_var: float) -> None:
        """One sample: regressors ``phi``, measurement ``y``, its noise variance (Kalman-form RLS, the covariance
        divided by the forgetting factor, then held at the prior's size: :meth:`_no_wind_up`)."""
        if len(phi) == 2:
            self._update2(phi, y, noise_var)
        else:
            self._update3(phi, y, noise_var)

    def _update2(self, phi: list[float], y: float, noise_var: float) -> None:
        """:meth:`update` for two parameters (the wheel pairs, the brake gain: most updates), unrolled: each product
        summed from 0, left to right (as ``sum()`` and :func:`_dot`), without loops."""
        P, theta, lam = self.P, self.theta, self.forget
        (p00, p01), (p10, p11) = P
        phi0, phi1 = phi
        pphi0 = 0.0 + p00 * phi0 + p01 * phi1
        pphi1 = 0.0 + p10 * phi0 + p11 * phi1
        s = noise_var * lam + (0.0 + phi0 * pphi0 + phi1 * pphi1)
        if not s > 0.0:
            return
        err = y - (0.0 + theta[0] * phi0 + theta[1] * phi1)
        k0, k1 = pphi0 / s, pphi1 / s
        theta[0] += k0 * err
        theta[1] += k1 * err
        P[0][0], P[0][1] = (p00 - k0 * pphi0) / lam, (p01 - k0 * pphi1) / lam
        P[1][0], P[1][1] = (p10 - k1 * pphi0) / lam, (p11 - k1 * pphi1) / lam
        self._no_wind_up()
        self.n += 1

    def _update3(self, phi: list[float], y: float, noise_var: float) -> None:
        """:meth:`update` for three parameters (the steering model), unrolled like :meth:`_update2`."""
        P, theta, lam = self.P, self.theta, self.forget
        (p00, p01, p02), (p10, p11, p12), (p20, p21, p22) = P
        phi0, phi1, phi2 = phi
        pphi0 = 0.0 + p00 * phi0 + p01 * phi1 + p02 * phi2
        pphi1 = 0.0 + p10 * phi0 + p11 * phi1 + p12 * phi2
        pphi2 = 0.0 + p20 * phi0 + p21 * phi1 + p22 * phi2
        s = noise_var * lam + (0.0 + phi0 * pphi0 + phi1 * pphi1 + phi2 * pphi2)
        if not s > 0.0:
            return
        err = y - (0.0 + theta[0] * phi0 + theta[1] * phi1 + theta[2] * phi2)
        k0, k1, k2 = pphi0 / s, pphi1 / s, pphi2 / s
        theta[0] += k0 * err
        theta[1] += k1 * err
        theta[2] += k2 * err
        P[0][0], P[0][1], P[0][2] = (p00 - k0 * pphi0) / lam, (p01 - k0 * pphi1) / lam, (p02 - k0 * pphi2) / lam
        P[1][0], P[1][1], P[1][2] = (p10 - k1 * pphi0) / lam, (p11 - k1 * pphi1) / lam, (p12 - k1 * pphi2) / lam
        P[2][0], P[2][1], P[2][2] = (p20 - k2 * pphi0) / lam, (p21 - k2 * pphi1) / lam, (p22 - k2 * pphi2) / lam
        self._no_wind_up()
        self.n += 1

    def _no_wind_up(self) -> None:
        """A parameter the data do not excite (the track on a straight) keeps at most its prior uncertainty, so
        one odd sample cannot move it far."""
        P = self.P
        n = len(P)
        for i in range(n):
            if P[i][i] > self.max_var[i]:
                f = math.sqrt(self.max_var[i] / P[i][i])
                for j in range(n):
                    P[i][j] *= f
                    P[j][i] *= f

    def predict(self, phi: list[float]) -> float:
        return _dot(self.theta, phi)  # (sum()'s order, unrolled)


class Ema:
    """Exponential moving average ``value += alpha (x - value)``."""

    __slots__ = ("a", "value")

    def __init__(self, alpha: float, value: float = 0.0) -> None:
        self.a = alpha
        self.value = value

    def update(self, x: float) -> float:
        self.value += self.a * (x - self.value)
        return self.value


def weighted_median(items: list[tuple[float, float]]) -> tuple[float, float]:
    """``(value, sigma)`` of the weighted median of ``(value, sigma)`` pairs, weights ``1 / sigma^2``."""
    items = sorted(items)
    w = [1.0 / (sd * sd) for _, sd in items]
    half = 0.5 * sum(w)
    acc = 0.0
    for (value, sd), wi in zip(items, w, strict=True):
        acc += wi
        if acc >= half:
            return value, sd
    return items[-1]


def median(xs: list[float]) -> float:
    """The median of ``xs`` (the mean of the middle two for an even count)."""
    s = sorted(xs)
    n = len(s)
    m = n // 2
    return s[m] if n % 2 else 0.5 * (s[m - 1] + s[m])

