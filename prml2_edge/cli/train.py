"""``prml2 train``: train a PRML2 model (NLL pretraining, then fine-tuning through the differentiable EKF)."""

from __future__ import annotations

import argparse

from prml2_edge.errors import Prml2Error

HELP = "Train a PRML2 model (NLL pretraining, then fine-tuning through the differentiable EKF)."
NEEDS: tuple[tuple[str, str], ...] = (("torch", "train"),)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """No options yet: filled in by issue 4."""


def run(args: argparse.Namespace) -> int:
    raise Prml2Error("'prml2 train' is not available in this version yet (issue 4)")
