"""Sinks: where each 50 Hz :class:`~prml2_edge.runtime.localizer.StepOutput` goes.

* :class:`JsonlSink`: one JSON object per step (``StepOutput.record()``: time, full EKF state,
  uncertainties, status flags, per-signal validity).
* :class:`CsvSink`: the same, flat (validity as ``valid_<signal>`` 0/1 columns).
* :class:`TumSink`: TUM RGB-D trajectory format ``timestamp x y z qx qy qz qw`` (z = 0,
  quaternion of the heading about the up axis), for evo and friends.
* :class:`CanSink`: ``PRML2_POSE``, ``PRML2_DYNAMICS`` and ``PRML2_POSE_STD`` of the project
  DBC, sent on a python-can bus or written to a python-can log (any ``can.Logger`` format).

Every sink has ``step(out)`` and ``close()``; ``step`` never raises (write failures are counted
in ``errors``; the first is kept in ``last_error``). Steps still initialising (no pose) are
written by the file sinks with empty pose fields and skipped by TUM and CAN.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import can
import cantools

from prml2_edge import schema
from prml2_edge.can.signal_map import load_dbc
from prml2_edge.resources import project_dbc_path
from prml2_edge.runtime.localizer import StepOutput
from prml2_edge.runtime.status import PoseStatus
from prml2_edge.schema import EkfState
from prml2_edge.tum import tum_line


class _FileSink:
    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(self.path, "w", newline="", encoding="utf-8")  # noqa: SIM115 - closed in close()
        self.rows = 0
        self.errors = 0
        self.last_error = ""

    def _failed(self, exc: Exception) -> None:
        self.errors += 1
        if not self.last_error:
            self.last_error = f"{self.path}: {exc}"

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()


class JsonlSink(_FileSink):
    """JSON lines: one :meth:`StepOutput.record` per line."""

    def step(self, out: StepOutput) -> None:
        try:
            self._f.write(json.dumps(out.record(), separators=(",", ":")) + "\n")
            self.rows += 1
        except (OSError, ValueError) as exc:
            self._failed(exc)


CSV_COLUMNS = (["t_s", *EkfState.NAMES, "pos_std_m", "yaw_std_rad", "status", "model_used", "guard_fired",
                "gnss_fused", "gnss_outage", "outage_s", "degraded", "ekf_status"]
               + [f"valid_{n}" for n in schema.SIGNAL_NAMES])


class CsvSink(_FileSink):
    """CSV with the columns :data:`CSV_COLUMNS` (empty cells where a value is undefined)."""

    def __init__(self, path: str | Path) -> None:
        super().__init__(path)
        self._w = csv.writer(self._f)
        self._w.writerow(CSV_COLUMNS)

    def step(self, out: StepOutput) -> None:
        rec = out.record()
        valid = rec.pop("valid")
        try:
            row = []
            for col in CSV_COLUMNS:
                v = valid[col[6:]] if col.startswith("valid_") else rec[col]
                row.append("" if v is None else int(v) if isinstance(v, bool) else
                           f"{v:.6f}" if isinstance(v, float) else v)
            self._w.writerow(row)
            self.rows += 1
        except (OSError, ValueError) as exc:
            self._failed(exc)


class TumSink(_FileSink):
    """TUM trajectory: ``timestamp x y z qx qy qz qw`` (planar: z = 0, rotation about z by psi)."""

    def step(self, out: StepOutput) -> None:
        if out.status is PoseStatus.INITIALISING:
            return
        (x, y), psi = out.x[EkfState.POS], out.x[EkfState.YAW.start]
        try:
            self._f.write(tum_line(out.t_s, x, y, psi))
            self.rows += 1
        except (OSError, ValueError) as exc:
            self._failed(exc)


def _clip(value: float, signal: cantools.database.can.Signal) -> float:
    lo = signal.minimum if signal.minimum is not None else -math.inf
    hi = signal.maximum if signal.maximum is not None else math.inf
    if not math.isfinite(value):
        return 0.0
    return min(max(value, lo), hi)


class CanSink:
    """Send the pose, z and pose uncertainty as the project DBC's PRML2_* messages (50 Hz).

    Parameters
    ----------
    target:
        A python-can bus (``send``) or listener such as ``can.Logger`` (``on_message_received``).
    db:
        The project DBC (default: the shipped ``dbc/prml2_onboard.dbc``).
    """

    def __init__(self, target, db: cantools.database.can.Database | None = None) -> None:
        self.target = target
        self.db = db or load_dbc(project_dbc_path())
        self._pose = self.db.get_message_by_name("PRML2_POSE")
        self._dyn = self.db.get_message_by_name("PRML2_DYNAMICS")
        self._std = self.db.get_message_by_name("PRML2_POSE_STD")
        self._send = target.send if hasattr(target, "send") else target.on_message_received
        self.counter = 0
        self.frames = 0
        self.errors = 0
        self.last_error = ""

    def _encode(self, msg: cantools.database.can.Message, values: dict) -> bytes:
        return msg.encode({k: _clip(v, msg.get_signal_by_name(k)) for k, v in values.items()})

    def step(self, out: StepOutput) -> None:
        if out.status is PoseStatus.INITIALISING:
            return
        x = out.x
        heading_deg = math.degrees(x[EkfState.YAW.start]) % 360.0  # counter-clockwise from east
        (p_x, p_y), (v_x, v_y), (a_x, a_y) = x[EkfState.POS], x[EkfState.VEL], x[EkfState.ACC]
        try:
            payloads = (
                (self._pose, {"POSE_X": p_x, "POSE_Y": p_y, "POSE_HEADING": heading_deg,
                              "POSE_STATUS": int(out.status)}),
                (self._dyn, {"DYN_V_X": v_x, "DYN_V_Y": v_y, "DYN_A_X": a_x, "DYN_A_Y": a_y,
                             "DYN_YAW_RATE": x[EkfState.OMEGA_Z.start]}),
                (self._std, {"POSE_STD_POS": out.pos_std_m, "POSE_STD_HEADING": math.degrees(out.yaw_std_rad),
                             "OUTAGE_TIME": out.outage_s if math.isfinite(out.outage_s) else 0.0,
                             "COUNTER": self.counter}),
            )
            for msg, values in payloads:
                frame = can.Message(timestamp=out.t_s, arbitration_id=msg.frame_id, is_extended_id=False, is_rx=False,
                                    data=self._encode(msg, values))
                self._send(frame)
                self.frames += 1
            self.counter = (self.counter + 1) % 16
        except Exception as exc:  # a bus can fail in many backend-specific ways; never stop the loop
            self.errors += 1
            if not self.last_error:
                self.last_error = f"CAN out: {exc}"

    def close(self) -> None:
        stop = getattr(self.target, "stop", None)
        if stop is not None and not hasattr(self.target, "send"):
            stop()  # a can.Logger: flush and close the file
