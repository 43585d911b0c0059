"""``prml2 export``: export a trained checkpoint to ONNX for the edge runtime."""

from __future__ import annotations

import argparse

from prml2_edge.errors import Prml2Error

HELP = "Export a trained checkpoint to ONNX for the edge runtime."
NEEDS: tuple[tuple[str, str], ...] = (("torch", "train"), ("onnx", "train"))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """No options yet: filled in by issue 6."""


def run(args: argparse.Namespace) -> int:
    raise Prml2Error("'prml2 export' is not available in this version yet (issue 6)")
