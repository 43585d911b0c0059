"""Entry point of the ``prml2`` console script."""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import logging
import sys
from types import ModuleType

from prml2_edge import __version__
from prml2_edge.errors import MissingExtraError, Prml2Error

# Subcommand name -> module under prml2_edge.cli (order is the order in --help).
COMMANDS: dict[str, str] = {
    "demo": "demo",
    "simulate": "simulate",
    "encode": "encode",
    "train": "train",
    "export": "export",
    "evaluate": "evaluate",
    "replay": "replay",
    "fleet": "fleet",
    "run": "run_live",
    "bench": "bench",
    "doctor": "doctor",
}


def module_available(name: str) -> bool:
    """True when ``name`` can be imported (honours ``sys.modules[name] = None`` blocks)."""
    if name in sys.modules:
        return sys.modules[name] is not None
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        return False


def _load(command: str) -> ModuleType:
    return importlib.import_module(f"prml2_edge.cli.{COMMANDS[command]}")


def _missing_extra(mod: ModuleType, command: str) -> MissingExtraError | None:
    for module_name, extra in getattr(mod, "NEEDS", ()):
        if not module_available(module_name):
            return MissingExtraError(module_name, extra, command)
    return None


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="prml2",
        description="PRML2 proprioceptive localisation from onboard CAN signals.",
    )
    parser.add_argument("--version", action="version", version=f"prml2-edge {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks and debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for command in COMMANDS:
        mod = _load(command)
        help_text = mod.HELP
        extras = sorted({extra for _, extra in getattr(mod, "NEEDS", ())})
        if extras:
            help_text += f" [needs extra: {', '.join(extras)}]"
        p = sub.add_parser(command, help=help_text, description=mod.HELP)
        p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help="show tracebacks")
        mod.add_arguments(p)
        p.set_defaults(_module=mod)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv
    logging.basicConfig(
        level=logging.DEBUG if debug else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s" if debug else "%(message)s",
    )
    if not debug:  # asammdf (for .mf4 logs) imports numexpr, which logs its thread count at INFO
        logging.getLogger("numexpr").setLevel(logging.WARNING)
    try:
        # A subcommand whose extra is missing says so in one line, even for --help.
        first = next((a for a in argv if not a.startswith("-")), None)
        if first in COMMANDS:
            missing = _missing_extra(_load(first), first)
            if missing is not None:
                raise missing
        parser = build_parser()
        args = parser.parse_args(argv)
        if args.command is None:
            parser.print_help()
            return 2
        return int(args._module.run(args) or 0)
    except KeyboardInterrupt:
        print("prml2: interrupted", file=sys.stderr)
        return 130
    except Prml2Error as exc:
        if debug:
            raise
        print(f"prml2: error: {exc}", file=sys.stderr)
        return 1
    except (OSError, ValueError) as exc:
        if debug:
            raise
        print(f"prml2: error: {exc} (run with --debug for the traceback)", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
