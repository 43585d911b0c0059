"""Moved to :mod:`prml2_edge.evaluation.osd` (torch-free); this alias remains only for
``evaluation/protocol.py``, which is being rewritten elsewhere. Import from ``evaluation.osd``."""

from prml2_edge.evaluation.osd import StandstillBias, drive_bias

__all__ = ["StandstillBias", "drive_bias"]
