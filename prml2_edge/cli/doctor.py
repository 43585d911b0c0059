"""``prml2 doctor``: check this box: CAN interfaces, ONNX Runtime providers, DBC/map/model consistency."""

from __future__ import annotations

import argparse

HELP = ("Check this box (CAN interfaces, ONNX Runtime providers, DBC/map/model consistency); with --log, a signal "
        "map against a recorded drive (signs, scales, rates); with --data, a dataset's sign conventions.")
NEEDS: tuple[tuple[str, str], ...] = ()


# the box's settings doctor checks, each in place of the runtime config's: (flag, metavar, what it names)
_OVERRIDES: tuple[tuple[str, str | None, str], ...] = (
    ("--interface", None, "python-can interface"),
    ("--channel", None, "CAN channel"),
    ("--map", "NAME|PATH", "signal map"),
    ("--dbc", "PATH", "DBC file"),
    ("--model", "PATH", "ONNX model"),
)
# recorded data doctor checks instead of this box: (flag, metavar, what it checks)
_RECORDED: tuple[tuple[str, str, str], ...] = (
    ("--log", "LOG", "a recorded CAN log of this car (any python-can format): check the map and DBC against it: "
                     "every signal's frames, rate, range, resolution and validity, signals never seen, and signs and "
                     "scales from physics (a few minutes with some curves). Exit status 0 OK, 1 FAIL, 3 NOT "
                     "VERIFIED (a sign check could not run on this drive: drive curves)"),
    ("--data", "DIR", "a folder of ReV-StED-schema CSVs (or one CSV): check the sign conventions of the ground "
                      "truth and the onboard columns from physics"),
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="TOML", help="runtime config to check (deploy/runtime.toml)")
    for flag, metavar, what in _OVERRIDES:
        parser.add_argument(flag, metavar=metavar, help=f"{what} (overrides the config)")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    for flag, metavar, what in _RECORDED:
        parser.add_argument(flag, metavar=metavar, help=what)


def run(args: argparse.Namespace) -> int:
    import dataclasses
    import json

    from prml2_edge.config import RuntimeConfig, load_config, with_overrides
    from prml2_edge.service.doctor import FAIL, format_table, run_checks

    cfg = load_config(args.config) if args.config else RuntimeConfig()
    cfg = with_overrides(cfg, can={"interface": args.interface, "channel": args.channel},
                         signals={"map": args.map, "dbc": args.dbc}, model={"path": args.model})
    if args.log:
        return _check_log(args, cfg)
    if args.data:
        return _check_data(args)
    checks = run_checks(cfg)
    failed = [c for c in checks if c.result == FAIL]
    if args.json:
        print(json.dumps({"ok": not failed, "checks": [dataclasses.asdict(c) for c in checks]}))
    else:
        print(format_table(checks))
        print(f"\n{len(checks) - len(failed)} of {len(checks)} checks passed" + (" (see the hints)" if failed else ""))
    return 1 if failed else 0


def _check_log(args: argparse.Namespace, cfg) -> int:
    import json

    from prml2_edge.service.log_doctor import EXIT_CODES, check_log_file, format_report

    report = check_log_file(args.log, cfg.signals.map, cfg.signals.dbc)
    if args.json:
        print(json.dumps(report.as_dict()))
    else:
        print(format_report(report))
    return EXIT_CODES[report.verdict]  # OK 0, FAIL 1, NOT VERIFIED 3 (a check could not run on this drive)


def _check_data(args: argparse.Namespace) -> int:
    import json

    from prml2_edge.data.conventions import format_findings
    from prml2_edge.data.revsted import check_folder

    results = check_folder(args.data)
    failed = [r for r in results if r.result == "FAIL"]
    if args.json:
        print(json.dumps({"ok": not failed, "checks": [r.as_dict() for r in results]}))
    else:
        print(format_findings(results))
    return 1 if failed else 0
