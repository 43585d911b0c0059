"""The simulated fleet: named cars, each a vehicle parameter set and a sensor profile.

A benchmark with one car cannot say whether a model works on anyone else's. The cars below
span the ranges of real passenger cars (curb mass 1.1-2.1 t, wheelbase 2.45-3.0 m, track
1.45-1.62 m, COG height 0.5-0.75 m, steering ratio 13.7-17.5, FWD/RWD/AWD) and of their
CAN sensors (yaw-rate resolution 1.28 deg/s in ReV-StED, 0.244 deg/s on a Toyota RAV4,
0.01 deg/s on VW MQB and Hyundai, from the opendbc DBCs; speedometer factor 1-6 % over, as
UN R39 / 75/443/EEC allow). Yaw inertia follows ``Iz ~ m (a b)`` (k^2 = lf lr, a common
rule for passenger cars; the reference car has 0.87 of it); cornering stiffnesses scale with
the wheel load (the reference car's 12 and 18 per rad front and rear); brake gain with mass
(same deceleration per bar of pressure).

``reference`` is the single car the simulator had before (ReV-StED-like sensors); its
drives keep the onboard profile that ``benchmarks/sensor_profile.py`` checks against the real
sample. Names and parameters are recorded in every dataset manifest.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

from prml2_edge import schema
from prml2_edge.data.simulate.sensors import SensorProfile
from prml2_edge.data.simulate.vehicle import VehicleParams
from prml2_edge.errors import ConfigError

_DEG = schema.DEG_TO_RAD
_KMH = schema.KMH_TO_MPS
_G = schema.G_MPS2


@dataclass(frozen=True)
class Car:
    """One simulated car: what it is, its dynamics and its sensors."""

    name: str
    description: str
    params: VehicleParams
    sensors: SensorProfile = field(default_factory=SensorProfile)

    def as_dict(self) -> dict:
        return {"name": self.name, "description": self.description, "params": asdict(self.params),
                "sensors": {**asdict(self.sensors), "steps": dict(self.sensors.steps)}}

    def filter_settings(self) -> dict:
        """What a user tells the runtime about this car (:class:`~prml2_edge.runtime.localizer_config.LocalizerConfig`
        fields): its driven axle and steering ratio."""
        axle = {"fwd": "front", "rwd": "rear", "awd": "all"}[self.params.drivetrain]
        return {"driven_axle": axle, "steering_ratio": float(self.params.steering_ratio)}


def _car(name: str, description: str, mass: float, lf: float, lr: float, track: float, cog: float, ratio: float,
         drivetrain: str = "fwd", stiffness_per_load: tuple[float, float] = (12.0, 18.0),
         sensors: SensorProfile | None = None, **extra) -> Car:
    """A car from its headline numbers: yaw inertia, tyre stiffnesses and brake gain follow from them."""
    axle_f, axle_r = mass * _G * lr / (lf + lr), mass * _G * lf / (lf + lr)
    params = VehicleParams(
        mass_kg=mass, yaw_inertia_kgm2=round(mass * lf * lr * 0.9, -1), lf_m=lf, lr_m=lr, track_m=track,
        cog_height_m=cog, steering_ratio=ratio,
        cornering_stiffness_front_npr=round(stiffness_per_load[0] * axle_f / 2, -2),
        cornering_stiffness_rear_npr=round(stiffness_per_load[1] * axle_r / 2, -2),
        brake_gain_n_per_bar=round(160.0 * mass / 1550.0, 1), drivetrain=drivetrain, **extra)
    return Car(name, description, params, sensors or SensorProfile())


CARS: dict[str, Car] = {c.name: c for c in (
    Car("reference", "C/D-segment FWD sedan with ReV-StED-like sensors (the simulator's original car)",
        VehicleParams()),
    _car("compact_fwd", "C-segment FWD hatchback (Golf-class), MQB-like sensors: yaw 0.01 deg/s, "
         "lateral acceleration 0.01 g", 1350.0, 1.03, 1.60, 1.54, 0.52, 14.1,
         sensors=SensorProfile(steps=(("yaw_rate_radps", 0.01 * _DEG), ("lat_accel_mps2", 0.01 * _G),
                                      ("steering_wheel_angle_rad", 0.1 * _DEG)),
                               speedo_factor=(1.01, 1.04))),
    _car("city_fwd", "B-segment FWD city car, coarse sensors: yaw 0.5 deg/s, steering 1 deg",
         1120.0, 0.95, 1.47, 1.46, 0.50, 15.8, stiffness_per_load=(11.0, 16.5),
         sensors=SensorProfile(steps=(("yaw_rate_radps", 0.5 * _DEG), ("steering_wheel_angle_rad", 1.0 * _DEG)),
                               speedo_factor=(1.03, 1.07), wheel_radius_sigma=0.006)),
    _car("rwd_sedan", "D-segment RWD sedan (3-series-class), yaw 0.1 deg/s", 1600.0, 1.38, 1.47, 1.58, 0.50, 15.0,
         drivetrain="rwd", brake_front_share=0.62,
         sensors=SensorProfile(steps=(("yaw_rate_radps", 0.1 * _DEG),), speedo_factor=(1.02, 1.05))),
    _car("van_fwd", "large FWD MPV / light van, Hyundai-like sensors: yaw 0.01 deg/s, steering 0.1 deg",
         2100.0, 1.32, 1.68, 1.62, 0.75, 17.5, stiffness_per_load=(10.5, 15.5), front_roll_share=0.6,
         sensors=SensorProfile(steps=(("yaw_rate_radps", 0.01 * _DEG), ("lat_accel_mps2", 0.01),
                                      ("steering_wheel_angle_rad", 0.1 * _DEG)),
                               brake_baseline_bar=(0.0, 0.8))),
    _car("suv_awd", "compact AWD SUV (RAV4-class), Toyota-like sensors: yaw 0.244 deg/s, lateral acceleration "
         "0.036 m/s^2, steering 0.1 deg, wheels 0.01 km/h", 1680.0, 1.16, 1.50, 1.61, 0.68, 13.7,
         drivetrain="awd", stiffness_per_load=(11.5, 17.0),
         sensors=SensorProfile(steps=(("yaw_rate_radps", 0.244 * _DEG), ("lat_accel_mps2", 0.03589),
                                      ("steering_wheel_angle_rad", 0.1 * _DEG),
                                      *((n, 0.01 * _KMH) for n in schema.WHEEL_SPEED_NAMES)),
                               speedo_factor=(1.02, 1.05))),
)}


def get_car(name: str) -> Car:
    """The fleet car called ``name`` (a one-line error listing the fleet otherwise)."""
    if name not in CARS:
        raise ConfigError(f"unknown vehicle {name!r}; the simulated fleet has {', '.join(CARS)}")
    return CARS[name]


def with_params(car: Car, **params) -> Car:
    """A copy of ``car`` with some vehicle parameters changed (sweeps, tests)."""
    return replace(car, params=replace(car.params, **params))
