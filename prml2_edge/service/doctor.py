"""``prml2 doctor``: check an edge box before it goes into a car.

Each check returns a :class:`Check` (PASS, WARN or FAIL, a detail line and, for problems, a
hint saying what to do). Nothing here raises: a check that cannot run is a FAIL with the reason.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from prml2_edge.config import RuntimeConfig, verify_pinned_model
from prml2_edge.errors import Prml2Error, first_line

PASS, WARN, FAIL = "PASS", "WARN", "FAIL"
ARPHRD_CAN = 280  # /sys/class/net/<if>/type of a CAN interface
DEADLINE_MS = 20.0  # one 50 Hz step


@dataclass(frozen=True)
class Check:
    name: str
    result: str  # PASS | WARN | FAIL
    detail: str
    hint: str = ""


def can_links(sys_class_net: Path = Path("/sys/class/net")) -> dict[str, str]:
    """CAN network interfaces of this kernel and their operstate (``up``, ``down``, ...)."""
    links = {}
    if not sys_class_net.is_dir():
        return links
    for dev in sorted(sys_class_net.iterdir()):
        try:
            if int((dev / "type").read_text().strip()) != ARPHRD_CAN:
                continue
            links[dev.name] = (dev / "operstate").read_text().strip()
        except (OSError, ValueError):
            continue
    return links


def check_python_can() -> Check:
    import can

    names = sorted(can.interfaces.VALID_INTERFACES)
    return Check("python-can interfaces", PASS, f"python-can {can.__version__}: {len(names)} interfaces "
                 f"({', '.join(n for n in names if n in ('socketcan', 'pcan', 'kvaser', 'vector', 'virtual'))}, ...)")


def check_can_link(cfg: RuntimeConfig, sys_class_net: Path = Path("/sys/class/net")) -> Check:
    interface, channel = cfg.can.interface, cfg.can.channel
    if interface == "virtual":
        return Check("CAN link", PASS, f"virtual bus {channel!r} (bench testing; no hardware)")
    if interface != "socketcan":
        try:
            import can

            bus = can.Bus(interface=interface, channel=channel, bitrate=cfg.can.bitrate)
            bus.shutdown()
            return Check("CAN link", PASS, f"{interface} channel {channel} opens")
        except Exception as exc:
            return Check("CAN link", FAIL, f"{interface} channel {channel}: {first_line(exc, 200)}",
                         f"check the adapter and its driver for python-can's {interface!r} interface")
    links = can_links(sys_class_net)
    if channel not in links:
        found = ", ".join(f"{k} ({v})" for k, v in links.items()) or "none"
        return Check("CAN link", FAIL, f"no SocketCAN interface {channel!r} (CAN interfaces here: {found})",
                     f"sudo deploy/can-setup.sh {channel} (or vcan0 for bench tests); on an Orin enable mttcan")
    state = links[channel]
    if state not in ("up", "unknown"):
        return Check("CAN link", FAIL, f"{channel} is {state}", f"sudo deploy/can-setup.sh {channel}")
    return Check("CAN link", PASS, f"{channel} is {state}")


def check_providers(cfg: RuntimeConfig) -> Check:
    import onnxruntime as ort

    from prml2_edge.runtime.providers import select_providers

    try:
        choice = select_providers(cfg.model.providers, trt_cache_dir=cfg.model.trt_cache_dir,
                                  trt_fp16=cfg.model.trt_fp16)
    except Prml2Error as exc:
        return Check("ONNX Runtime providers", FAIL, str(exc), "fix [model] providers")
    detail = f"onnxruntime {ort.__version__}: {', '.join(ort.get_available_providers())}; will use {choice.chosen}"
    if choice.chosen == "CPUExecutionProvider" and choice.skipped:
        return Check("ONNX Runtime providers", WARN, detail,
                     "GPU providers not offered: install onnxruntime-gpu for JetPack (deploy/INSTALL_JETSON.md)")
    return Check("ONNX Runtime providers", PASS, detail)


def check_map_and_dbc(cfg: RuntimeConfig) -> Check:
    from prml2_edge.can.signal_map import load_map_and_dbc, resolve_map

    try:
        smap, db, dbc_path = load_map_and_dbc(resolve_map(cfg.signals.map), cfg.signals.dbc)
    except Prml2Error as exc:
        return Check("DBC and signal map", FAIL, first_line(exc, 200), "fix [signals] map/dbc (see dbc/maps/*.toml)")
    return Check("DBC and signal map", PASS, f"map {smap.name} on {dbc_path.name}: 9 signals in "
                 f"{len(smap.message_names)} messages, GNSS {'yes' if smap.gnss else 'no'}")


def check_model(cfg: RuntimeConfig, runs: int = 50) -> list[Check]:
    from prml2_edge.runtime.inference import OnnxModel, default_model_path
    from prml2_edge.runtime.status import InferenceStatus

    try:
        path = Path(cfg.model.path) if cfg.model.path else default_model_path()
        digest = verify_pinned_model(path, cfg.model.sha256)
        model = OnnxModel(path, threads=cfg.model.threads, providers=cfg.model.providers,
                          spinning=cfg.model.spinning, fixed_threads=cfg.model.fixed_threads,
                          trt_cache_dir=cfg.model.trt_cache_dir, trt_fp16=cfg.model.trt_fp16)
    except (Prml2Error, OSError) as exc:
        return [Check("model", FAIL, first_line(exc, 200),
                      "export a model with 'prml2 export' or fix [model] path/sha256")]
    pin = "pinned" if cfg.model.sha256 else "not pinned"
    checks = [Check("model", PASS, f"{path.name}: preset {model.metadata.preset}, schema "
                    f"{model.metadata.schema_hash}, sha256 {digest[:12]}... ({pin})")]
    rng = np.random.default_rng(0)
    window = (np.asarray(model.metadata.norm_mean) + rng.standard_normal((1, model.window_len, 9))
              * np.asarray(model.metadata.norm_std)).astype(np.float32)
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        status = model.step(window)
        times.append((time.perf_counter() - t0) * 1e3)
        if status != InferenceStatus.SUCCESS:
            return checks + [Check("warm inference", FAIL, f"inference returned {status.name}: {model.last_error}",
                                   "re-export the model; check the provider")]
    p50, p99 = np.percentile(times, [50, 99])
    detail = f"{runs} runs after warm-up: p50 {p50:.2f} ms, p99 {p99:.2f} ms on {model.providers[0]}"
    if p99 > DEADLINE_MS:
        return checks + [Check("warm inference", FAIL, detail + f" (> {DEADLINE_MS:.0f} ms: cannot keep 50 Hz)",
                               "use a GPU provider, int8 (prml2 export --int8), more threads or --stride 2")]
    return checks + [Check("warm inference", PASS, detail)]


def run_checks(cfg: RuntimeConfig) -> list[Check]:
    checks = [check_python_can(), check_can_link(cfg), check_providers(cfg), check_map_and_dbc(cfg)]
    checks += check_model(cfg)
    return checks


def format_table(checks: list[Check]) -> str:
    width = max(len(c.name) for c in checks)
    lines = [f"{'check':<{width}}  result  detail", f"{'-' * width}  ------  ------"]
    for c in checks:
        lines.append(f"{c.name:<{width}}  {c.result:<6}  {c.detail}")
        if c.hint and c.result != PASS:
            lines.append(f"{'':<{width}}          hint: {c.hint}")
    return "\n".join(lines)
