"""A test-track driver: manoeuvre plans for the paper's families, at 50 Hz.

The plan is a sequence of manoeuvres, each giving a planned speed ``v_ref`` [m/s] with
its feed-forward acceleration [m/s^2] (cosine ramps: smooth jerk) and a path curvature
``kappa`` [1/m] (left positive). The steering demand is the kinematic angle plus an
understeer correction, rate limited like a human hand, with small corrections noise.

Families (method.md; paper Sec. IV):

* ``longitudinal``: accelerate, cruise, brake (also to standstill), gentle bends;
* ``lateral``: slaloms, steady circles, lane changes, tight low-speed turns;
* ``mixed``: both, plus braking and accelerating in bends;
* ``snow``: the mixed catalogue at mu 0.2-0.5 with gentler inputs, driven closer to
  the (lower) limit, so the tyres slip more.
* ``highway``: a real car's commute rather than a test track: the drive starts at speed
  (14-25 m/s) and never stops, gentle bends (|a_y| <= ~1.2 m/s^2, yaw rate a few deg/s),
  slow lane changes and gentle speed changes. No standstill, so nothing calibrates a gyro
  offset for free (issue 28: what real highway logs look like).

``standstill=False`` (any family) is the same test-track driver without stops: the drive starts
at speed (:data:`NO_STOP_V0_MPS`), the ``standstill`` manoeuvre is out of the catalogue and a
``brake`` ends at :data:`NO_STOP_V_MIN_MPS` or faster. Nothing calibrates a gyro offset at rest,
as on a real car that never stops (``benchmarks/robustness.py``, issue 26).

Accelerations stay inside what a driver does on a test track: longitudinal up to
~0.6 mu g (emergency-like stops rarer), lateral up to ~0.75 mu g.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from prml2_edge import schema
from prml2_edge.data.simulate.vehicle import VehicleParams

FAMILIES = ("longitudinal", "lateral", "mixed", "snow", "highway")
HIGHWAY_V0_MPS = (14.0, 25.0)
HIGHWAY_AY_MAX_MPS2 = 1.2
V_MAX_PLAN_MPS = 28.0
NO_STOP_V0_MPS = (8.0, 16.0)  # standstill=False: start speed of a test-track family [m/s]
NO_STOP_V_MIN_MPS = 3.0  # standstill=False: the lowest speed a brake manoeuvre ends at [m/s]
DT = schema.DT_S


@dataclass
class DriverPlan:
    """50 Hz driver plan; every array is (N,)."""

    v_ref: np.ndarray  # m/s
    accel_ff: np.ndarray  # m/s^2
    kappa: np.ndarray  # 1/m, left positive
    delta_cmd: np.ndarray  # front wheel angle [rad]
    free_steer: np.ndarray  # bool: the driver may steer back towards the track centre
    manoeuvre: list[tuple[int, str]]  # (start sample, name)
    v0_mps: float = 0.0  # speed at the first sample (0: the drive starts at rest)


class _Builder:
    def __init__(self, rng: np.random.Generator, mu: float, family: str, v_min: float = 0.0) -> None:
        self.rng = rng
        self.mu = mu
        self.family = family
        self.v_min = v_min  # the lowest speed a brake ends at (0: to standstill)
        self.v = 0.0
        self.v_parts: list[np.ndarray] = []
        self.a_parts: list[np.ndarray] = []
        self.k_parts: list[np.ndarray] = []
        self.f_parts: list[np.ndarray] = []
        self.labels: list[tuple[int, str]] = []
        self.n = 0
        gentle = 0.75 if family == "snow" else 1.0
        self.a_long = min(4.0, 0.6 * mu * schema.G_MPS2) * gentle  # typical firm acceleration/braking
        self.a_lat = min(7.5, 0.75 * mu * schema.G_MPS2) * (0.95 if family == "snow" else 1.0)

    # -- primitives ------------------------------------------------------------------------
    def _push(self, name: str, v: np.ndarray, a: np.ndarray, kappa: np.ndarray, free: bool) -> None:
        self.labels.append((self.n, name))
        self.v_parts.append(v)
        self.a_parts.append(a)
        self.k_parts.append(kappa)
        self.f_parts.append(np.full(len(v), free))
        self.n += len(v)
        self.v = float(v[-1]) if len(v) else self.v

    def speed_change(self, v_target: float, a_peak: float, kappa: float = 0.0, kappa_end: float | None = None,
                     name: str = "speed_change", free: bool = True) -> None:
        """Cosine speed ramp to ``v_target`` with peak acceleration ``a_peak``; curvature ramps linearly."""
        dv = v_target - self.v
        if abs(dv) < 0.05:
            return
        duration = math.pi * abs(dv) / (2.0 * a_peak)
        t = np.arange(1, max(2, int(round(duration / DT))) + 1) * DT
        duration = t[-1]
        v = self.v + dv * 0.5 * (1.0 - np.cos(np.pi * t / duration))
        a = dv * 0.5 * np.pi / duration * np.sin(np.pi * t / duration)
        k = np.linspace(kappa, kappa if kappa_end is None else kappa_end, len(v))
        self._push(name, v, a, k, free)

    def hold(self, duration_s: float, kappa: np.ndarray | float = 0.0, name: str = "cruise",
             free: bool = True) -> None:
        n = max(1, int(round(duration_s / DT)))
        k = np.full(n, float(kappa)) if np.ndim(kappa) == 0 else np.asarray(kappa)[:n]
        self._push(name, np.full(n, self.v), np.zeros(n), k, free)

    def gentle_bends(self, n: int, ay_max: float = 1.5) -> np.ndarray:
        """Road-like curvature: sum of slow sinusoids, |kappa| keeps a_y below ~``ay_max`` m/s^2."""
        t = np.arange(n) * DT
        k = np.zeros(n)
        for _ in range(3):
            period = self.rng.uniform(15.0, 60.0)
            k += self.rng.uniform(-1.0, 1.0) * np.sin(2 * np.pi * t / period + self.rng.uniform(0, 2 * np.pi))
        v = max(self.v, 5.0)
        return k / 3.0 * min(1.0 / 150.0, ay_max / v**2)

    # -- manoeuvres ------------------------------------------------------------------------
    def standstill(self) -> None:
        if self.v > 0.1:
            self.speed_change(0.0, self.rng.uniform(0.4, 0.9) * self.a_long, name="stop", free=False)
        self.hold(self.rng.uniform(3.0, 10.0), kappa=0.0, name="standstill", free=False)

    def accelerate(self) -> None:
        v_t = self.rng.uniform(max(self.v + 4.0, 8.0), V_MAX_PLAN_MPS) if self.v < V_MAX_PLAN_MPS - 4 else self.v
        self.speed_change(min(v_t, V_MAX_PLAN_MPS), self.rng.uniform(0.35, 1.0) * self.a_long, name="accelerate")

    def brake(self) -> None:
        v_t = self.rng.uniform(self.v_min, max(self.v_min, self.v - 4.0))
        a = self.rng.uniform(0.4, 1.0) * self.a_long * (1.4 if self.rng.random() < 0.15 else 1.0)
        self.speed_change(v_t, min(a, 0.8 * self.mu * schema.G_MPS2), name="brake")

    def cruise(self) -> None:
        dur = self.rng.uniform(4.0, 20.0)
        n = int(round(dur / DT))
        self.hold(dur, kappa=self.gentle_bends(n), name="cruise")

    def _to_speed(self, lo: float, hi: float) -> None:
        v_t = self.rng.uniform(lo, hi)
        if abs(v_t - self.v) > 1.0:
            self.speed_change(v_t, self.rng.uniform(0.4, 0.8) * self.a_long)

    def slalom(self) -> None:
        self._to_speed(7.0, 18.0)
        v = max(self.v, 5.0)
        period = self.rng.uniform(2.5, 5.0)
        cycles = int(self.rng.integers(2, 6))
        ay = self.rng.uniform(0.3, 0.8) * self.a_lat
        n = int(round(cycles * period / DT))
        t = np.arange(n) * DT
        k = (ay / v**2) * np.sin(2 * np.pi * t / period) * np.sign(self.rng.uniform(-1, 1))
        self.hold(n * DT, kappa=k, name="slalom", free=False)

    def circle(self) -> None:
        self._to_speed(6.0, 16.0)
        v = max(self.v, 4.0)
        ay = self.rng.uniform(0.3, 0.9) * self.a_lat
        kap = ay / v**2 * (1 if self.rng.random() < 0.5 else -1)
        ramp = int(round(self.rng.uniform(1.0, 2.5) / DT))
        held = int(round(self.rng.uniform(4.0, 15.0) / DT))
        up = kap * 0.5 * (1 - np.cos(np.pi * np.arange(ramp) / ramp))
        k = np.concatenate([up, np.full(held, kap), up[::-1]])
        if self.family != "lateral" and self.rng.random() < 0.4:
            # trail-brake out of the circle: speed change while turning (mixed dynamics)
            self.hold((ramp + held) * DT, kappa=k[: ramp + held], name="circle", free=False)
            a = self.rng.uniform(0.3, 0.6) * self.a_long
            self.speed_change(max(2.0, self.v * self.rng.uniform(0.4, 0.8)), a, kappa=kap, kappa_end=0.0,
                              name="brake_in_bend", free=False)
            return
        self.hold(len(k) * DT, kappa=k, name="circle", free=False)

    def highway_cruise(self) -> None:
        dur = self.rng.uniform(8.0, 30.0)
        self.hold(dur, kappa=self.gentle_bends(int(round(dur / DT)), HIGHWAY_AY_MAX_MPS2), name="cruise")

    def highway_speed(self) -> None:
        """A gentle speed change between 14 and 27 m/s in a gentle bend."""
        v_t = self.rng.uniform(14.0, 27.0)
        kap = self.gentle_bends(2, HIGHWAY_AY_MAX_MPS2)[0]
        self.speed_change(v_t, self.rng.uniform(0.15, 0.4) * self.a_long, kappa=kap, kappa_end=0.0,
                          name="speed_change")

    def highway_lane_change(self) -> None:
        self.lane_change(duration_s=(4.5, 7.0), to_speed=False)

    def lane_change(self, duration_s: tuple[float, float] = (2.5, 4.5), to_speed: bool = True) -> None:
        if to_speed:
            self._to_speed(10.0, 25.0)
        v = max(self.v, 5.0)
        dur = self.rng.uniform(*duration_s)
        width = self.rng.uniform(3.0, 4.0) * (1 if self.rng.random() < 0.5 else -1)
        n = int(round(dur / DT))
        t = np.arange(n) * DT
        # lateral offset y(t) = W (t/T - sin(2 pi t/T)/(2 pi)): kappa = y'' / v^2
        k = width * 2 * np.pi / dur**2 * np.sin(2 * np.pi * t / dur) / v**2
        k = np.clip(k, -self.a_lat / v**2, self.a_lat / v**2)
        if self.rng.random() < 0.5:  # double lane change
            k = np.concatenate([k, np.zeros(int(round(1.0 / DT))), -k])
        self.hold(len(k) * DT, kappa=k, name="lane_change", free=False)

    def tight_turn(self) -> None:
        self._to_speed(2.5, 5.0)
        v = max(self.v, 2.0)
        radius = self.rng.uniform(5.5, 12.0)
        angle = self.rng.uniform(0.5, 1.2) * np.pi
        sgn = 1 if self.rng.random() < 0.5 else -1
        ramp = int(round(1.5 / DT))
        held = max(1, int(round((angle * radius / v) / DT)))
        up = 0.5 * (1 - np.cos(np.pi * np.arange(ramp) / ramp)) * sgn / radius
        k = np.concatenate([up, np.full(held, sgn / radius), up[::-1]])
        self.hold(len(k) * DT, kappa=k, name="tight_turn", free=False)

    def bend_accelerate(self) -> None:
        self._to_speed(6.0, 12.0)
        v_t = min(V_MAX_PLAN_MPS, self.v + self.rng.uniform(4.0, 10.0))
        v_mid = 0.5 * (self.v + v_t)
        kap = self.rng.uniform(0.2, 0.5) * self.a_lat / v_mid**2 * (1 if self.rng.random() < 0.5 else -1)
        self.speed_change(v_t, self.rng.uniform(0.3, 0.7) * self.a_long, kappa=kap, name="bend_accelerate",
                          free=False)


_CATALOGUE = {
    "longitudinal": {"accelerate": 3, "brake": 3, "cruise": 3, "standstill": 1, "lane_change": 0.5},
    "lateral": {"slalom": 3, "circle": 3, "lane_change": 2, "tight_turn": 1.5, "cruise": 1, "standstill": 0.5},
    "mixed": {"accelerate": 2, "brake": 2, "cruise": 2, "standstill": 1, "slalom": 1.5, "circle": 1.5,
              "lane_change": 1.5, "tight_turn": 1, "bend_accelerate": 1.5},
}
_CATALOGUE["snow"] = _CATALOGUE["mixed"]
_CATALOGUE["highway"] = {"highway_cruise": 4, "highway_speed": 1.5, "highway_lane_change": 1}


def plan_drive(n_samples: int, mu: float, family: str, rng: np.random.Generator,
               params: VehicleParams | None = None, standstill: bool = True) -> DriverPlan:
    """A driver plan of ``n_samples`` 50 Hz samples for ``family`` at friction ``mu``.

    ``standstill=False``: the driver never stops (starts at speed, no ``standstill`` manoeuvre, brakes
    end at :data:`NO_STOP_V_MIN_MPS` or faster); the default plan is unchanged by the option.
    """
    if family not in FAMILIES:
        raise ValueError(f"unknown family {family!r}; one of {', '.join(FAMILIES)}")
    p = params or VehicleParams()
    b = _Builder(rng, mu, family, v_min=0.0 if standstill else NO_STOP_V_MIN_MPS)
    cat = {k: w for k, w in _CATALOGUE[family].items() if standstill or k != "standstill"}
    names = list(cat)
    weights = np.array([cat[k] for k in names], dtype=float)
    weights /= weights.sum()
    if family == "highway":
        b.v = v0 = float(rng.uniform(*HIGHWAY_V0_MPS))
    elif not standstill:
        b.v = v0 = float(rng.uniform(*NO_STOP_V0_MPS))
    else:
        v0 = 0.0
        b.hold(rng.uniform(2.0, 5.0), name="standstill", free=False)
        b.accelerate()
    while b.n < n_samples:
        choice = names[int(rng.choice(len(names), p=weights))]
        if choice == "brake" and b.v < 6.0:
            choice = "accelerate"
        if choice == "accelerate" and b.v > V_MAX_PLAN_MPS - 5.0:
            choice = "brake"
        if choice in ("cruise", "lane_change", "slalom") and b.v < 4.0:
            b.accelerate()
        getattr(b, choice)()
    v_ref = np.concatenate(b.v_parts)[:n_samples]
    accel = np.concatenate(b.a_parts)[:n_samples]
    kappa = np.concatenate(b.k_parts)[:n_samples]
    free = np.concatenate(b.f_parts)[:n_samples]
    # driver's small corrections: low-pass filtered noise on the curvature
    noise = _lowpass(rng.normal(0.0, 1.0, n_samples), tau_s=0.8) * 2.5e-4 * (0.5 if family == "snow" else 1.0)
    kappa = kappa + noise
    # steering: kinematic angle + understeer gradient (from the plan's lateral acceleration)
    L = p.wheelbase_m
    k_us = p.mass_kg * (p.lr_m / p.cornering_stiffness_front_npr - p.lf_m / p.cornering_stiffness_rear_npr) / (2 * L)
    ay_plan = kappa * v_ref**2
    delta = np.arctan(L * kappa) + k_us * ay_plan / max(mu, 0.2) ** 0.5
    delta = np.clip(delta, -p.max_wheel_angle_rad, p.max_wheel_angle_rad)
    delta = _rate_limit(_lowpass(delta, tau_s=0.12), max_rate=np.radians(500.0) / p.steering_ratio * DT)
    return DriverPlan(v_ref=v_ref, accel_ff=accel, kappa=kappa, delta_cmd=delta, free_steer=free,
                      manoeuvre=[lab for lab in b.labels if lab[0] < n_samples], v0_mps=v0)


def _lowpass(x: np.ndarray, tau_s: float) -> np.ndarray:
    """First-order low-pass at 50 Hz (zero initial state relative to x[0])."""
    alpha = DT / (tau_s + DT)
    y = np.empty_like(x)
    acc = float(x[0])
    for i, v in enumerate(x.tolist()):
        acc += alpha * (v - acc)
        y[i] = acc
    return y


def _rate_limit(x: np.ndarray, max_rate: float) -> np.ndarray:
    """Limit the per-sample change of x to ``max_rate``."""
    y = np.empty_like(x)
    acc = float(x[0])
    for i, v in enumerate(x.tolist()):
        acc += max(-max_rate, min(max_rate, v - acc))
        y[i] = acc
    return y
