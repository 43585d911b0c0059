"""``prml2 run``: run the localiser on a live CAN interface."""

from __future__ import annotations

import argparse

HELP = "Run the localiser on a live CAN interface."
NEEDS: tuple[tuple[str, str], ...] = ()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from prml2_edge.cli.runtime_args import add_pipeline_arguments

    g = parser.add_argument_group("CAN interface")
    g.add_argument("--interface", help="python-can interface: socketcan (default), pcan, kvaser, vector, virtual, ...")
    g.add_argument("--channel", help="channel, e.g. can0 (default), PCAN_USBBUS1")
    g.add_argument("--bitrate", type=int, help="bit rate for interfaces that set it themselves (pcan, kvaser)")
    g.add_argument("--fd", action="store_true", help="CAN FD")
    g.add_argument("--can-out", action="store_true",
                   help="send PRML2_POSE/PRML2_DYNAMICS/PRML2_POSE_STD back on the bus every 50 Hz step")
    g.add_argument("--status-interval", type=float, help="seconds between status lines (default 5; 0: none)")
    g.add_argument("--duration", type=float, help="stop after this many seconds (default: until SIGINT/SIGTERM)")
    add_pipeline_arguments(parser)
    from prml2_edge.cli.runtime_args import add_gnss_arguments

    add_gnss_arguments(parser, live=True)


def run(args: argparse.Namespace) -> int:
    import logging
    import signal
    import threading
    import time

    from prml2_edge.cli.runtime_app import build_pipeline, config_from_args, open_gnss_receiver, report_run
    from prml2_edge.runtime.pipeline import run_source
    from prml2_edge.runtime.sinks import CanSink
    from prml2_edge.runtime.source import BusSource, open_bus
    from prml2_edge.service.notify import SystemdNotifier

    log = logging.getLogger("prml2.run")
    cfg = config_from_args(args)
    gnss = open_gnss_receiver(cfg, args)
    pipeline = build_pipeline(cfg, external_gnss=gnss is not None)
    if gnss is not None:
        pipeline.add_gnss_source(gnss.start())
    bus = open_bus(cfg.can.interface, cfg.can.channel, bitrate=cfg.can.bitrate, fd=cfg.can.fd)
    if args.can_out or cfg.sinks.can_out:
        pipeline.sinks.append(CanSink(bus))
    source = BusSource(bus)
    notifier = SystemdNotifier()
    stop = threading.Event()

    def on_signal(signum, _frame) -> None:
        stop.set()

    previous = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, on_signal)
    t_start = time.monotonic()
    interval = cfg.sinks.status_interval_s
    next_status = t_start + interval if interval > 0 else float("inf")

    def on_idle() -> None:
        nonlocal next_status
        notifier.maybe_ping()
        now = time.monotonic()
        if args.duration is not None and now - t_start >= args.duration:
            stop.set()
        if now >= next_status:
            line = pipeline.status_line()
            log.info(line)
            notifier.status(line)
            next_status = now + interval

    print(f"listening on {cfg.can.interface} {cfg.can.channel}; {pipeline.model.describe()}; "
          f"map {pipeline.signal_map.name}; Ctrl-C to stop", flush=True)
    notifier.ready(f"listening on {cfg.can.channel}")
    try:
        run_source(pipeline, source, should_stop=stop.is_set, on_idle=on_idle)
    finally:
        notifier.stopping()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        pipeline.close()
        source.close()
        notifier.close()
        if gnss is not None:
            gnss.close()
    summary = pipeline.summary()
    summary["bus_errors"] = source.errors
    if gnss is not None:
        summary["gnss_input"] = gnss.summary()
    extra_lines = [f"bus receive errors: {source.errors} (last: {source.last_error})"] if source.errors else []
    # Like a replay, a live run in which the model never ran failed: its poses came from the filter alone.
    return report_run(pipeline, summary, args.summary_json, extra_lines,
                      error=live_failure(pipeline, cfg.can, time.monotonic() - t_start))


def live_failure(pipeline, can_cfg, wall_s: float) -> str | None:
    """Why a live run could not do its job (one line), or None: no frame on the bus, or the model never ran."""
    if pipeline.stats.received == 0:
        return (f"no CAN frame arrived on {can_cfg.interface} {can_cfg.channel} in {wall_s:.1f} s, so the model "
                "never ran: check that the interface is up (ip -details link show), the channel name and that the "
                "car's bus is connected (ignition on)")
    return pipeline.model_never_ran("the run")
