"""Calibration that survives a restart: the filter's calibration states in a small JSON file.

What is saved (every ``save_interval_s`` of drive time and at a clean shutdown, atomically: a
temporary file in the same folder, fsync, rename): the calibration estimate
(:class:`prml2_edge.schema.CalState`) with its covariance, the wall-clock and drive time, and the
vehicle identity (the signal map's name and its DBC's file name). At start the file is restored
when it matches; a missing file starts from the prior silently (the first drive), while a corrupt,
stale or mismatched one gives one warning line and the prior, never a crash.

The restored covariance is floored at :data:`RESTORE_STD_FLOOR`: offsets drift between drives
(temperature, tyre pressure), so a restored estimate is a strong prior, not a certainty.

An optional ``yaw_gain`` section holds the evidence on the CAN yaw rate's gain gathered over every drive so far
(:mod:`prml2_edge.runtime.yaw_gain`: its information and information-weighted sum, which the next drive adds to).
A file without it (written before the gain was learned) loads as before; a malformed section is refused with one
warning line and the gain starts from its prior, the rest of the file still restored.

An optional ``cue_offsets`` section holds the cues' own offsets (:mod:`prml2_edge.runtime.cue_offset`: the
accelerometer's, the rear wheels' radius difference, the steering's) with their covariance, which the cue estimator
starts the next drive from. The same rules: absent loads as before, malformed is refused with one warning line.
"""

from __future__ import annotations

import json
import logging
import math
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from prml2_edge.ekf.numpy_ekf import checked_gaussian
from prml2_edge.schema import CalState

log = logging.getLogger(__name__)

FORMAT = "prml2-calibration"
VERSION = 1
SAVE_INTERVAL_S = 60.0
MAX_AGE_DAYS = 30.0
# one-sigma floor of a restored estimate: yaw-rate offset [rad/s], wheel scale [1], model bias [rad/s]
RESTORE_STD_FLOOR = np.array([0.05 * math.pi / 180.0, 0.002, 0.2 * math.pi / 180.0])


