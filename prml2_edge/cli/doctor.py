"""``prml2 doctor``: check this box: CAN interfaces, ONNX Runtime providers, DBC/map/model consistency."""

from __future__ import annotations

import argparse

from prml2_edge.errors import Prml2Error

HELP = "Check this box: CAN interfaces, ONNX Runtime providers, DBC/map/model consistency."
NEEDS: tuple[tuple[str, str], ...] = ()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """No options yet: filled in by issue 9."""


def run(args: argparse.Namespace) -> int:
    raise Prml2Error("'prml2 doctor' is not available in this version yet (issue 9)")
