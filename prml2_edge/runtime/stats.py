"""Frame accounting: every frame that enters is counted as used, ignored or rejected (by reason).

The counts add up: ``received == used + ignored + sum(rejected)``; :meth:`FrameStats.balanced`
checks it. Per-signal counters say which signal values were dropped and why. The pipeline is
the only writer: the decoder and the assembler note what happened on the frame's record
(:class:`~prml2_edge.runtime.rows.DecodedFrame`) and on each row, and the pipeline counts
them here with :meth:`FrameStats.add_frame` and :meth:`FrameStats.add_row`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from prml2_edge import schema
from prml2_edge.runtime.rows import AssembledRow, DecodedFrame
from prml2_edge.runtime.status import FrameStatus


def _zeros() -> list[int]:
    return [0] * schema.NUM_SIGNALS


@dataclass
class FrameStats:
    """Counters of frames by outcome, and of individual signal values by outcome."""

    received: int = 0
    by_status: list[int] = field(default_factory=lambda: [0] * len(FrameStatus))
    by_message: dict[str, int] = field(default_factory=dict)  # used frames per message name
    rejected_by_message: dict[str, dict[str, int]] = field(default_factory=dict)  # message -> reason -> frames
    signal_updates: list[int] = field(default_factory=_zeros)  # values applied to the hold
    signal_out_of_range: list[int] = field(default_factory=_zeros)
    signal_nonfinite: list[int] = field(default_factory=_zeros)
    signal_invalid_flag: list[int] = field(default_factory=_zeros)  # quality bit said invalid
    signal_late: list[int] = field(default_factory=_zeros)  # older than the held value: dropped
    signal_frozen: list[int] = field(default_factory=_zeros)  # stuck-sensor episodes (assembler StuckCheck)
    error_frames: int = 0  # CAN error frames received (counted as ignored)
    remote_frames: int = 0  # remote frames received (counted as ignored)
    clock_jumps: int = 0  # frame clock jumped backwards: the grid was re-based
    late_applied: int = 0  # frames older than the current 50 Hz row, applied to the hold value
    counter_gaps: int = 0  # counter jumped forward by more than one (frames lost upstream)
    gnss_fixes: int = 0
    gnss_invalid: int = 0

    def count(self, status: FrameStatus, message: str | None = None) -> None:
        """Count one frame's final outcome only."""
        self.received += 1
        self.by_status[status] += 1
        if status is FrameStatus.USED and message is not None:
            self.by_message[message] = self.by_message.get(message, 0) + 1
        elif status.is_rejected and message is not None:
            reasons = self.rejected_by_message.setdefault(message, {})
            reason = status.name.removeprefix("REJECTED_").lower()
            reasons[reason] = reasons.get(reason, 0) + 1

    def add_frame(self, status: FrameStatus, frame: DecodedFrame) -> None:
        """Count one frame: its final ``status`` and what the decoder and assembler noted on it."""
        message = frame.message
        if status is FrameStatus.USED and message is not None:  # the usual frame: count() inlined
            self.received += 1
            self.by_status[status] += 1
            self.by_message[message] = self.by_message.get(message, 0) + 1
        else:
            self.count(status, message)
        if frame.kind is not None:
            if frame.kind == "error":
                self.error_frames += 1
            elif frame.kind == "remote":
                self.remote_frames += 1
        if frame.flagged:
            per_reason = {"out_of_range": self.signal_out_of_range, "nonfinite": self.signal_nonfinite,
                          "invalid_flag": self.signal_invalid_flag}
            for index, reason in frame.flagged:
                per_reason[reason][index] += 1
        updates = self.signal_updates
        for index in frame.updated:
            updates[index] += 1
        if frame.late:
            for index in frame.late:
                self.signal_late[index] += 1
        self.counter_gaps += frame.counter_gap
        self.late_applied += frame.late_applied
        self.clock_jumps += frame.clock_jump
        if frame.gnss is not None:
            if frame.gnss.valid:
                self.gnss_fixes += 1
            else:
                self.gnss_invalid += 1

    def add_row(self, row: AssembledRow) -> None:
        """Count what the assembler noted on one 50 Hz row (stuck-sensor episodes)."""
        for index in row.newly_frozen:
            self.signal_frozen[index] += 1

    @property
    def used(self) -> int:
        return self.by_status[FrameStatus.USED]

    @property
    def ignored(self) -> int:
        return self.by_status[FrameStatus.IGNORED]

    @property
    def rejected(self) -> int:
        return sum(n for s, n in zip(FrameStatus, self.by_status, strict=True) if s.is_rejected)

    def balanced(self) -> bool:
        """True when every received frame is counted exactly once."""
        return self.received == self.used + self.ignored + self.rejected

    def rejected_by_reason(self) -> dict[str, int]:
        return {s.name.removeprefix("REJECTED_").lower(): n
                for s, n in zip(FrameStatus, self.by_status, strict=True) if s.is_rejected and n}

    def as_dict(self) -> dict:
        per_signal = {}
        for i, name in enumerate(schema.SIGNAL_NAMES):
            per_signal[name] = {
                "updates": self.signal_updates[i], "out_of_range": self.signal_out_of_range[i],
                "nonfinite": self.signal_nonfinite[i], "invalid_flag": self.signal_invalid_flag[i],
                "late": self.signal_late[i], "frozen": self.signal_frozen[i],
            }
        return {
            "received": self.received, "used": self.used, "ignored": self.ignored, "rejected": self.rejected,
            "rejected_by_reason": self.rejected_by_reason(), "balanced": self.balanced(),
            "late_applied": self.late_applied, "counter_gaps": self.counter_gaps,
            "error_frames": self.error_frames, "remote_frames": self.remote_frames, "clock_jumps": self.clock_jumps,
            "gnss_fixes": self.gnss_fixes, "gnss_invalid": self.gnss_invalid,
            "used_by_message": dict(self.by_message),
            "rejected_by_message": {m: dict(r) for m, r in self.rejected_by_message.items()}, "signals": per_signal,
        }
