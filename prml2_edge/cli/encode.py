"""``prml2 encode``: encode the onboard signals of a CSV drive into a CAN log with a DBC."""

from __future__ import annotations

import argparse

from prml2_edge.errors import Prml2Error

HELP = "Encode the onboard signals of a CSV drive into a CAN log with a DBC."
NEEDS: tuple[tuple[str, str], ...] = ()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """No options yet: filled in by issue 3."""


def run(args: argparse.Namespace) -> int:
    raise Prml2Error("'prml2 encode' is not available in this version yet (issue 3)")
