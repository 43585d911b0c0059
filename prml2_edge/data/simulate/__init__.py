"""Simulated drives: driver plan -> single-track vehicle -> onboard sensors -> :class:`Drive`.

``simulate_drive(minutes, mu, seed, family)`` is deterministic for its arguments. The
result has the onboard signals as the car reports them (quantised, held, offset,
noisy) and the exact ground truth (z at the COG and the planar pose) the INS would give.
"""

from __future__ import annotations

import numpy as np

from prml2_edge import schema
from prml2_edge.data.revsted import Drive
from prml2_edge.data.simulate.driver import FAMILIES, DriverPlan, plan_drive
from prml2_edge.data.simulate.fleet import CARS, Car, get_car
from prml2_edge.data.simulate.sensors import SensorErrors, SensorProfile, onboard_signals
from prml2_edge.data.simulate.vehicle import VehicleParams, VehicleTrace, simulate_vehicle
from prml2_edge.errors import ConfigError
from prml2_edge.progress import Progress

__all__ = ["CARS", "FAMILIES", "Car", "DriverPlan", "SensorErrors", "SensorProfile", "VehicleParams", "VehicleTrace",
           "get_car", "simulate_drive"]

SNOW_MU_RANGE = (0.2, 0.5)
HIGHWAY_HOME_RADIUS_M = 3000.0  # a highway leaves the test track's 700 m; turn back only far out


def simulate_drive(minutes: float, mu: float, seed: int, family: str = "mixed", name: str | None = None,
                   progress: bool = False, sensor_errors: dict | None = None,
                   vehicle: str | Car = "reference", standstill: bool = True) -> Drive:
    """Simulate one drive and return it with ground truth.

    Parameters
    ----------
    minutes : float
        Duration [min]; the drive has ``round(minutes * 60 * 50)`` samples at 50 Hz.
    mu : float
        Friction coefficient (0 < mu <= 1.2). Family ``snow`` expects 0.2-0.5.
    seed : int
        Seeds the driver, the vehicle's start heading and the sensor errors.
    family : str
        ``longitudinal``, ``lateral``, ``mixed``, ``snow`` or ``highway`` (starts at speed, never stops).
    name : str, optional
        Drive name (default ``sim_<family>_s<seed>``).
    progress : bool
        Show a progress bar on stderr.
    sensor_errors : dict, optional
        Fields of :class:`SensorErrors` to set instead of drawing them (known offsets for
        calibration tests), e.g. ``{"yaw_offset_radps": -0.007}``; ``wheel_radius_error`` may be one
        number (all four wheels).
    vehicle : str or Car
        A car of the simulated fleet (:data:`CARS`; default ``reference``, the ReV-StED-like car).
    standstill : bool
        False: the driver never stops (starts at speed, no standstill manoeuvre, brakes end at 3 m/s
        or faster; :func:`~prml2_edge.data.simulate.driver.plan_drive`), so no standstill calibrates a
        gyro offset. True (default): the family's plan as it always was, bit for bit.

    Returns
    -------
    Drive
        ``t_s`` from 0 s; ``meta`` records family, mu, seed, snow, the sensor errors and
        the manoeuvre sequence (and ``standstill: false`` when the driver never stopped).
    """
    if family not in FAMILIES:
        raise ConfigError(f"unknown family {family!r}; choose one of {', '.join(FAMILIES)}")
    if not (0.05 < mu <= 1.2):
        raise ConfigError(f"friction coefficient mu={mu} outside (0.05, 1.2]; dry asphalt ~1.0, snow 0.2-0.5")
    if family == "snow" and not (SNOW_MU_RANGE[0] - 1e-9 <= mu <= SNOW_MU_RANGE[1] + 1e-9):
        raise ConfigError(f"family 'snow' needs mu in {SNOW_MU_RANGE[0]}-{SNOW_MU_RANGE[1]}, got {mu}")
    n = int(round(minutes * 60.0 * schema.SAMPLE_RATE_HZ))
    if n < 2:
        raise ConfigError(f"--minutes {minutes} gives fewer than 2 samples")
    rng = np.random.default_rng([int(seed), 0x50524D4C])  # "PRML"
    car = vehicle if isinstance(vehicle, Car) else get_car(vehicle)
    params = car.params
    plan = plan_drive(n, mu, family, rng, params, standstill=standstill)
    psi0 = float(rng.uniform(-np.pi, np.pi))
    bar = Progress(n, desc=f"simulate {name or family}", unit="samples", enabled=None if progress else False)
    try:
        trace = simulate_vehicle(params, mu, plan.delta_cmd, plan.accel_ff, plan.v_ref, psi0_rad=psi0,
                                 free_steer=plan.free_steer, progress_cb=bar.update, v0_mps=plan.v0_mps,
                                 home_radius_m=HIGHWAY_HOME_RADIUS_M if family == "highway" else 700.0)
    finally:
        bar.close()
    errors = SensorErrors.draw(rng, car.sensors)
    if sensor_errors:
        errors = errors.with_overrides(sensor_errors)
    onboard, errors = onboard_signals(trace, params, rng, errors, car.sensors)
    z_gt = np.stack([trace.v_x, trace.v_y, trace.a_x, trace.a_y, trace.r], axis=1)
    pose = np.stack([trace.x, trace.y, trace.psi], axis=1)
    meta = {
        "source": "prml2 simulator",
        "family": family,
        "vehicle": car.name,
        "mu": float(mu),
        "seed": int(seed),
        "snow": family == "snow" or mu <= schema.LOW_MU_THRESHOLD,
        "minutes": float(minutes),
        "sensor_errors": errors.as_dict(),
        "manoeuvres": [[int(k), lab] for k, lab in plan.manoeuvre],
    }
    if not standstill:
        meta["standstill"] = False
    return Drive(name=name or f"sim_{family}_s{seed}", path=None, t_s=np.arange(n) * schema.DT_S,
                 onboard=onboard, z_gt=z_gt, pose_gt=pose, meta=meta, repairs={})
