"""``prml2 simulate``: simulate drives and write ReV-StED-schema CSV files."""

from __future__ import annotations

import argparse

from prml2_edge.errors import Prml2Error

HELP = "Simulate drives and write ReV-StED-schema CSV files."
NEEDS: tuple[tuple[str, str], ...] = ()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """No options yet: filled in by issue 3."""


def run(args: argparse.Namespace) -> int:
    raise Prml2Error("'prml2 simulate' is not available in this version yet (issue 3)")
