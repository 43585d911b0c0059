"""Command-line options shared by the runtime commands (argparse only: cheap to import)."""

from __future__ import annotations

import argparse

from prml2_edge.config import DEFAULT_STRIDE, DRIVEN_AXLES


def add_pipeline_arguments(parser: argparse.ArgumentParser) -> None:
    """Options every runtime command shares (map, DBC, model, guard, initial pose, sinks)."""
    g = parser.add_argument_group("vehicle and model")
    g.add_argument("--config", metavar="TOML", help="runtime config file (deploy/runtime.toml); flags override it")
    g.add_argument("--map", metavar="NAME|PATH",
                   help="signal map: prml2_onboard (default), vw_mqb, hyundai_2015_ccan, or a map .toml")
    g.add_argument("--dbc", metavar="PATH", help="DBC file (default: the one the map names)")
    g.add_argument("--model", metavar="PATH", help="ONNX model (default: the shipped model)")
    g.add_argument("--mu", type=float, help="road friction for the physics guard (default 1.0; <= 0.5 low-mu)")
    g.add_argument("--driven-axle", choices=DRIVEN_AXLES,
                   help="the car's driven axle: front (FWD, default), rear (RWD) or all (AWD); the wheel-speed cue "
                        "is taken from the other axle, whose wheels do not spin up with the traction")
    g.add_argument("--steering-ratio", type=float,
                   help="steering wheel angle over road wheel angle (default 15; front-wheel steer corrections)")
    g.add_argument("--threads", type=int, help="ONNX Runtime intra-op threads (default 1); 2 or more is an upper "
                   "bound: a model that runs faster on one thread on this machine gets one (logged)")
    g.add_argument("--fixed-threads", action="store_true",
                   help="run the model on --threads even where one intra-op thread is faster")
    g.add_argument("--spinning", action="store_true",
                   help="with --threads >= 2: ONNX Runtime worker threads busy-wait between parallel sections "
                        "instead of sleeping (tighter p99 latency, more CPU)")
    g.add_argument("--stride", type=int, help=f"a new model window every N 50 Hz steps (default {DEFAULT_STRIDE})")
    g.add_argument("--async-inference", action="store_true",
                   help="run the model on a worker thread so that no 50 Hz step waits for it; its output is used "
                        "when it arrives (for a model slower than the 20 ms step)")
    g.add_argument("--providers", metavar="LIST",
                   help="execution providers in order, comma separated (default tensorrt,cuda,cpu)")
    g.add_argument("--stale-periods", type=float,
                   help="a signal is invalid after this many of its periods without a frame (default 3)")
    c = parser.add_argument_group("self-calibration (yaw-rate offset, wheel scale)")
    c.add_argument("--calibration", metavar="FILE",
                   help="calibration state file: restored at start when it matches this vehicle (map and DBC), "
                        "saved every minute of drive time and at the end")
    c.add_argument("--no-calibration", action="store_true",
                   help="switch the filter's calibration states and raw cues off (the paper's filter)")
    p = parser.add_argument_group("initial pose (default: first GNSS fix on the bus)")
    p.add_argument("--initial-pose", metavar="X,Y,HEADING_DEG",
                   help="east [m], north [m], heading clockwise from north [deg]")
    p.add_argument("--initial-pose-file", metavar="PATH", help="JSON/TOML file with x_m, y_m, heading_deg")
    s = parser.add_argument_group("outputs")
    s.add_argument("--jsonl", metavar="PATH", help="write every 50 Hz step as JSON lines")
    s.add_argument("--csv", metavar="PATH", help="write every 50 Hz step as CSV")
    s.add_argument("--tum", metavar="PATH", help="write the trajectory in TUM format (timestamp x y z qx qy qz qw)")
    s.add_argument("--mcap", metavar="FILE",
                   help="write an MCAP file for Foxglove Studio: pose, transform, covariance, z with sigma, signals "
                        "with validity, GNSS fixes, status and flags (readable up to its last 1 s chunk after a crash)")
    s.add_argument("--summary-json", metavar="PATH", help="write the end-of-run summary as JSON")


def add_gnss_arguments(parser: argparse.ArgumentParser, live: bool) -> None:
    """``--gnss`` and its options: fixes from a receiver (live) or a recorded file (replay); each overrides its
    ``[gnss]`` key of the config (``receiver`` or ``file``, ``origin``, ``time_offset_s``)."""
    g = parser.add_argument_group("GNSS fixes from a receiver (not the CAN bus)")
    if live:
        g.add_argument("--gnss", metavar="SOURCE",
                       help="gpsd://HOST[:PORT] (gpsd's JSON protocol, port 2947) or a serial NMEA receiver "
                            "(/dev/ttyACM0, serial:///dev/ttyUSB0?baud=38400); fixes are stamped on receipt")
    else:
        g.add_argument("--gnss", metavar="FILE",
                       help="fixes merged with the CAN log by time: an NMEA log (GGA/RMC, UTC times), a CSV "
                            "(t_s,x_m,y_m[,heading_deg]) or a TUM file (local metres; the quaternion's yaw is the "
                            "course)")
        g.add_argument("--gnss-time-offset", type=float, metavar="S",
                       help="seconds added to the fixes' times when their clock differs from the CAN log's "
                            "(default 0)")
    g.add_argument("--gnss-origin", metavar="LAT,LON",
                   help="origin of the local east/north frame for latitude/longitude (default: the first fix)")
    # which [gnss] key of the config --gnss overrides: the receiver for a live run, the file for a replay
    parser.set_defaults(gnss_key="receiver" if live else "file")
