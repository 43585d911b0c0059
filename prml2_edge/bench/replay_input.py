"""Benchmark input: a seeded simulated drive, encoded to CAN frames with the shipped signal map.

The frames are what the runtime reads from a bus or a log (the project DBC, real counters,
checksums and validity bits), so the benchmark exercises decode and assembly for real.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import can

from prml2_edge.runtime.initial_pose import InitialPose
from prml2_edge.schema import psi_rad_to_heading_deg

DEFAULT_MAP = "prml2_onboard"


@dataclass
class ReplayInput:
    """CAN frames of one drive, its duration [s] and the true start pose (the EKF's initial pose)."""

    frames: list[can.Message]
    duration_s: float
    initial_pose: InitialPose
    log_path: Path | None = None


def simulate_log(seconds: float, out_path: str | Path, seed: int = 0, family: str = "mixed", mu: float = 1.0,
                 signal_map: str = DEFAULT_MAP, gnss_seconds: float = 0.0) -> tuple[Path, InitialPose, float]:
    """Simulate ``seconds`` of driving and write it as a CAN log (format from the suffix), with GNSS fix
    frames for the first ``gnss_seconds``.

    Returns ``(log path, initial pose from the drive's ground truth, duration [s])``.
    """
    from prml2_edge.can.encode import encode_drive_to_log
    from prml2_edge.can.signal_map import shipped_map_path
    from prml2_edge.data.simulate import simulate_drive

    drive = simulate_drive(seconds / 60.0, mu, seed, family)
    info = encode_drive_to_log(drive, out_path, signal_map_path=shipped_map_path(signal_map),
                               gnss_seconds=gnss_seconds)
    x_m, y_m, psi_rad = (float(v) for v in drive.pose_gt[0])
    pose = InitialPose(x_m, y_m, psi_rad_to_heading_deg(psi_rad), source="ground truth")
    return Path(info["out"]), pose, float(info["duration_s"])


def simulate_fleet_log(seconds: float, out_path: str | Path, seed: int = 0, gnss_head_s: float = 10.0,
                       gnss_tail_s: float = 2.0, family: str = "mixed", mu: float = 1.0,
                       signal_map: str = DEFAULT_MAP) -> tuple[Path, float]:
    """A drive as a fleet car logs it: GNSS for the first ``gnss_head_s``, an outage, GNSS again for the last
    ``gnss_tail_s`` (the fix after the outage measures the drift). Returns ``(log path, duration [s])``."""
    from prml2_edge.can.encode import encode_drive_to_log
    from prml2_edge.can.signal_map import load_map_and_dbc, shipped_map_path
    from prml2_edge.data.simulate import simulate_drive

    out_path = Path(out_path)
    drive = simulate_drive(seconds / 60.0, mu, seed, family)
    with tempfile.TemporaryDirectory(prefix="prml2-fleet-") as tmp:
        full = Path(tmp) / "full.log"
        info = encode_drive_to_log(drive, full, signal_map_path=shipped_map_path(signal_map), gnss_seconds=seconds)
        smap, db, _ = load_map_and_dbc(shipped_map_path(signal_map))
        gnss_id = db.get_message_by_name(smap.gnss.message).frame_id
        duration = float(info["duration_s"])
        with can.LogReader(str(full)) as reader, can.Logger(str(out_path)) as writer:
            t0 = None
            for msg in reader:
                t0 = msg.timestamp if t0 is None else t0
                t = msg.timestamp - t0
                if msg.arbitration_id != gnss_id or t < gnss_head_s or t >= duration - gnss_tail_s:
                    writer.on_message_received(msg)
    return out_path, duration


def read_frames(log_path: str | Path) -> list[can.Message]:
    """Every frame of a CAN log, in file order."""
    with can.LogReader(str(log_path)) as reader:
        return list(reader)


def simulated_frames(seconds: float, seed: int = 0, family: str = "mixed", mu: float = 1.0,
                     signal_map: str = DEFAULT_MAP) -> ReplayInput:
    """A simulated drive of ``seconds`` as in-memory CAN frames (encoded through a temporary log)."""
    with tempfile.TemporaryDirectory(prefix="prml2-bench-") as tmp:
        path, pose, duration_s = simulate_log(seconds, Path(tmp) / "drive.log", seed, family, mu, signal_map)
        frames = read_frames(path)
    return ReplayInput(frames, duration_s, pose)
