"""Onboard sensor model: the 9 signals of o_t as a production car's ECUs report them.

Parameters come from the real onboard profile measured on ``OBD_Sample.csv``
(method.md "Onboard sensor profile"; ``benchmarks/sensor_profile.py`` reproduces it); a car
of the simulated fleet (:mod:`prml2_edge.data.simulate.fleet`) may change them through its
:class:`SensorProfile` (resolutions of its own ECUs, speedometer factor):

* quantisation steps: :data:`schema.SIGNALS` ``revsted_step`` (0.05 km/h wheel speeds,
  0.0625 km/h speedometer, 0.481 deg steering, 1.28 deg/s yaw rate, 0.075 m/s^2 lateral
  acceleration, 0.182 bar brake pressure);
* sample-and-hold: each signal is refreshed at its bus rate (schema ``rate_hz``; the
  25 Hz speedometer holds every value for two 50 Hz samples);
* speedometer: a low-passed front-axle speed times 1.02-1.06 plus 0.1-0.5 km/h (the
  sample reads 5 % above the wheel speeds; 75/443/EEC: never below true speed);
* per-drive offsets: yaw rate (sigma 0.05 deg/s: what the ESC's own offset compensation
  leaves, see :class:`SensorProfile`), lateral acceleration (0.12 m/s^2), steering (1.5 deg),
  brake pressure baseline 0.2-1.5 bar (the sample idles at ~1 bar);
* per-wheel rolling-radius errors (sigma 0.4 %) and longitudinal slip from the tyre
  forces (magic-formula inverse), wheel speeds from the axle kinematics (inner and
  outer wheels differ in turns; front wheels steer);
* white noise and a short sensor lag per signal; wheel speeds below 1 km/h read 0
  (ABS sensors lose the signal near standstill).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from prml2_edge import schema
from prml2_edge.data.simulate.vehicle import VehicleParams, VehicleTrace
from prml2_edge.errors import ConfigError

_IDX = {s.name: s.index for s in schema.SIGNALS}
_KMH = schema.KMH_TO_MPS
_DEG = schema.DEG_TO_RAD


@dataclass(frozen=True)
class SensorProfile:
    """What a car's sensors are like: resolutions and the spread of the per-drive errors.

    The defaults are the ReV-StED reference car's (``OBD_Sample.csv``). ``steps`` overrides the
    quantisation step of some signals [SI] (schema ``revsted_step`` otherwise): production ECUs
    differ (yaw rate 1.28 deg/s in ReV-StED, 0.244 deg/s on a Toyota RAV4, 0.01 deg/s on VW MQB
    and Hyundai; opendbc DBCs).

    ``yaw_offset_dps`` is the spread of the yaw-rate offset left on the CAN value. ESC units
    compensate their yaw sensor's offset themselves (at standstill and when driving straight),
    so what reaches the bus is a few hundredths of a deg/s. With 0.25 deg/s (this simulator
    before) the offset hid under the 1.28 deg/s quantisation at standstill, no standstill
    calibration could see it, and the OSD baseline drifted six times more than on real drives
    (``benchmarks/sim_realism.py`` measures each choice).
    """

    steps: tuple[tuple[str, float], ...] = ()  # (canonical signal name, step [SI])
    yaw_offset_dps: float = 0.05
    speedo_factor: tuple[float, float] = (1.02, 1.06)
    wheel_radius_sigma: float = 0.004
    brake_baseline_bar: tuple[float, float] = (0.2, 1.5)
    yaw_scale_sigma: float = 0.01  # yaw-rate gain error (MEMS scale-factor tolerance)
    yaw_drift_dps: float = 0.02  # offset instability: Gauss-Markov sigma [deg/s] ...
    yaw_drift_tau_s: float = 200.0  # ... and correlation time [s] (temperature, ageing)

    def step(self, sig) -> float:
        """Quantisation step of canonical signal ``sig`` (a ``schema.Signal``) [SI]."""
        return dict(self.steps).get(sig.name, sig.revsted_step)


@dataclass(frozen=True)
class SensorErrors:
    """Per-drive sensor imperfections (drawn once per drive)."""

    speedo_factor: float  # speedometer gain over the front-axle speed
    speedo_offset_mps: float
    yaw_offset_radps: float
    lat_offset_mps2: float
    steer_offset_rad: float
    brake_baseline_bar: float
    wheel_radius_error: tuple[float, float, float, float]  # fl, fr, rl, rr, relative
    hold_phase: int  # phase of the speedometer's 25 Hz refresh
    yaw_scale_error: float = 0.0  # relative gain error of the yaw-rate sensor

    @staticmethod
    def draw(rng: np.random.Generator, profile: SensorProfile | None = None) -> SensorErrors:
        p = profile or SensorProfile()
        return SensorErrors(
            speedo_factor=float(rng.uniform(*p.speedo_factor)),
            speedo_offset_mps=float(rng.uniform(0.1, 0.5)) * _KMH,
            yaw_offset_radps=float(rng.normal(0.0, p.yaw_offset_dps)) * _DEG,
            lat_offset_mps2=float(rng.normal(0.0, 0.12)),
            steer_offset_rad=float(rng.normal(0.0, 1.5)) * _DEG,
            brake_baseline_bar=float(rng.uniform(*p.brake_baseline_bar)),
            wheel_radius_error=tuple(float(e) for e in rng.normal(0.0, p.wheel_radius_sigma, 4)),
            hold_phase=int(rng.integers(0, 2)),
            yaw_scale_error=float(rng.normal(0.0, p.yaw_scale_sigma)),
        )

    def as_dict(self) -> dict:
        return asdict(self)

    def with_overrides(self, values: dict) -> SensorErrors:
        """A copy with some fields set (``wheel_radius_error`` may be one number for all four wheels)."""
        from dataclasses import fields, replace

        known = {f.name for f in fields(self)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ConfigError(f"unknown sensor error {unknown[0]!r} (known: {', '.join(sorted(known))})")
        values = dict(values)
        wre = values.get("wheel_radius_error")
        if wre is not None and not isinstance(wre, tuple | list):
            values["wheel_radius_error"] = (float(wre),) * 4
        return replace(self, **values)


# White noise (1 sigma, SI) and first-order lag [s] per canonical signal.
NOISE_SI = {
    "speedometer_mps": 0.02 * _KMH,
    "steering_wheel_angle_rad": 0.15 * _DEG,
    "yaw_rate_radps": 0.06 * _DEG,
    "lat_accel_mps2": 0.03,
    "brake_pressure_bar": 0.05,
    "wheel_speed_fl_mps": 0.02 * _KMH,
    "wheel_speed_fr_mps": 0.02 * _KMH,
    "wheel_speed_rl_mps": 0.03 * _KMH,
    "wheel_speed_rr_mps": 0.03 * _KMH,
}
LAG_S = {
    "speedometer_mps": 0.25,
    "steering_wheel_angle_rad": 0.0,
    "yaw_rate_radps": 0.04,
    "lat_accel_mps2": 0.04,
    "brake_pressure_bar": 0.06,
}
WHEEL_DROPOUT_MPS = 1.0 * _KMH


def lowpass(x: np.ndarray, tau_s: float, dt_s: float = schema.DT_S) -> np.ndarray:
    """First-order low-pass along axis 0 (exact discretisation), initialised at x[0]."""
    if tau_s <= 0.0:
        return x.copy()
    a = math.exp(-dt_s / tau_s)
    b = 1.0 - a
    vals = x.tolist()
    acc = vals[0]
    out = []
    for v in vals:  # a scalar recursion (lfilter would need scipy); plain floats keep it fast
        acc = a * acc + b * v
        out.append(acc)
    return np.asarray(out, dtype=x.dtype)


def gauss_markov(rng: np.random.Generator, n: int, sigma: float, tau_s: float, dt_s: float = schema.DT_S) -> np.ndarray:
    """(n,) first-order Gauss-Markov process of stationary std ``sigma``, starting at 0 (calibrated)."""
    if sigma <= 0.0 or n == 0:
        return np.zeros(n)
    a = math.exp(-dt_s / tau_s)
    w = rng.normal(0.0, sigma * math.sqrt(1.0 - a * a), n)
    w[0] = 0.0
    out = np.empty(n)
    acc = 0.0
    for i, v in enumerate(w.tolist()):
        acc = a * acc + v
        out[i] = acc
    return out


def quantise(x: np.ndarray, step: float) -> np.ndarray:
    """Round to the nearest multiple of ``step`` (same unit as x)."""
    return np.round(x / step) * step


def sample_and_hold(x: np.ndarray, period: int, phase: int = 0) -> np.ndarray:
    """Hold every ``period``-th sample (starting at ``phase``) until the next refresh."""
    if period <= 1:
        return x
    idx = np.arange(len(x))
    src = np.maximum(((idx - phase) // period) * period + phase, 0)
    return x[src]


def _tyre_slip(fx_n: np.ndarray, fz_n: np.ndarray, mu: float, params: VehicleParams) -> np.ndarray:
    """Longitudinal slip ratio from the magic-formula inverse of Fx / (mu Fz)."""
    frac = np.clip(fx_n / (mu * np.maximum(fz_n, 1.0)), -0.97, 0.97)
    b = params.mf_b_long * (0.55 + 0.45 * min(mu, 1.0))  # snow: softer -> more slip for the same force share
    return np.tan(np.arcsin(frac) / params.mf_c_long) / b


def true_wheel_speeds(trace: VehicleTrace, params: VehicleParams) -> np.ndarray:
    """Wheel circumferential speeds [m/s] (N, 4) fl, fr, rl, rr, including slip; >= 0."""
    half = 0.5 * params.track_m
    cd, sd = np.cos(trace.delta), np.sin(trace.delta)
    vy_f = trace.v_y + params.lf_m * trace.r
    v_fl = (trace.v_x - half * trace.r) * cd + vy_f * sd
    v_fr = (trace.v_x + half * trace.r) * cd + vy_f * sd
    v_rl = trace.v_x - half * trace.r
    v_rr = trace.v_x + half * trace.r
    ground = np.stack([v_fl, v_fr, v_rl, v_rr], axis=1)
    fx = np.stack([trace.fx_front_n, trace.fx_front_n, trace.fx_rear_n, trace.fx_rear_n], axis=1) * 0.5
    slip = _tyre_slip(fx, trace.fz_n, trace.mu, params)
    moving = (trace.v_x > 0.05)[:, None]
    return np.where(moving, np.maximum(ground * (1.0 + slip), 0.0), 0.0)


def onboard_signals(trace: VehicleTrace, params: VehicleParams, rng: np.random.Generator,
                    errors: SensorErrors | None = None, profile: SensorProfile | None = None
                    ) -> tuple[np.ndarray, SensorErrors]:
    """The onboard vector o_t (N, 9), canonical order, SI, as the car's sensors report it.

    Returns the signals and the drawn per-drive :class:`SensorErrors`.
    """
    profile = profile or SensorProfile()
    errors = errors or SensorErrors.draw(rng, profile)
    n = len(trace.v_x)
    clean = np.zeros((n, schema.NUM_SIGNALS))
    wheels = true_wheel_speeds(trace, params)
    measured_wheels = wheels * (1.0 + np.asarray(errors.wheel_radius_error))[None, :]
    for k, name in enumerate(schema.WHEEL_SPEED_NAMES):
        clean[:, _IDX[name]] = measured_wheels[:, k]
    front = 0.5 * (wheels[:, 0] + wheels[:, 1])
    speedo = np.where(front > 0.05, front * errors.speedo_factor + errors.speedo_offset_mps, 0.0)
    clean[:, _IDX["speedometer_mps"]] = speedo
    clean[:, _IDX["steering_wheel_angle_rad"]] = trace.delta * params.steering_ratio + errors.steer_offset_rad
    drift = gauss_markov(rng, n, profile.yaw_drift_dps * _DEG, profile.yaw_drift_tau_s)
    clean[:, _IDX["yaw_rate_radps"]] = trace.r * (1.0 + errors.yaw_scale_error) + errors.yaw_offset_radps + drift
    clean[:, _IDX["lat_accel_mps2"]] = trace.a_y + errors.lat_offset_mps2
    clean[:, _IDX["brake_pressure_bar"]] = trace.brake_force_n / params.brake_gain_n_per_bar + errors.brake_baseline_bar

    out = np.empty_like(clean)
    for sig in schema.SIGNALS:
        x = lowpass(clean[:, sig.index], LAG_S.get(sig.name, 0.0))
        x = x + rng.normal(0.0, NOISE_SI[sig.name], n)
        if sig.name in schema.WHEEL_SPEED_NAMES or sig.name == "speedometer_mps":
            x = np.where(clean[:, sig.index] < WHEEL_DROPOUT_MPS, 0.0, np.maximum(x, 0.0))
        period = max(1, int(round(schema.SAMPLE_RATE_HZ / sig.rate_hz)))
        x = sample_and_hold(x, period, errors.hold_phase if period > 1 else 0)
        out[:, sig.index] = np.clip(quantise(x, profile.step(sig)), sig.min, sig.max)
    return out, errors
