"""``prml2 evaluate``: evaluate models with the paper's protocol (z RMSE, 60 s dead reckoning)."""

from __future__ import annotations

import argparse

from prml2_edge.errors import Prml2Error

HELP = "Evaluate models with the paper's protocol (z RMSE, 60 s dead reckoning)."
NEEDS: tuple[tuple[str, str], ...] = (("torch", "train"),)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """No options yet: filled in by issue 5."""


def run(args: argparse.Namespace) -> int:
    raise Prml2Error("'prml2 evaluate' is not available in this version yet (issue 5)")
