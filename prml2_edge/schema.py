"""Single source of truth for signals, dynamic states and the EKF state layout.

Everything that names, orders or scales a signal (DBC signal maps, the ReV-StED
loader, the simulator, datasets, the model's input order, ONNX metadata) is checked
against this module.

Units are SI throughout, except brake pressure, which is in bar (the unit production
ESP units put on the bus). Frames (``../shared/docs/method.md``):

* vehicle frame: x forward, y left, z up; yaw rate counter-clockwise positive;
* world frame (EKF): x east, y north, heading ``psi`` counter-clockwise from east [rad].
  ReV-StED's ``ins_yaw`` is clockwise from north [deg]: ``psi = pi/2 - radians(ins_yaw)``.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass

import numpy as np

SAMPLE_RATE_HZ = 50.0  # onboard vector o_t rate
DT_S = 1.0 / SAMPLE_RATE_HZ  # 0.02 s
G_MPS2 = 9.80665  # standard gravity
KMH_TO_MPS = 1.0 / 3.6
DEG_TO_RAD = math.pi / 180.0
RAD_TO_DEG = 180.0 / math.pi

# Window geometry (paper Sec. III-B; method.md "Model").
WINDOW_LEN = 250  # L: 5 s at 50 Hz
ENCODER_LEN = 150  # H
DECODER_LEN = WINDOW_LEN - ENCODER_LEN  # L - H = 100


@dataclass(frozen=True)
class Signal:
    """One onboard signal of o_t.

    ``min``/``max`` are the physical range [unit] beyond which a decoded value is
    rejected as implausible. ``revsted_scale`` converts the ReV-StED CSV column
    (``revsted_unit``) to ``unit`` (negative where the column's sign convention differs);
    ``revsted_step`` is the quantisation step measured on ``OBD_Sample.csv`` [unit].
    """

    index: int
    name: str
    symbol: str
    description: str
    unit: str
    rate_hz: float
    min: float
    max: float
    revsted_column: str
    revsted_unit: str
    revsted_scale: float
    revsted_step: float


def _sig(index, name, symbol, description, unit, rate_hz, lo, hi, col, col_unit, scale, step):
    return Signal(index, name, symbol, description, unit, rate_hz, lo, hi, col, col_unit, scale, step)


# Canonical order of o_t (paper Eq. obd_data).
SIGNALS: tuple[Signal, ...] = (
    _sig(0, "speedometer_mps", "v_s", "speedometer reading", "m/s", 25.0,
         0.0, 84.0, "speedo_obd", "km/h", KMH_TO_MPS, 0.0625 * KMH_TO_MPS),
    _sig(1, "steering_wheel_angle_rad", "delta_sw", "steering wheel angle, left positive", "rad", 100.0,
         -14.0, 14.0, "SW_pos_obd", "deg", DEG_TO_RAD, 0.481 * DEG_TO_RAD),
    _sig(2, "yaw_rate_radps", "psi_dot", "yaw rate, counter-clockwise positive", "rad/s", 50.0,
         -2.5, 2.5, "Yawrate_obd", "deg/s", DEG_TO_RAD, 1.28 * DEG_TO_RAD),
    # LatAcc_obd is right-positive: in OBD_Sample.csv it reads +2.2 m/s^2 in a right turn
    # (yaw rate -36 deg/s, steering -454 deg, right wheels slower), hence the scale -1.
    _sig(3, "lat_accel_mps2", "a_y", "lateral acceleration, left positive", "m/s^2", 50.0,
         -15.0, 15.0, "LatAcc_obd", "m/s^2", -1.0, 0.075),
    _sig(4, "brake_pressure_bar", "p_br", "brake master cylinder pressure", "bar", 50.0,
         -10.0, 250.0, "brake_pressure_obd", "bar", 1.0, 0.182),
    _sig(5, "wheel_speed_fl_mps", "v_fl", "wheel speed front left", "m/s", 100.0,
         0.0, 84.0, "VelFL_obd", "km/h", KMH_TO_MPS, 0.05 * KMH_TO_MPS),
    _sig(6, "wheel_speed_fr_mps", "v_fr", "wheel speed front right", "m/s", 100.0,
         0.0, 84.0, "VelFR_obd", "km/h", KMH_TO_MPS, 0.05 * KMH_TO_MPS),
    _sig(7, "wheel_speed_rl_mps", "v_rl", "wheel speed rear left", "m/s", 100.0,
         0.0, 84.0, "VelRL_obd", "km/h", KMH_TO_MPS, 0.05 * KMH_TO_MPS),
    _sig(8, "wheel_speed_rr_mps", "v_rr", "wheel speed rear right", "m/s", 100.0,
         0.0, 84.0, "VelRR_obd", "km/h", KMH_TO_MPS, 0.05 * KMH_TO_MPS),
)
SIGNAL_NAMES: tuple[str, ...] = tuple(s.name for s in SIGNALS)
SIGNAL_BY_NAME: dict[str, Signal] = {s.name: s for s in SIGNALS}
NUM_SIGNALS = len(SIGNALS)  # m = 9
WHEEL_SPEED_NAMES = SIGNAL_NAMES[5:9]
WHEEL_SPEED_INDICES: tuple[int, ...] = tuple(SIGNAL_BY_NAME[n].index for n in WHEEL_SPEED_NAMES)  # fl, fr, rl, rr

# ReV-StED column aliases: the public sample names the yaw rate ``yaw_rate``.
REVSTED_ALIASES: dict[str, tuple[str, ...]] = {"Yawrate_obd": ("yaw_rate",)}


@dataclass(frozen=True)
class DynState:
    """One component of the dynamic state z_t at the centre of gravity, vehicle frame."""

    index: int
    name: str
    symbol: str
    unit: str


# z_t = [v_x, v_y, a_x, a_y, omega_z] (method.md "Signals and states").
STATES: tuple[DynState, ...] = (
    DynState(0, "v_x_mps", "v_x", "m/s"),
    DynState(1, "v_y_mps", "v_y", "m/s"),
    DynState(2, "a_x_mps2", "a_x", "m/s^2"),
    DynState(3, "a_y_mps2", "a_y", "m/s^2"),
    DynState(4, "omega_z_radps", "omega_z", "rad/s"),
)
STATE_NAMES: tuple[str, ...] = tuple(s.name for s in STATES)
NUM_STATES = len(STATES)  # 5


class Z:
    """Index of each component in z_t."""

    V_X = 0  # m/s
    V_Y = 1  # m/s
    A_X = 2  # m/s^2
    A_Y = 3  # m/s^2
    OMEGA_Z = 4  # rad/s
    VEL = slice(0, 2)  # m/s
    ACC = slice(2, 4)  # m/s^2


class EkfState:
    """Planar EKF state x = [p_x, p_y, psi, omega_z, v_x, v_y, a_x, a_y] as named slices.

    The paper's 15-state model restricted to the plane (method.md).
    """

    POS = slice(0, 2)  # m, world frame (x east, y north)
    POS_X = slice(0, 1)  # m
    POS_Y = slice(1, 2)  # m
    YAW = slice(2, 3)  # rad, counter-clockwise from east
    OMEGA_Z = slice(3, 4)  # rad/s
    VEL = slice(4, 6)  # m/s, vehicle frame
    ACC = slice(6, 8)  # m/s^2, vehicle frame
    DIM = 8
    NAMES = ("p_x_m", "p_y_m", "psi_rad", "omega_z_radps", "v_x_mps", "v_y_mps", "a_x_mps2", "a_y_mps2")


class CalState:
    """Slow error states appended to :class:`EkfState` when the filter self-calibrates.

    Full state with calibration: ``[EkfState (8) | yaw-rate offset, wheel scale, model omega bias]``.
    The offset and the scale are random walks, the model bias a first-order Gauss-Markov process;
    what makes them observable (standstill, GNSS, the raw cues) is in :mod:`prml2_edge.runtime.filter`.
    Measurement models (:mod:`prml2_edge.ekf.numpy_ekf`):

    * ``YAW_RATE_OFFSET`` [rad/s]: CAN yaw rate ``= omega_z + offset``; the model's
      ``omega_z = omega_z + offset + model bias`` (it reads the same sensor);
    * ``WHEEL_SCALE`` [1]: rear-axle wheel speed ``(v_rl + v_rr) / 2 = (1 + scale) v_x`` and the model's
      ``v_x = (1 + scale) v_x`` (rolling-radius error; 0.01: the wheels read 1 % fast); learned from
      GNSS distance only;
    * ``MODEL_OMEGA_BIAS`` [rad/s]: the model's slow omega_z error (a bias over its 5 s window).
    """

    YAW_RATE_OFFSET = slice(8, 9)
    WHEEL_SCALE = slice(9, 10)
    MODEL_OMEGA_BIAS = slice(10, 11)
    ALL = slice(8, 11)
    DIM = 3
    NAMES = ("yaw_rate_offset_radps", "wheel_scale", "model_omega_bias_radps")
    FULL_DIM = 11  # EkfState.DIM + DIM


# Heading conventions: people, GNSS receivers, DBCs and ReV-StED's ``ins_yaw`` give a true heading
# clockwise from north [deg]; the EKF's ``psi`` is counter-clockwise from east [rad].
def heading_deg_to_psi(heading_deg):
    """True heading clockwise from north [deg] -> psi counter-clockwise from east [rad], not wrapped.

    Plain arithmetic: floats and NumPy arrays alike (unwrap an array's result yourself).
    """
    return math.pi / 2.0 - heading_deg * DEG_TO_RAD


def heading_deg_to_psi_rad(heading_deg: float) -> float:
    """True heading clockwise from north [deg] -> psi counter-clockwise from east [rad], wrapped to (-pi, pi]."""
    psi = heading_deg_to_psi(heading_deg)
    return math.atan2(math.sin(psi), math.cos(psi))


def course_over_ground(psi, v_x, v_y):
    """The direction of travel [rad, the EKF's convention], ``psi + atan2(v_y, v_x)``: what a single-antenna GNSS
    receiver reports as its course (NMEA RMC, gpsd's ``track``), the yaw plus the sideslip angle. Not wrapped;
    floats and NumPy arrays alike."""
    return psi + np.arctan2(v_y, v_x)


def psi_rad_to_heading_deg(psi_rad):
    """psi counter-clockwise from east [rad] -> true heading clockwise from north [deg] in [0, 360).

    Plain arithmetic: floats and NumPy arrays alike.
    """
    return (90.0 - psi_rad * RAD_TO_DEG) % 360.0


# Measurement model: H selects z (in z order) from the EKF state.
Z_TO_EKF_INDEX: tuple[int, ...] = (4, 5, 6, 7, 3)  # v_x, v_y, a_x, a_y, omega_z


# Physics guard limits (paper Eq. kamms circle; method.md "Model").
V_MAX_MPS = 30.0  # norm of (v_x, v_y)
OMEGA_MAX_RADPS = 1.5  # |omega_z|
A_MAX_DRY_MPS2 = 10.0  # norm of (a_x, a_y) on dry road, mu ~ 1
A_MAX_LOW_MU_MPS2 = 5.0  # mu <= 0.5
LOW_MU_THRESHOLD = 0.5
GUARD_EPS = 1e-6  # epsilon in the norm clamp


def accel_limit_mps2(mu: float) -> float:
    """Kamm's-circle acceleration bound a_max [m/s^2] for friction coefficient ``mu``."""
    if not (mu > 0.0):
        raise ValueError(f"friction coefficient mu must be > 0, got {mu!r}")
    return A_MAX_LOW_MU_MPS2 if mu <= LOW_MU_THRESHOLD else A_MAX_DRY_MPS2


def schema_dict() -> dict:
    """The schema as plain data (what the hash covers and what artifacts embed)."""
    return {
        "sample_rate_hz": SAMPLE_RATE_HZ,
        "window": {"L": WINDOW_LEN, "H": ENCODER_LEN},
        "signals": [{k: v for k, v in asdict(s).items() if k in ("index", "name", "unit")} for s in SIGNALS],
        "states": [asdict(s) for s in STATES],
        "ekf_state": list(EkfState.NAMES),
        "z_to_ekf_index": list(Z_TO_EKF_INDEX),
    }


def schema_hash() -> str:
    """Short SHA-256 of the signal/state layout; artifacts built against another layout differ."""
    blob = json.dumps(schema_dict(), sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


SCHEMA_HASH = schema_hash()
