"""MCAP out: the run as Foxglove Studio, PlotJuggler and the ``mcap`` tools read it.

:class:`McapSink` writes one JSON-encoded message per topic and 50 Hz step with the ``mcap``
library; the schemas are JSON Schemas, Foxglove's well-known ones where one fits (Foxglove picks
a message's visualisation by its schema name):

==================== ============================ ==================================================
topic                schema                       what, when
==================== ============================ ==================================================
``/pose``            ``foxglove.PoseInFrame``     the pose in ``world`` (x east, y north, z up), each
                                                  step with a pose
``/tf``              ``foxglove.FrameTransform``  ``world`` -> ``vehicle``, each step with a pose
``/pose/covariance`` ``prml2.PoseCovariance``     2x2 position covariance [m^2], radial and heading
                                                  sigma, each step with a pose
``/dynamics``        ``prml2.DynamicStates``      the model's z with its sigma (null when the model was
                                                  not used) and the EKF's states, every step
``/signals``         ``prml2.OnboardSignals``     the 9 onboard signals [SI] and their validity, every
                                                  step
``/status``          ``prml2.PoseStatus``         pose status, EKF status, guard/model/GNSS/standstill
                                                  flags, calibration states, every step
``/gnss/fix``        ``prml2.GnssFix``            every GNSS fix received (valid or not), at its frame
                                                  time
``/gnss/pose``       ``foxglove.PoseInFrame``     every valid GNSS fix, for the 3D panel
==================== ============================ ==================================================

Log and publish times are the CAN frame times (the 50 Hz row time; a fix's own frame time) in
nanoseconds. Messages go into zstd chunks of ``chunk_s`` seconds of drive time; each chunk is
written to the file when it closes (a crashed process loses at most the open chunk) and fsync'ed
right after by a background thread, so that a slow disk never stalls the 50 Hz loop and a power
cut loses at most the open chunk and the one being synced (the header and schemas are synced before
the first message). ``step`` never raises: write failures are counted in ``errors``, the first kept
in ``last_error``.
"""

from __future__ import annotations

import json
import math
import os
import threading
from pathlib import Path

import numpy as np
from mcap.writer import CompressionType, Writer

from prml2_edge import __version__, schema
from prml2_edge.runtime.localizer import StepOutput
from prml2_edge.runtime.rows import GnssFix
from prml2_edge.runtime.status import PoseStatus
from prml2_edge.schema import CalState, EkfState

WORLD_FRAME = "world"
VEHICLE_FRAME = "vehicle"

# ---- JSON Schemas (Foxglove's published ones for the foxglove.* names) ------------------------------------------

