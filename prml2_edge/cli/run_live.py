"""``prml2 run``: run the localiser on a live CAN interface."""

from __future__ import annotations

import argparse

from prml2_edge.errors import Prml2Error

HELP = "Run the localiser on a live CAN interface."
NEEDS: tuple[tuple[str, str], ...] = ()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """No options yet: filled in by issue 6."""


def run(args: argparse.Namespace) -> int:
    raise Prml2Error("'prml2 run' is not available in this version yet (issue 6)")
