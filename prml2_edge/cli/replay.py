"""``prml2 replay``: replay a recorded CAN log through a virtual bus into the runtime."""

from __future__ import annotations

import argparse

HELP = "Replay a recorded CAN log through a virtual bus into the runtime."
NEEDS: tuple[tuple[str, str], ...] = ()


# what the replay writes or compares besides the runtime's sinks: (flag, metavar, help)
_WRITES: tuple[tuple[str, str, str], ...] = (
    ("--can-out", "PATH", "write PRML2_POSE/PRML2_DYNAMICS/PRML2_POSE_STD frames to this CAN log"),
    ("--truth", "CSV", "ReV-StED-schema CSV of the same drive with ground truth (e.g. the one prml2 encode read): "
                       "print the outage error, drift and how often the error lies inside the reported 1/2/3-sigma "
                       "ellipses"),
    ("--truth-tum", "PATH", "with --truth: write the ground truth at the replayed steps' times in TUM format, to "
                            "score --tum with evo (evo_ape tum PATH pose.tum)"),
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from prml2_edge.cli.runtime_args import add_pipeline_arguments

    parser.add_argument("log", metavar="LOG",
                        help="CAN log: .log (candump), .asc, .blf, .trc, .csv, .mf4 (ASAM MDF4, the mf4 extra)")
    parser.add_argument("--realtime", action="store_true", help="keep the log's original timing")
    parser.add_argument("--speed", type=float, default=1.0, help="playback speed factor with --realtime (default 1)")
    parser.add_argument("--batch", action="store_true",
                        help="offline schedule: read and assemble the log directly, run every model window ahead of "
                             "the filter in worker processes; same poses as the streaming replay (not with --realtime)")
    parser.add_argument("--workers", type=int, default=None,
                        help="with --batch: inference worker processes (default: this machine's CPUs; 1: no processes)")
    parser.add_argument("--batch-size", type=int, default=1,
                        help="with --batch: windows per ONNX Runtime call (default 1, bitwise the streaming poses; > 1 "
                             "needs a graph with a free batch dimension)")
    for flag, metavar, what in _WRITES:
        parser.add_argument(flag, metavar=metavar, help=what)
    add_pipeline_arguments(parser)
    from prml2_edge.cli.runtime_args import add_gnss_arguments

    add_gnss_arguments(parser, live=False)


def run(args: argparse.Namespace) -> int:
    from prml2_edge.cli.runtime_app import build_pipeline, config_from_args, recorded_gnss, report_run
    from prml2_edge.errors import DataError
    from prml2_edge.runtime.source import scan_log

    cfg = config_from_args(args)
    _check_options(args)
    # A broken or cut-off log is still replayed up to the problem: every pose it yields is written,
    # then the problem is reported (one line, non-zero exit).
    n_frames, t_first, t_last, problem = scan_log(args.log)
    if n_frames == 0:
        raise DataError(problem or f"{args.log}: CAN log holds no frames")
    extra, memory, truth = _extra_sinks(args)
    feed = recorded_gnss(cfg, t_first, t_last)  # --gnss FILE or [gnss] file
    pipeline = build_pipeline(cfg, extra, external_gnss=feed is not None)
    if feed is not None:
        pipeline.add_gnss_source(feed)
        print(f"GNSS: {len(feed.fixes)} fixes from {feed.describe}, merged by time")
    print(f"replaying {args.log}: {n_frames} frames, {t_last - t_first:.1f} s"
          f"{' in real time' if args.realtime else ''}{' (offline schedule)' if args.batch else ''}; "
          f"{pipeline.model.describe()}"
          + (" (the log is damaged: replaying the frames before the damage)" if problem else ""))
    try:
        error = _replay(pipeline, args, n_frames)
    finally:
        pipeline.close()
    summary = pipeline.summary()
    if feed is not None:
        summary["gnss_input"] = feed.summary()
    extra_lines = _offline_lines(pipeline, summary) if args.batch else []
    if truth is not None:
        extra_lines += _truth_lines(args, memory, truth, summary)
    # A replay that could not do its job fails: a model that never ran means a pose from nothing but the filter.
    return report_run(pipeline, summary, args.summary_json, extra_lines,
                      error=error or problem or pipeline.model_never_ran())


def _check_options(args: argparse.Namespace) -> None:
    """Refuse option combinations that cannot work together, before the log is read."""
    from prml2_edge.errors import ConfigError

    if args.truth_tum and not args.truth:
        raise ConfigError("--truth-tum needs --truth DRIVE.csv (the drive with the ground truth)")
    if args.batch and args.realtime:
        raise ConfigError("--batch replays as fast as it can; drop --realtime (or --batch)")
    if not args.batch and (args.workers is not None or args.batch_size != 1):
        raise ConfigError("--workers and --batch-size go with --batch")


def _extra_sinks(args: argparse.Namespace) -> tuple[list, object, object]:
    """The sinks besides the configured ones: ``--can-out``, and with ``--truth`` a memory of every step.

    Returns ``(sinks, memory sink or None, truth drive or None)``.
    """
    extra: list = []
    if args.can_out:
        from pathlib import Path

        import can

        from prml2_edge.runtime.sinks import CanSink

        Path(args.can_out).parent.mkdir(parents=True, exist_ok=True)
        extra.append(CanSink(can.Logger(args.can_out)))
    memory = truth = None
    if args.truth:
        from prml2_edge.data.revsted import load_drive
        from prml2_edge.runtime.pipeline import MemorySink

        truth = load_drive(args.truth, require_ground_truth=True)
        memory = MemorySink()
        extra.append(memory)
    return extra, memory, truth


def _replay(pipeline, args: argparse.Namespace, n_frames: int):
    """Run the log through the pipeline (streaming, or the offline schedule with ``--batch``); the log's error."""
    from prml2_edge.progress import Progress

    if args.batch:
        from prml2_edge.runtime.offline import run_offline

        with Progress(n_frames, desc="replay", unit="frames") as bar:
            return run_offline(pipeline, args.log, batch=args.batch_size, workers=args.workers,
                               progress=bar).problem
    from prml2_edge.runtime.pipeline import run_source
    from prml2_edge.runtime.source import LogReplay

    with LogReplay(args.log, realtime=args.realtime, speed=args.speed) as source, \
            Progress(n_frames, desc="replay", unit="frames") as bar:
        run_source(pipeline, source, progress=bar)
        return source.error


def _offline_lines(pipeline, summary: dict) -> list[str]:
    """The offline schedule's figures: into the summary, and one line for the report."""
    off = summary["offline"] = pipeline.offline
    t = off["timing_s"]
    if off.get("in_step"):
        return [f"offline: {off['windows']} windows, each in the filter's step ({off['in_step']}); decode+assemble "
                f"{t['decode_assemble']:.1f} s, filter and inference {t['filter']:.1f} s"]
    return [f"offline: {off['windows']} windows, {off['workers']} worker(s), {off['batch']} per call; "
            f"decode+assemble {t['decode_assemble']:.1f} s, filter {t['filter']:.1f} s, inference "
            f"{t['inference_workers']:.1f} s (summed over workers), filter waited "
            f"{t['filter_waited_for_inference']:.1f} s"]


def _truth_lines(args: argparse.Namespace, memory, truth, summary: dict) -> list[str]:
    """Score the replayed steps against ``--truth`` (into the summary; ``--truth-tum`` written); the report lines."""
    from prml2_edge.runtime.demo import compare_with_truth, truth_lines

    arrays = memory.arrays()
    summary["truth"] = compare_with_truth(arrays, truth)
    if args.truth_tum:
        from prml2_edge.evaluation.tum import write_tum
        from prml2_edge.runtime.demo import align_with_truth

        true_pose, _, ok = align_with_truth(arrays, truth)
        write_tum(args.truth_tum, arrays["t_s"][ok], true_pose[ok])
    return truth_lines(summary["truth"])