_NUM = {"type": "number"}
_NUM_OR_NULL = {"type": ["number", "null"]}
_BOOL = {"type": "boolean"}
_STR = {"type": "string"}
_TIME = {"type": "object", "title": "time", "description": "Timestamp of the message",
         "properties": {"sec": {"type": "integer", "minimum": 0},
                        "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}}}
_VECTOR3 = {"title": "foxglove.Vector3", "type": "object", "properties": {"x": _NUM, "y": _NUM, "z": _NUM}}
_QUATERNION = {"title": "foxglove.Quaternion", "type": "object",
               "properties": {"x": _NUM, "y": _NUM, "z": _NUM, "w": _NUM}}
_POSE = {"title": "foxglove.Pose", "type": "object", "properties": {"position": _VECTOR3, "orientation": _QUATERNION}}


def _obj(title: str, description: str, properties: dict) -> dict:
    return {"title": title, "description": description, "type": "object", "properties": properties}


SCHEMAS: dict[str, dict] = {
    "foxglove.PoseInFrame": _obj("foxglove.PoseInFrame", "A timestamped pose for an object or reference frame in 3D "
                                 "space", {"timestamp": _TIME, "frame_id": _STR, "pose": _POSE}),
    "foxglove.FrameTransform": _obj("foxglove.FrameTransform", "A transform between two reference frames in 3D space",
                                    {"timestamp": _TIME, "parent_frame_id": _STR, "child_frame_id": _STR,
                                     "translation": _VECTOR3, "rotation": _QUATERNION}),
    "prml2.PoseCovariance": _obj("prml2.PoseCovariance", "Planar position covariance (row-major 2x2, world frame, "
                                 "m^2) and one-sigma radial position and heading uncertainty",
                                 {"timestamp": _TIME, "frame_id": _STR,
                                  "position_covariance": {"type": "array", "items": _NUM, "minItems": 4,
                                                          "maxItems": 4},
                                  "pos_std_m": _NUM, "yaw_std_rad": _NUM, "yaw_std_deg": _NUM}),
    "prml2.DynamicStates": _obj("prml2.DynamicStates", "Vehicle dynamic states: the model's z and its one-sigma "
                                "(null when the model was not used at this step) and the EKF's estimate (SI)",
                                {"timestamp": _TIME, "model_used": _BOOL,
                                 "z": _obj("z", "model output after the physics guard",
                                           {n: _NUM_OR_NULL for n in schema.STATE_NAMES}),
                                 "z_std": _obj("z_std", "one-sigma of z",
                                               {n: _NUM_OR_NULL for n in schema.STATE_NAMES}),
                                 "ekf": _obj("ekf", "EKF state", {n: _NUM_OR_NULL for n in EkfState.NAMES[3:]})}),
    "prml2.OnboardSignals": _obj("prml2.OnboardSignals", "The 9 onboard signals on the 50 Hz grid (SI, held values) "
                                 "and whether each is valid",
                                 {"timestamp": _TIME,
                                  "values": _obj("values", "SI", {n: _NUM_OR_NULL for n in schema.SIGNAL_NAMES}),
                                  "valid": _obj("valid", "per signal", {n: _BOOL for n in schema.SIGNAL_NAMES}),
                                  "all_valid": _BOOL}),
    "prml2.PoseStatus": _obj("prml2.PoseStatus", "Pose status, EKF step status and the guard, model, GNSS and "
                             "standstill flags of one 50 Hz step",
                             {"timestamp": _TIME, "status": {"type": "string", "enum": [s.name for s in PoseStatus]},
                              "status_code": {"type": "integer"}, "ekf_status": {"type": ["string", "null"]},
                              "model_used": _BOOL, "inferred": _BOOL, "guard_fired": _BOOL, "gnss_fused": _BOOL,
                              "gnss_outage": _BOOL, "outage_s": _NUM_OR_NULL, "degraded": _BOOL, "bus_silent": _BOOL,
                              "cues_used": _BOOL, "standstill": _BOOL,
                              "calibration": _obj("calibration", "calibration states (null when off)",
                                                  {n: _NUM_OR_NULL for n in CalState.NAMES})}),
    "prml2.GnssFix": _obj("prml2.GnssFix", "A GNSS fix as received on the bus: local frame, heading clockwise from "
                          "north (null when the map has none)",
                          {"timestamp": _TIME, "frame_id": _STR, "x_m": _NUM_OR_NULL, "y_m": _NUM_OR_NULL,
                           "heading_deg": _NUM_OR_NULL, "valid": _BOOL}),
}

_FLAGS = ("model_used", "inferred", "guard_fired", "gnss_fused", "gnss_outage", "degraded", "bus_silent", "cues_used",
          "standstill")

TOPICS: dict[str, str] = {
    "/pose": "foxglove.PoseInFrame",
    "/tf": "foxglove.FrameTransform",
    "/pose/covariance": "prml2.PoseCovariance",
    "/dynamics": "prml2.DynamicStates",
    "/signals": "prml2.OnboardSignals",
    "/status": "prml2.PoseStatus",
    "/gnss/fix": "prml2.GnssFix",
    "/gnss/pose": "foxglove.PoseInFrame",
}


def _num(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def _named(names, values) -> dict:
    """``{name: value}`` with non-finite values (or all of them, when ``values`` is None) as null."""
    if values is None:
        return dict.fromkeys(names)
    return {n: _num(v) for n, v in zip(names, values, strict=True)}


def _stamp(ns: int) -> dict:
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _yaw_quaternion(psi_rad: float) -> dict:
    half = 0.5 * psi_rad
    return {"x": 0.0, "y": 0.0, "z": math.sin(half), "w": math.cos(half)}


class McapSink:
    """Write every step to an MCAP file (topics and schemas in the module docstring).

    Parameters
    ----------
    path:
        The ``.mcap`` file (overwritten).
    chunk_s:
        Drive time per chunk [s]: what a crash can lose at most.
    """

    def __init__(self, path: str | Path, chunk_s: float = 1.0) -> None:
        if not chunk_s > 0:
            raise ValueError(f"chunk_s must be > 0, got {chunk_s}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.chunk_s = float(chunk_s)
        self.rows = 0
        self.messages = 0
        self.errors = 0
        self.last_error = ""
        self._f = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        # chunks close on drive time (below); the size limit is only a backstop
        self._writer = Writer(self._f, chunk_size=8 * 1024 * 1024, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library=f"prml2-edge {__version__}")
        schema_ids = {name: self._writer.register_schema(name, "jsonschema", json.dumps(s).encode())
                      for name, s in SCHEMAS.items()}
        self._channel = {topic: self._writer.register_channel(topic, "json", schema_ids[name])
                         for topic, name in TOPICS.items()}
        self._seq = dict.fromkeys(TOPICS, 0)
        self._chunk_end_ns: int | None = None
        self._closed = False
        self._sync()  # header, schemas and channels are on disk before the first message
        self._sync_due = threading.Event()
        self._syncer = threading.Thread(target=self._sync_loop, name="prml2-mcap-fsync", daemon=True)
        self._syncer.start()

    # ---- writing -------------------------------------------------------------------------------------------------

    def _failed(self, exc: Exception) -> None:
        self.errors += 1
        if not self.last_error:
            self.last_error = f"{self.path}: {exc}"

    def _sync(self) -> None:
        self._f.flush()
        os.fsync(self._f.fileno())

    def _sync_loop(self) -> None:
        """Background thread: fsync the file after each chunk the writer closed (until :meth:`close`)."""
        while True:
            self._sync_due.wait()
            self._sync_due.clear()
            if self._closed:
                return
            try:
                os.fsync(self._f.fileno())
            except (OSError, ValueError) as exc:  # ValueError: closed meanwhile
                self._failed(exc)

    def _add(self, topic: str, ns: int, msg: dict) -> None:
        self._seq[topic] += 1
        self._writer.add_message(self._channel[topic], log_time=ns, publish_time=ns, sequence=self._seq[topic],
                                 data=json.dumps(msg, separators=(",", ":"), allow_nan=False).encode())
        self.messages += 1

    def step(self, out: StepOutput) -> None:
        if self._closed:
            return
        try:
            ns = round(out.t_s * 1e9)
            if not ns >= 0:
                raise ValueError(f"step time {out.t_s} s cannot be an MCAP timestamp (must be >= 0)")
            chunk_ns = round(self.chunk_s * 1e9)
            if self._chunk_end_ns is None:
                self._chunk_end_ns = ns + chunk_ns
            elif not self._chunk_end_ns - chunk_ns <= ns < self._chunk_end_ns:  # a second on, or the clock jumped
                self._writer.flush()  # closes the chunk in progress and hands it to the OS
                self._sync_due.set()  # ... and the background thread syncs it to the disk
                self._chunk_end_ns = ns + chunk_ns
            if out.gnss is not None:
                self._gnss(out.gnss)
            stamp = _stamp(ns)
            x = out.x
            if out.status is not PoseStatus.INITIALISING:
                self._pose(ns, stamp, out)
            z_std = None if out.z_var is None else np.sqrt(np.maximum(out.z_var, 0.0))
            self._add("/dynamics", ns, {
                "timestamp": stamp, "model_used": bool(out.model_used), "z": _named(schema.STATE_NAMES, out.z),
                "z_std": _named(schema.STATE_NAMES, z_std), "ekf": _named(EkfState.NAMES[3:], x[3:])})
            self._add("/signals", ns, {
                "timestamp": stamp, "values": _named(schema.SIGNAL_NAMES, out.signals),
                "valid": {n: bool(v) for n, v in zip(schema.SIGNAL_NAMES, out.valid, strict=True)},
                "all_valid": bool(np.all(out.valid))})
            self._add("/status", ns, {
                "timestamp": stamp, "status": out.status.name, "status_code": int(out.status),
                "ekf_status": None if out.ekf_status is None else out.ekf_status.name,
                **{k: bool(getattr(out, k)) for k in _FLAGS}, "outage_s": _num(out.outage_s),
                "calibration": _named(CalState.NAMES, out.cal)})
            self.rows += 1
        except (OSError, ValueError, TypeError, OverflowError) as exc:
            self._failed(exc)

    def _pose(self, ns: int, stamp: dict, out: StepOutput) -> None:
        (p_x, p_y), psi = out.x[EkfState.POS], float(out.x[EkfState.YAW.start])
        position = {"x": _num(p_x), "y": _num(p_y), "z": 0.0}
        rotation = _yaw_quaternion(psi) if math.isfinite(psi) else {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}
        self._add("/pose", ns, {"timestamp": stamp, "frame_id": WORLD_FRAME,
                                "pose": {"position": position, "orientation": rotation}})
        self._add("/tf", ns, {"timestamp": stamp, "parent_frame_id": WORLD_FRAME, "child_frame_id": VEHICLE_FRAME,
                              "translation": position, "rotation": rotation})
        cov = out.pos_cov if out.pos_cov is not None else np.full((2, 2), np.nan)
        self._add("/pose/covariance", ns, {
            "timestamp": stamp, "frame_id": WORLD_FRAME, "position_covariance": [_num(v) for v in np.ravel(cov)],
            "pos_std_m": _num(out.pos_std_m), "yaw_std_rad": _num(out.yaw_std_rad),
            "yaw_std_deg": _num(math.degrees(out.yaw_std_rad))})

    def _gnss(self, fix: GnssFix) -> None:
        ns = max(round(fix.t_s * 1e9), 0) if math.isfinite(fix.t_s) else 0
        stamp = _stamp(ns)
        self._add("/gnss/fix", ns, {"timestamp": stamp, "frame_id": WORLD_FRAME, "x_m": _num(fix.x_m),
                                    "y_m": _num(fix.y_m),
                                    "heading_deg": None if fix.heading_deg is None else _num(fix.heading_deg),
                                    "valid": bool(fix.valid)})
        if fix.valid and math.isfinite(fix.x_m) and math.isfinite(fix.y_m):
            psi = fix.psi_rad
            orientation = _yaw_quaternion(psi) if psi is not None and math.isfinite(psi) else \
                {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}
            self._add("/gnss/pose", ns, {"timestamp": stamp, "frame_id": WORLD_FRAME,
                                         "pose": {"position": {"x": fix.x_m, "y": fix.y_m, "z": 0.0},
                                                  "orientation": orientation}})

    def close(self) -> None:
        """Write the summary (indexes, statistics) and the footer, sync and close."""
        if self._closed:
            return
        self._closed = True
        self._sync_due.set()
        self._syncer.join(timeout=10.0)
        try:
            self._writer.finish()
            self._sync()
        except (OSError, ValueError) as exc:
            self._failed(exc)
        finally:
            self._f.close()