@dataclass
class CalibrationFile:
    """Load and save the calibration of one vehicle (``identity``) at ``path``."""

    path: Path
    identity: str
    max_age_days: float = MAX_AGE_DAYS
    save_interval_s: float = SAVE_INTERVAL_S

    def __post_init__(self) -> None:
        self.path = Path(self.path).expanduser()
        self.n_saves = 0
        self.last_error: str | None = None
        self.write_error: str | None = None  # the last failed save (a refused file on load is not one)
        self.restored = False
        self.yaw_gain: tuple[float, float] | None = None  # the loaded gain evidence (info, info_c), if any
        self.cue_offsets: tuple[np.ndarray, np.ndarray] | None = None  # the loaded cue offsets (values, cov), if any
        self._last_save_t: float | None = None

    def load(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(cal (3,), cov (3, 3))`` from the file, or None (absent, or refused with one warning line)."""
        if not self.path.exists():
            return None
        try:
            data = json.loads(self.path.read_text())
            if not isinstance(data, dict) or data.get("format") != FORMAT:
                raise ValueError("not a prml2 calibration file")
            if data.get("version") != VERSION:
                raise ValueError(f"version {data.get('version')!r}, this runtime reads {VERSION}")
            if list(data.get("state_names", [])) != list(CalState.NAMES):
                raise ValueError(f"states {data.get('state_names')} differ from {list(CalState.NAMES)}")
            cal, cov = checked_gaussian(data["cal"], data["cov"], CalState.DIM)
            saved = float(data["saved_unix_s"])
        except (OSError, ValueError, KeyError, TypeError) as exc:
            self._refuse(f"corrupt ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})")
            return None
        if data.get("vehicle") != self.identity:
            self._refuse(f"written for vehicle {data.get('vehicle')!r}, this run is {self.identity!r}")
            return None
        age_days = (time.time() - saved) / 86400.0
        if age_days > self.max_age_days:
            self._refuse(f"stale ({age_days:.0f} days old, the limit is {self.max_age_days:g})")
            return None
        if age_days < -1.0 / 24.0:
            self._refuse("saved in the future (check the system clock)")
            return None
        cov = cov + np.diag(RESTORE_STD_FLOOR**2)
        self.restored = True
        self.yaw_gain = self._load_gain(data.get("yaw_gain"))
        self.cue_offsets = self._load_cues(data.get("cue_offsets"))
        return cal, cov

    def _load_gain(self, section) -> tuple[float, float] | None:
        """The ``yaw_gain`` section's ``(info, info_c)``; None when absent, or refused with one warning line."""
        if section is None:
            return None
        try:
            info, info_c = float(section["info"]), float(section["info_c"])
            if not (math.isfinite(info) and math.isfinite(info_c) and info >= 0.0):
                raise ValueError("non-finite or negative information")
        except (ValueError, KeyError, TypeError) as exc:
            self.last_error = f"yaw_gain section refused ({exc})"
            log.warning("calibration file %s: yaw_gain section refused (%s): the gyro gain starts from its prior",
                        self.path, exc)
            return None
        return info, info_c

    def _load_cues(self, section) -> tuple[np.ndarray, np.ndarray] | None:
        """The ``cue_offsets`` section's ``(values (3,), cov (3, 3))``; None when absent, or refused with one warning
        line."""
        from prml2_edge.runtime.cue_offset import NUISANCE_NAMES, checked_nuisance

        if section is None:
            return None
        try:
            if list(section["names"]) != list(NUISANCE_NAMES):
                raise ValueError(f"names {section['names']} differ from {list(NUISANCE_NAMES)}")
            values, cov = checked_nuisance(section["values"], section["cov"])
        except (ValueError, KeyError, TypeError) as exc:
            self.last_error = f"cue_offsets section refused ({exc})"
            log.warning("calibration file %s: cue_offsets section refused (%s): the cues' offsets start from their "
                        "priors", self.path, exc)
            return None
        return values, cov

    def check_writable(self) -> None:
        """Refuse at start-up, with one line, a place the calibration can never be saved to."""
        from prml2_edge.errors import ConfigError

        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with tempfile.NamedTemporaryFile(prefix=f".{self.path.name}.", dir=self.path.parent):
                pass
        except OSError as exc:
            raise ConfigError(f"calibration file {self.path}: cannot write there ({exc.strerror or exc}); "
                              "give a writable path or leave --calibration out") from None

    def _refuse(self, why: str) -> None:
        self.last_error = why
        log.warning("calibration file %s %s: starting from the default calibration (it is rewritten at the "
                    "end of this run)", self.path, why)

    def due(self, t_s: float) -> bool:
        """Time to save at drive time ``t_s`` [s]? (The first call only starts the clock.)"""
        if self._last_save_t is None:
            self._last_save_t = t_s
            return False
        return t_s - self._last_save_t >= self.save_interval_s

    def save(self, cal: np.ndarray, cov: np.ndarray, t_s: float | None = None, yaw_gain: dict | None = None,
             cue_offsets: dict | None = None) -> bool:
        """Write atomically; False (and ``last_error``) when the folder is not writable, never raises.
        ``yaw_gain``: the gain estimator's :meth:`~prml2_edge.runtime.yaw_gain.YawGainEstimator.state`;
        ``cue_offsets``: :meth:`~prml2_edge.runtime.localizer.StreamingLocalizer.cue_offset_state`."""
        doc = {"format": FORMAT, "version": VERSION, "vehicle": self.identity, "saved_unix_s": time.time(),
               "drive_t_s": t_s, "state_names": list(CalState.NAMES),
               "cal": [float(v) for v in cal], "cov": [[float(v) for v in row] for row in cov],
               "readable": {"yaw_rate_offset_dps": math.degrees(float(cal[0])),
                            "wheel_scale_pct": 100.0 * float(cal[1])}}
        if yaw_gain is not None:
            doc["yaw_gain"] = {k: float(v) for k, v in yaw_gain.items()}
            doc["readable"]["yaw_rate_gain_pct"] = 100.0 * float(yaw_gain["gain"])
        if cue_offsets is not None:
            doc["cue_offsets"] = cue_offsets
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", dir=self.path.parent)
            try:
                with os.fdopen(fd, "w") as fh:
                    json.dump(doc, fh, indent=1)
                    fh.flush()
                    os.fsync(fh.fileno())
                os.replace(tmp, self.path)
            except BaseException:
                Path(tmp).unlink(missing_ok=True)
                raise
        except OSError as exc:
            self.last_error = self.write_error = f"cannot write {self.path} ({exc.strerror or exc})"
            return False
        if t_s is not None:
            self._last_save_t = t_s
        self.n_saves += 1
        return True

    def summary(self) -> dict:
        return {"file": str(self.path), "restored": self.restored, "saves": self.n_saves,
                "error": self.last_error}
