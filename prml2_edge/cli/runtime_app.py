"""Command-line plumbing shared by ``prml2 replay``, ``prml2 run`` and ``prml2 demo``.

Options come from :class:`prml2_edge.config.RuntimeConfig` (``--config FILE``, see
``deploy/runtime.toml``) with command-line flags overriding it; :func:`build_pipeline` turns
the result into a :class:`~prml2_edge.runtime.pipeline.Pipeline` with its sinks.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from prml2_edge.config import RuntimeConfig, load_config, verify_pinned_model, with_overrides
from prml2_edge.errors import ConfigError
from prml2_edge.runtime.initial_pose import InitialPose
from prml2_edge.runtime.pipeline import Pipeline
from prml2_edge.runtime.status import PoseStatus


def config_from_args(args: argparse.Namespace) -> RuntimeConfig:
    """``--config`` (or the defaults) with the command-line flags applied."""
    cfg = load_config(args.config) if getattr(args, "config", None) else RuntimeConfig()
    pose: dict = {}
    if getattr(args, "initial_pose", None) and getattr(args, "initial_pose_file", None):
        raise ConfigError("give either --initial-pose or --initial-pose-file, not both")
    if getattr(args, "initial_pose", None):
        ip = InitialPose.parse(args.initial_pose)
        pose = {"source": "config", "x_m": ip.x_m, "y_m": ip.y_m, "heading_deg": ip.heading_deg}
    elif getattr(args, "initial_pose_file", None):
        pose = {"source": "file", "file": args.initial_pose_file}
    providers = None
    if getattr(args, "providers", None):
        providers = tuple(p.strip() for p in args.providers.split(",") if p.strip())
    gnss = {"time_offset_s": getattr(args, "gnss_time_offset", None)}
    if getattr(args, "gnss", None):
        gnss[getattr(args, "gnss_key", "receiver")] = args.gnss
    if getattr(args, "gnss_origin", None):
        from prml2_edge.runtime.gnss_input import LocalFrame

        gnss["origin"] = LocalFrame.parse(args.gnss_origin).origin
    can_section = {k: getattr(args, k, None) for k in ("interface", "channel", "bitrate")}
    if getattr(args, "fd", False):
        can_section["fd"] = True
    return with_overrides(
        cfg,
        can=can_section,
        signals={"map": args.map, "dbc": args.dbc, "mu": args.mu, "stale_periods": args.stale_periods,
                 "driven_axle": getattr(args, "driven_axle", None),
                 "steering_ratio": getattr(args, "steering_ratio", None)},
        model={"path": args.model, "threads": args.threads, "stride": args.stride, "providers": providers,
               "spinning": True if getattr(args, "spinning", False) else None,
               "fixed_threads": True if getattr(args, "fixed_threads", False) else None,
               "async_inference": True if getattr(args, "async_inference", False) else None},
        initial_pose=pose,
        sinks={"jsonl": args.jsonl, "csv": args.csv, "tum": args.tum, "mcap": getattr(args, "mcap", None),
               "status_interval_s": getattr(args, "status_interval", None)},
        calibration={"file": getattr(args, "calibration", None),
                     "enabled": False if getattr(args, "no_calibration", False) else None},
        gnss=gnss,
    )


def open_gnss_receiver(cfg: RuntimeConfig, args: argparse.Namespace):
    """The live receiver ``--gnss`` or ``[gnss] receiver`` names, opened but not started; None when neither does."""
    if not cfg.gnss.receiver:
        return None
    from prml2_edge.runtime.gnss_input import LocalFrame, open_live

    where = "--gnss" if getattr(args, "gnss", None) else "[gnss] receiver"
    return open_live(cfg.gnss.receiver, LocalFrame(cfg.gnss.origin), where)


def recorded_gnss(cfg: RuntimeConfig, t_first: float, t_last: float):
    """The fixes of ``--gnss FILE`` or ``[gnss] file`` as a time-ordered feed, refused in one line when they do not
    overlap the CAN log (``t_first..t_last``); None when no file is named."""
    if not cfg.gnss.file:
        return None
    from prml2_edge.runtime.gnss_input import FixFeed, LocalFrame, check_overlap, load_fixes

    fixes = load_fixes(cfg.gnss.file, LocalFrame(cfg.gnss.origin), cfg.gnss.time_offset_s)
    check_overlap(fixes, t_first, t_last, cfg.gnss.file)
    return FixFeed(fixes, cfg.gnss.file)


def initial_pose_from_config(cfg: RuntimeConfig) -> InitialPose | None:
    """The configured initial pose; None means "from the first GNSS fix"."""
    ip = cfg.initial_pose
    if ip.source == "config":
        return InitialPose(ip.x_m, ip.y_m, ip.heading_deg, source="config")
    if ip.source == "file":
        return InitialPose.from_file(ip.file)  # type: ignore[arg-type]
    return None


def file_sinks(cfg: RuntimeConfig) -> list:
    from prml2_edge.runtime.sinks import CsvSink, JsonlSink, TumSink

    sinks: list = []
    if cfg.sinks.jsonl:
        sinks.append(JsonlSink(cfg.sinks.jsonl))
    if cfg.sinks.csv:
        sinks.append(CsvSink(cfg.sinks.csv))
    if cfg.sinks.tum:
        sinks.append(TumSink(cfg.sinks.tum))
    if cfg.sinks.mcap:
        from prml2_edge.runtime.mcap_sink import McapSink

        sinks.append(McapSink(cfg.sinks.mcap))
    return sinks


def build_pipeline(cfg: RuntimeConfig, extra_sinks: list | None = None, external_gnss: bool = False) -> Pipeline:
    """Everything the config names, loaded and cross-checked (one-line errors on any mismatch)."""
    model_path = cfg.model.path
    if cfg.model.sha256 is not None:
        from prml2_edge.runtime.inference import default_model_path

        verify_pinned_model(model_path or default_model_path(), cfg.model.sha256)
    initial_pose = initial_pose_from_config(cfg)
    sinks = file_sinks(cfg) + list(extra_sinks or [])
    try:
        return Pipeline.build(map=cfg.signals.map, dbc=cfg.signals.dbc, model=model_path, threads=cfg.model.threads,
                              spinning=cfg.model.spinning, fixed_threads=cfg.model.fixed_threads,
                              providers=cfg.model.providers, stride=cfg.model.stride,
                              async_inference=cfg.model.async_inference, mu=cfg.signals.mu,
                              stale_periods=cfg.signals.stale_periods, driven_axle=cfg.signals.driven_axle,
                              steering_ratio=cfg.signals.steering_ratio, initial_pose=initial_pose, sinks=sinks,
                              trt_cache_dir=cfg.model.trt_cache_dir, trt_fp16=cfg.model.trt_fp16,
                              calibration=cfg.calibration.enabled, calibration_file=cfg.calibration.file,
                              external_gnss=external_gnss, gnss_course=cfg.gnss.course)
    except BaseException:
        for sink in sinks:
            sink.close()
        raise


def _ms(v) -> str:
    return "-" if v is None else f"{v:.2f}"


def summary_lines(summary: dict) -> list[str]:
    """The end-of-run summary for the terminal."""
    fr = summary["frames"]
    lines = [f"map {summary['map']} ({summary['dbc']}); {summary['model']}"]
    rejected = ", ".join(f"{k} {v}" for k, v in fr["rejected_by_reason"].items()) or "none"
    lines.append(f"frames: {fr['received']} received = {fr['used']} used + {fr['ignored']} ignored + "
                 f"{fr['rejected']} rejected ({rejected}); balanced: {'yes' if fr['balanced'] else 'NO'}")
    if fr["late_applied"] or fr["counter_gaps"]:
        lines.append(f"late frames applied {fr['late_applied']}, counter gaps {fr['counter_gaps']}")
    for line in summary.get("signals_missing") or []:
        lines.append(f"WARNING signal never received: {line}")
    faults = [f"{n} {fr[k]}" for k, n in (("error_frames", "error frames"), ("remote_frames", "remote frames"),
                                          ("clock_jumps", "clock jumps back")) if fr.get(k)]
    if summary.get("bus_silent_rows"):
        faults.append(f"bus silent {summary['bus_silent_rows'] / 50.0:.2f} s")
    frozen = (summary.get("signal_faults") or {}).get("frozen_episodes") or {}
    faults += [f"{name} frozen {n}x" for name, n in frozen.items()]
    if faults:
        lines.append("faults: " + ", ".join(faults))
    lines += plausibility_lines(summary)
    steps = ", ".join(f"{k} {v}" for k, v in summary["steps_by_status"].items()) or "none"
    lines.append(f"50 Hz steps: {summary['rows']} ({steps}); model used on {summary['model_used_steps']}; "
                 f"inferences {summary['inferences']} ({summary['inference_failures']} failed); "
                 f"guard fired {100.0 * summary['guard']['fire_rate']:.2f} %; EKF resets {summary['ekf_resets']}")
    rf = summary.get("realtime_factor")
    lines.append(f"drive time {summary['data_s']:.1f} s in {summary['wall_s']:.1f} s wall"
                 + (f" ({rf:.1f}x real time)" if rf else ""))
    last = summary.get("last")
    if last and last.get("x_m") is not None:
        outage = last.get("outage_s")
        lines.append(f"final pose: x {last['x_m']:.2f} m east, y {last['y_m']:.2f} m north, "
                     f"psi {math.degrees(last['psi_rad']):.1f} deg ccw from east, +-{last['pos_std_m']:.2f} m, "
                     f"{last['status']}" + (f", {outage:.1f} s since the last fix" if outage else ""))
    elif last:
        lines.append(f"final status: {last['status']} (no pose: {PoseStatus.INITIALISING.name})")
    lines += calibration_lines(summary.get("calibration") or {}, summary.get("gnss_init_rejected", 0))
    for name, s in summary.get("sinks", {}).items():
        if s.get("errors"):
            lines.append(f"WARNING {name}: {s['errors']} write errors ({s.get('last_error', '')})")
    return lines


def plausibility_lines(summary: dict) -> list[str]:
    """Signals the cross-checks took out, messages suspected of injection, GNSS fixes refused as suspect."""
    lines = []
    pl = summary.get("plausibility") or {}
    for name, first in (pl.get("first_flag") or {}).items():
        rows = (pl.get("flagged_rows") or {}).get(name, 0)
        subst = (pl.get("substituted_rows") or {}).get(name, 0)
        lines.append(f"signal check: {name} taken out {pl['flag_episodes'].get(name, 0)}x "
                     f"({rows / 50.0:.1f} s, substituted {subst / 50.0:.1f} s); first at t={first['t_s']:.2f} s: "
                     f"{first['reason']}")
    for name, why in (pl.get("flagged_now") or {}).items():
        lines.append(f"WARNING {name} still out at the end: {why}")
    for name, inj in (summary.get("injection_suspected") or {}).items():
        rate = f", {inj['observed_hz']:.0f} frames/s for a declared {inj['declared_hz']:.0f}" \
            if inj.get("observed_hz") else ""
        lines.append(f"WARNING injection suspected on {name} (ID {inj['id']}): {inj['episodes']} episode(s){rate}; "
                     f"{inj['intruder_frames_rejected']} frames of a second sender rejected")
    noise = summary.get("gnss_std_m") or {}
    if noise.get("measured") is not None and noise["used"] > noise["configured"]:
        lines.append(f"GNSS: the fixes' own noise is {noise['measured']:.2f} m per axis, more than the configured "
                     f"{noise['configured']:.2f} m: the gate, the fusion and the checks used {noise['used']:.2f} m")
    spoof = summary.get("gnss_suspect") or {}
    if spoof.get("episodes"):
        lines.append(f"WARNING GNSS suspect {spoof['episodes']}x ({spoof['fixes_refused']} fixes not fused): "
                     f"{spoof.get('first_reason', '')}")
    return lines


def calibration_lines(cal: dict, init_rejected: int = 0) -> list[str]:
    """The self-calibration part of the end-of-run summary."""
    lines = []
    if "yaw_rate_offset_dps" in cal:
        lines.append(f"calibration: CAN yaw-rate offset {cal['yaw_rate_offset_dps']:+.3f} ± "
                     f"{cal['yaw_rate_offset_std_dps']:.3f} °/s, wheel scale {cal['wheel_scale_pct']:+.2f} ± "
                     f"{cal['wheel_scale_std_pct']:.2f} %, {cal['standstill_updates']} standstill updates, yaw-rate "
                     f"resolution {cal['yaw_rate_resolution_dps']:.3g} °/s")
        if not cal["standstill_updates"]:
            lines.append("calibration: no standstill in this drive: the yaw-rate offset was learned from GNSS while "
                         "driving, and its ± is all that is known (a stop of a second or more pins it down)")
    elif cal.get("enabled") is False:
        lines.append("calibration: off (--no-calibration)")
    if cal.get("file"):
        state = "restored" if cal.get("restored") else "not restored (defaults)"
        lines.append(f"calibration file {cal['file']}: {state}, saved {cal.get('saves', 0)} time(s)"
                     + (f"; ERROR {cal['error']}" if cal.get("error") else ""))
    if init_rejected:
        lines.append(f"GNSS start-up: {init_rejected} first fix(es) contradicted by the next fix or the wheels, "
                     "restarted from the newer one")
    return lines


def calibration_save_error(pipeline: Pipeline) -> str | None:
    """One line when the calibration file the user asked for could not be saved (the run then exits non-zero)."""
    f = pipeline.calibration_file
    if f is None or f.write_error is None:
        return None
    return f"calibration file {f.path}: the calibration could not be saved ({f.write_error})"


def write_summary_json(path: str | Path, summary: dict) -> None:
    def default(obj):
        if hasattr(obj, "item"):
            return obj.item()
        return str(obj)

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(summary, indent=2, default=default) + "\n")


def report_run(pipeline: Pipeline, summary: dict, summary_json: str | None, extra_lines: list[str] = (),
               error: str | None = None) -> int:
    """End of a replay or a live run: print the summary, ``extra_lines`` and the latency per stage, write
    ``summary_json``; raise one line when the run failed (``error``, or the calibration file could not be saved)."""
    from prml2_edge.errors import DataError

    for line in [*summary_lines(summary), *extra_lines]:
        print(line)
    print("latency per stage:")
    for line in pipeline.latency.report_lines():
        print("  " + line)
    if summary_json:
        write_summary_json(summary_json, summary)
    error = error or calibration_save_error(pipeline)
    if error:
        raise DataError(error)
    return 0
