"""``prml2 doctor``: check this box: CAN interfaces, ONNX Runtime providers, DBC/map/model consistency."""

from __future__ import annotations

import argparse

HELP = "Check this box: CAN interfaces, ONNX Runtime providers, DBC/map/model consistency."
NEEDS: tuple[tuple[str, str], ...] = ()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="TOML", help="runtime config to check (deploy/runtime.toml)")
    parser.add_argument("--interface", help="python-can interface (overrides the config)")
    parser.add_argument("--channel", help="CAN channel (overrides the config)")
    parser.add_argument("--map", metavar="NAME|PATH", help="signal map (overrides the config)")
    parser.add_argument("--dbc", metavar="PATH", help="DBC file (overrides the config)")
    parser.add_argument("--model", metavar="PATH", help="ONNX model (overrides the config)")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of the table")


def run(args: argparse.Namespace) -> int:
    import dataclasses
    import json

    from prml2_edge.config import RuntimeConfig, load_config, with_overrides
    from prml2_edge.service.doctor import FAIL, format_table, run_checks

    cfg = load_config(args.config) if args.config else RuntimeConfig()
    cfg = with_overrides(cfg, can={"interface": args.interface, "channel": args.channel},
                         signals={"map": args.map, "dbc": args.dbc}, model={"path": args.model})
    checks = run_checks(cfg)
    failed = [c for c in checks if c.result == FAIL]
    if args.json:
        print(json.dumps({"ok": not failed, "checks": [dataclasses.asdict(c) for c in checks]}))
    else:
        print(format_table(checks))
        print(f"\n{len(checks) - len(failed)} of {len(checks)} checks passed" + (" (see the hints)" if failed else ""))
    return 1 if failed else 0
