"""Rows the runtime's stages hand each other: a GNSS fix, a decoded frame, an assembled 50 Hz row.

The decoder produces :class:`DecodedFrame` (and :class:`GnssFix`), the assembler consumes
them and produces :class:`AssembledRow`, the pipeline and localiser consume those. Keeping
the types here lets each stage import what it receives without importing the stage before it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from prml2_edge.runtime.status import FrameStatus
from prml2_edge.schema import heading_deg_to_psi_rad


@dataclass(frozen=True)
class GnssFix:
    """A GNSS fix from the bus: position in the local frame, heading as GNSS receivers give it.

    ``x_m`` east [m], ``y_m`` north [m], ``heading_deg`` true heading clockwise from north
    [deg] (None when the map has no heading signal). ``t_s`` is the frame's timestamp [s].
    The angle is what a single-antenna receiver gives, the course over ground (NMEA RMC, gpsd's ``track``, a
    ``--gnss`` CSV or TUM file), unless the runtime config says it is the yaw (``[gnss] course = false``).
    """

    t_s: float
    x_m: float
    y_m: float
    heading_deg: float | None
    valid: bool

    @property
    def psi_rad(self) -> float | None:
        """Heading counter-clockwise from east [rad] (the EKF's convention), wrapped to (-pi, pi]."""
        return None if self.heading_deg is None else heading_deg_to_psi_rad(self.heading_deg)


@dataclass(slots=True)  # slots: one is built per CAN frame (~0.3 µs less each)
class DecodedFrame:
    """What one frame contributed: values of canonical signals and their quality flags.

    ``index[i]`` is the canonical signal index (``schema.SIGNALS``) of ``value_si[i]``;
    ``ok[i]`` is False when the value's quality bit says invalid (the value is then not held,
    but the signal is marked invalid at once).

    The frame is also its own record: the decoder notes what it saw (``kind``, ``counter_gap``,
    ``flagged``), the assembler what it did with the values (``updated``, ``late``,
    ``late_applied``, ``clock_jump``), and the pipeline counts it once
    (:meth:`prml2_edge.runtime.stats.FrameStats.add_frame`). No stage writes the counters.
    """

    status: FrameStatus
    t_s: float
    message: str | None = None
    index: list[int] = field(default_factory=list)
    value_si: list[float] = field(default_factory=list)
    ok: list[bool] = field(default_factory=list)
    gnss: GnssFix | None = None
    kind: str | None = None  # "error" / "remote" for CAN error and remote frames
    counter_gap: bool = False  # alive counter advanced by more than one (frames lost upstream)
    flagged: list[tuple[int, str]] = field(default_factory=list)  # (signal index, "out_of_range" |
    #                                    "nonfinite" | "invalid_flag"); the first two are dropped
    updated: list[int] = field(default_factory=list)  # signals whose held value this frame set
    late: list[int] = field(default_factory=list)  # signals dropped: older than the held value
    late_applied: bool = False  # older than the current row, but applied to the hold
    clock_jump: bool = False  # this frame confirmed a clock jump back (the grid was re-based)
    injection: bool = False  # this frame's message is under suspicion of injection (decode.InjectionMonitor)


@dataclass
class AssembledRow:
    """One 50 Hz row of o_t.

    ``values`` (9,) SI, canonical order (never-received signals hold 0.0 and are invalid);
    ``valid`` (9,) bool; ``age_s`` (9,) seconds since the held value's frame (inf if never);
    ``gnss`` the newest GNSS fix that arrived within this row's interval;
    ``trigger_ns`` ``time.perf_counter_ns()`` when the frame that closed this row was received
    (0 when the row was flushed at the end), the start of the end-to-end latency.
    """

    k: int
    t_s: float
    values: np.ndarray
    valid: np.ndarray
    age_s: np.ndarray
    gnss: GnssFix | None = None
    discontinuity: bool = False
    trigger_ns: int = 0
    bus_silent: bool = False  # no frame at all for more than bus_silent_s before this row
    newly_frozen: tuple[int, ...] = ()  # signals a stuck check froze at this row
    # runtime.plausibility: values replaced by what the other signals predict (flagged or stale signals)
    substituted: np.ndarray | None = None  # (9,) bool, None: none replaced
    substitute_std: np.ndarray | None = None  # (9,) uncertainty of each substituted value [SI] (nan: not known)
    # offset jumps the cross-checks measured at this row: (signal index, offset [SI], its std, time of the step [s])
    offset_jumps: tuple[tuple[int, float, float, float], ...] = ()
    newly_flagged: tuple[int, ...] = ()  # signals the cross-checks flagged at this row

    @property
    def all_valid(self) -> bool:
        return bool(self.valid.all())
