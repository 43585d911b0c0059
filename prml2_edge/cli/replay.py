"""``prml2 replay``: replay a recorded CAN log through a virtual bus into the runtime."""

from __future__ import annotations

import argparse

from prml2_edge.errors import Prml2Error

HELP = "Replay a recorded CAN log through a virtual bus into the runtime."
NEEDS: tuple[tuple[str, str], ...] = ()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """No options yet: filled in by issue 6."""


def run(args: argparse.Namespace) -> int:
    raise Prml2Error("'prml2 replay' is not available in this version yet (issue 6)")
