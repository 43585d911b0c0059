"""Status enums returned by the hot-path stages instead of raising.

:class:`FrameStatus` says what happened to one CAN frame (every frame gets exactly one,
so the frame accounting adds up); :class:`PoseStatus` is the localiser's state per 50 Hz
step, with the values of ``PRML2_POSE.POSE_STATUS`` in ``dbc/prml2_onboard.dbc``.
"""

from __future__ import annotations

from enum import IntEnum


class FrameStatus(IntEnum):
    """Outcome of one frame in the decoder and assembler."""

    USED = 0  # at least one value (or a GNSS fix) taken from it
    IGNORED = 1  # arbitration ID not in the signal map (or a remote/error frame)
    REJECTED_DLC = 2  # data length differs from the DBC's
    REJECTED_CHECKSUM = 3  # checksum mismatch
    REJECTED_COUNTER = 4  # alive counter repeated or out of sequence
    REJECTED_DECODE = 5  # cantools could not decode it
    REJECTED_RANGE = 6  # every mapped value outside the schema's physical range
    REJECTED_NONFINITE = 7  # every mapped value NaN/inf
    REJECTED_INVALID = 8  # every mapped value flagged invalid by its quality bit
    REJECTED_LATE = 9  # older than the values already held for all its signals (out of order)
    REJECTED_TIMESTAMP = 10  # a clock jump not (yet) confirmed by the next frame: a lone outlier timestamp
    REJECTED_INTRUDER = 11  # continues a second sender's counter sequence interleaved with the ECU's

    @property
    def is_rejected(self) -> bool:
        return self >= FrameStatus.REJECTED_DLC


class PoseStatus(IntEnum):
    """Localiser state per 50 Hz step (``PRML2_POSE.POSE_STATUS``)."""

    INITIALISING = 0  # no initial pose yet (waiting for a GNSS fix)
    GNSS_AIDED = 1  # GNSS fixes are being fused
    DEAD_RECKONING = 2  # model-driven dead reckoning (no GNSS, or GNSS outage)
    DEGRADED = 3  # a signal is out (stale, invalid or flagged by the cross-checks); substituted, or predict-only
    PREDICT_ONLY = 4  # no model output yet (window filling) or model output invalid


class InferenceStatus(IntEnum):
    """Outcome of one model inference."""

    SUCCESS = 0
    NOT_READY = 1  # window not yet full
    INVALID_OUTPUT = 2  # non-finite mean or non-positive variance
    ERROR = 3  # onnxruntime raised
