"""``prml2 encode``: encode the onboard signals of a CSV drive into a CAN log with a DBC.

``prml2 encode CSV [--dbc F] [--map M] --out drive.log [--gnss-seconds S]``; the log
format follows the extension (.log candump, .asc, .blf, .csv, .trc; .mf4 with the mf4 extra).
"""

from __future__ import annotations

import argparse

HELP = "Encode the onboard signals of a CSV drive into a CAN log with a DBC."
NEEDS: tuple[tuple[str, str], ...] = ()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("csv", help="ReV-StED-schema CSV drive (simulated or recorded)")
    parser.add_argument("--out", required=True,
                        help="output CAN log: .log (candump), .asc, .blf, .csv, .trc, .mf4 (ASAM MDF4, the mf4 extra)")
    parser.add_argument("--dbc", default=None, help="DBC file (default: the one the signal map names)")
    parser.add_argument("--map", default=None, help="signal map TOML (default: the shipped prml2_onboard map)")
    parser.add_argument("--gnss-seconds", type=float, default=0.0,
                        help="also send 10 Hz GNSS fixes for the first S seconds (needs ground truth in the CSV)")
    parser.add_argument("--channel", default="vcan0", help="channel name written to the log (default vcan0)")


def run(args: argparse.Namespace) -> int:
    import time

    from prml2_edge.can.encode import encode_drive_to_log
    from prml2_edge.data.revsted import load_drive
    from prml2_edge.errors import ConfigError

    if args.gnss_seconds < 0:
        raise ConfigError(f"--gnss-seconds must be >= 0, got {args.gnss_seconds}")
    t0 = time.monotonic()
    drive = load_drive(args.csv)
    if args.gnss_seconds > 0 and drive.pose_gt is None:
        raise ConfigError(f"{args.csv}: --gnss-seconds needs the ground-truth pose columns, which the file lacks")
    stats = encode_drive_to_log(drive, args.out, signal_map_path=args.map, dbc_path=args.dbc,
                                gnss_seconds=args.gnss_seconds, progress=True, channel=args.channel)
    per = ", ".join(f"{k} {v}" for k, v in stats["per_message"].items())
    print(f"wrote {stats['frames']} frames ({stats['duration_s']:.1f} s of driving) to {stats['out']} "
          f"in {time.monotonic() - t0:.1f} s")
    print(f"  DBC {stats['dbc']}; per message: {per}; GNSS fixes {stats['gnss_frames']}")
    if drive.repairs:
        print(f"  loader repairs: {drive.repairs}")
    if stats["clipped"]:
        print(f"  values clipped to the DBC range: {stats['clipped']}")
    if stats["invalid"]:
        print(f"  non-finite samples sent invalid: {stats['invalid']}")
    return 0
