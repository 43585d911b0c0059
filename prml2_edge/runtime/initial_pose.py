"""Initial pose: from the command line, a file, or the first GNSS fix on the bus.

Headings given by people and GNSS receivers are *true heading, clockwise from north, in
degrees* (as in ``deploy/runtime.toml`` and the project DBC's ``GNSS_HEADING``); the EKF
uses ``psi`` counter-clockwise from east in radians: ``psi = pi/2 - radians(heading_deg)``
(:func:`prml2_edge.schema.heading_deg_to_psi_rad`).
"""

from __future__ import annotations

import json
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from prml2_edge import schema
from prml2_edge.ekf.numpy_ekf import default_initial_covariance
from prml2_edge.errors import ConfigError, first_line, reject_unknown_keys
from prml2_edge.runtime.rows import GnssFix
from prml2_edge.schema import EkfState, heading_deg_to_psi_rad

_FILE_KEYS = {"x_m", "y_m", "heading_deg", "pos_std_m", "heading_std_deg"}


@dataclass(frozen=True)
class InitialPose:
    """A starting pose: ``x_m`` east, ``y_m`` north [m], ``heading_deg`` clockwise from north.

    ``pos_std_m``/``heading_std_deg`` are its one-sigma uncertainties (initial covariance).
    """

    x_m: float
    y_m: float
    heading_deg: float
    pos_std_m: float = 0.5
    heading_std_deg: float = 2.0
    source: str = "config"

    def __post_init__(self) -> None:
        for name in ("x_m", "y_m", "heading_deg", "pos_std_m", "heading_std_deg"):
            if not math.isfinite(getattr(self, name)):
                raise ConfigError(f"initial pose: {name} must be finite, got {getattr(self, name)!r}")
        if self.pos_std_m <= 0 or self.heading_std_deg <= 0:
            raise ConfigError("initial pose: pos_std_m and heading_std_deg must be > 0")

    @property
    def psi_rad(self) -> float:
        return heading_deg_to_psi_rad(self.heading_deg)

    @classmethod
    def parse(cls, text: str) -> InitialPose:
        """``"X,Y,HEADING_DEG"`` (east [m], north [m], clockwise from north [deg])."""
        parts = [p.strip() for p in text.split(",")]
        try:
            if len(parts) != 3:
                raise ValueError
            x, y, h = (float(p) for p in parts)
        except ValueError:
            raise ConfigError(f"--initial-pose {text!r}: want X,Y,HEADING_DEG (east m, north m, deg clockwise "
                              "from north), e.g. 12.5,-3,90") from None
        return cls(x, y, h, source="command line")

    @classmethod
    def from_file(cls, path: str | Path) -> InitialPose:
        """A JSON or TOML file with ``x_m``, ``y_m``, ``heading_deg`` (optional ``pos_std_m``, ``heading_std_deg``)."""
        path = Path(path)
        try:
            raw = path.read_bytes()
        except OSError as exc:
            raise ConfigError(f"{path}: cannot read initial pose file ({exc.strerror})") from None
        try:
            data = tomllib.loads(raw.decode()) if path.suffix == ".toml" else json.loads(raw)
        except (ValueError, UnicodeDecodeError) as exc:
            raise ConfigError(f"{path}: initial pose file does not parse ({first_line(exc)})") from None
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: initial pose file must hold an object with x_m, y_m, heading_deg")
        reject_unknown_keys(data, _FILE_KEYS, "{path}: unknown key {key} (known: {known})", path=path)
        missing = [k for k in ("x_m", "y_m", "heading_deg") if k not in data]
        if missing:
            raise ConfigError(f"{path}: initial pose file lacks {', '.join(missing)}")
        try:
            values = {k: float(v) for k, v in data.items()}
        except (TypeError, ValueError):
            raise ConfigError(f"{path}: initial pose values must be numbers") from None
        return cls(**values, source=str(path))

    @classmethod
    def from_gnss(cls, fix: GnssFix, pos_std_m: float = 0.5, heading_std_deg: float = 2.0) -> InitialPose:
        heading = fix.heading_deg if fix.heading_deg is not None else 0.0
        std_h = heading_std_deg if fix.heading_deg is not None else 180.0
        return cls(fix.x_m, fix.y_m, heading, pos_std_m, std_h, source="gnss")


def initial_state(pose: InitialPose, values: np.ndarray | None = None,
                  valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """EKF state (8,) and covariance (8, 8) from a pose and, when given, the current onboard row.

    The dynamics come from the row's valid signals: ``v_x`` = mean of the valid wheel speeds
    (else the speedometer), ``omega_z`` = yaw rate, ``a_y`` = lateral acceleration; the rest 0.
    """
    x0 = np.zeros(EkfState.DIM)
    x0[EkfState.POS] = (pose.x_m, pose.y_m)
    x0[EkfState.YAW] = pose.psi_rad
    if values is not None:
        ok = np.ones(schema.NUM_SIGNALS, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
        idx = schema.SIGNAL_BY_NAME
        wheels = [idx[n].index for n in schema.WHEEL_SPEED_NAMES if ok[idx[n].index]]
        if wheels:
            x0[EkfState.VEL.start] = float(np.mean(values[wheels]))
        elif ok[idx["speedometer_mps"].index]:
            x0[EkfState.VEL.start] = float(values[idx["speedometer_mps"].index])
        if ok[idx["yaw_rate_radps"].index]:
            x0[EkfState.OMEGA_Z] = float(values[idx["yaw_rate_radps"].index])
        if ok[idx["lat_accel_mps2"].index]:
            x0[EkfState.ACC.start + 1] = float(values[idx["lat_accel_mps2"].index])
    p0 = default_initial_covariance()
    pos = np.arange(EkfState.POS.start, EkfState.POS.stop)
    p0[pos, pos] = pose.pos_std_m ** 2
    yaw = EkfState.YAW.start
    p0[yaw, yaw] = math.radians(pose.heading_std_deg) ** 2
    return x0, p0
