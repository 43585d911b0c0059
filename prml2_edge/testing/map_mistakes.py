"""The mistakes a user makes when writing a signal map, for the ``doctor --log`` tests and benchmark.

Each mistake turns a correct map (and a log encoded with it) into what a user would have: a
map with a flipped sign or a wheel speed declared in m/s that is in km/h, or a log on which
one mapped message never appears (the DBC is not this car's). :func:`expected_culprit` says
which signal ``prml2 doctor --log`` must blame. :func:`straight_drive` is the drive on which no
sign can be checked (doctor must say NOT VERIFIED, never OK). This module only builds test input.
"""

from __future__ import annotations

import re
from pathlib import Path

import can
import numpy as np

from prml2_edge import schema
from prml2_edge.can.signal_map import load_signal_map

MISTAKES = ("flip_yaw", "flip_lat", "flip_steer", "wheel_kmh_as_mps", "message_absent")
_SIGNAL = {"flip_yaw": "yaw_rate_radps", "flip_lat": "lat_accel_mps2", "flip_steer": "steering_wheel_angle_rad",
           "wheel_kmh_as_mps": "wheel_speed_fr_mps", "message_absent": "yaw_rate_radps"}


def expected_culprit(mistake: str) -> str:
    """The canonical signal ``doctor --log`` must name for ``mistake``."""
    return _SIGNAL[mistake]


def _set_scale(text: str, signal: str, new_scale: str) -> str:
    """``text`` with the ``scale`` line of ``[signals.<signal>]`` replaced (added when the table has none)."""
    head = f"[signals.{signal}]"
    start = text.index(head)
    nxt = text.find("\n[", start + len(head))
    end = len(text) if nxt < 0 else nxt
    block = text[start:end]
    if re.search(r"^scale\s*=", block, flags=re.M):
        block = re.sub(r"^scale\s*=\s*[^#\n]*", f"scale = {new_scale} ", block, count=1, flags=re.M)
    else:
        block = block.replace(head, f"{head}\nscale = {new_scale}", 1)
    return text[:start] + block + text[end:]


def wrong_map(map_path: str | Path, mistake: str, out_path: str | Path) -> Path:
    """Write the map a user would have written with ``mistake`` (``message_absent`` leaves the map right).

    The map's ``dbc`` is made absolute so the copy loads from anywhere.
    """
    map_path, out_path = Path(map_path), Path(out_path)
    smap = load_signal_map(map_path)
    text = map_path.read_text()
    by = {s.name: s for s in smap.signals}
    if mistake.startswith("flip_"):
        spec = by[_SIGNAL[mistake]]
        text = _set_scale(text, spec.name, repr(-spec.scale))
    elif mistake == "wheel_kmh_as_mps":
        text = _set_scale(text, _SIGNAL[mistake], "1.0")
    elif mistake != "message_absent":
        raise ValueError(f"unknown mistake {mistake!r}; known: {', '.join(MISTAKES)}")
    dbc = smap.resolve_dbc() if Path(smap.dbc).is_absolute() or (map_path.parent.parent / smap.dbc).is_file() \
        else None
    if dbc is not None:
        text = re.sub(r'^dbc\s*=\s*"[^"]*"', f'dbc = "{dbc.resolve()}"', text, count=1, flags=re.M)
    out_path.write_text(text)
    return out_path


def drop_message(log_in: str | Path, log_out: str | Path, frame_id: int) -> int:
    """Copy ``log_in`` to ``log_out`` without the frames of ``frame_id``; returns the frames dropped."""
    dropped = 0
    with can.LogReader(str(log_in)) as reader, can.Logger(str(log_out)) as writer:
        for msg in reader:
            if msg.arbitration_id == frame_id:
                dropped += 1
                continue
            writer.on_message_received(msg)
    return dropped


def straight_drive(minutes: float, seed: int, vehicle: str = "reference"):
    """A highway drive on a dead-straight road: the ``highway`` family's speeds and speed changes, the steering
    wheel held straight (no bend, lane change or correction), the car's sensor errors drawn as for any drive."""
    from prml2_edge.data.revsted import Drive
    from prml2_edge.data.simulate import SensorErrors, get_car, simulate_vehicle
    from prml2_edge.data.simulate.driver import plan_drive
    from prml2_edge.data.simulate.sensors import onboard_signals

    car = get_car(vehicle)
    n = int(round(minutes * 60.0 * schema.SAMPLE_RATE_HZ))
    rng = np.random.default_rng([int(seed), 0x5354])  # "ST"
    plan = plan_drive(n, 1.0, "highway", rng, car.params)
    trace = simulate_vehicle(car.params, 1.0, np.zeros(n), plan.accel_ff, plan.v_ref, free_steer=np.zeros(n, bool),
                             v0_mps=plan.v0_mps)
    onboard, _ = onboard_signals(trace, car.params, rng, SensorErrors.draw(rng, car.sensors), car.sensors)
    return Drive(name=f"straight_{vehicle}_s{seed}", path=None, t_s=np.arange(n) * schema.DT_S, onboard=onboard,
                 z_gt=None, pose_gt=None, meta={"family": "straight", "vehicle": vehicle, "seed": int(seed)},
                 repairs={})
