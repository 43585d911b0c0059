"""Runtime configuration: frozen dataclasses loaded from TOML, validated on load.

Unknown keys and wrong types are refused with the key's full name (``[can] bitrat``),
so a typo never silently falls back to a default. ``deploy/runtime.toml`` lists every
option with its default. Command-line flags override file values.
"""

from __future__ import annotations

import dataclasses
import hashlib
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path

from prml2_edge.errors import ConfigError, ModelError, reject_unknown_keys

# The model runs every DEFAULT_STRIDE-th 50 Hz step (10 Hz); the filter fuses the raw cues and the held newest
# output in between. Chosen on the validation split (issue 29, docs/benchmarks.md "Model rate"): the lowest
# model rate whose paired 60 s RMSE interval against stride 1 contains 0 and whose 2-sigma coverage stays in
# 75-95 % (stride 10 fell to 73 %). A fifth of the inference cost of stride 1.
DEFAULT_STRIDE = 5


@dataclass(frozen=True)
class CanConfig:
    interface: str = "socketcan"  # any python-can interface name: socketcan, pcan, kvaser, virtual, ...
    channel: str = "can0"
    bitrate: int | None = None  # None: leave the interface as configured (SocketCAN: deploy/can-setup.sh)
    fd: bool = False


@dataclass(frozen=True)
class SignalsConfig:
    map: str = "prml2_onboard"  # shipped map name or path to a map TOML
    dbc: str | None = None  # DBC path; None: the map's own DBC
    mu: float = 1.0  # road friction for the physics guard (<= 0.5: low-mu limits)
    stale_periods: float = 3.0  # a signal is invalid after this many of its periods without a frame
    driven_axle: str = "front"  # "front" (FWD), "rear" (RWD) or "all" (AWD): the wheel cue is the other axle's
    steering_ratio: float = 15.0  # steering wheel angle / road wheel angle (front-wheel steer corrections)


@dataclass(frozen=True)
class ModelConfig:
    path: str | None = None  # ONNX file; None: the shipped default model
    sha256: str | None = None  # pin: refuse any other file
    providers: tuple[str, ...] = ("tensorrt", "cuda", "cpu")
    threads: int = 1  # ONNX Runtime intra-op threads; >= 2 is an upper bound: one where that runs the model faster
    fixed_threads: bool = False  # run on `threads` even where one intra-op thread is faster (runtime/inference.py)
    # ONNX Runtime's worker threads spin (busy-wait) between parallel sections instead of sleeping: with
    # threads >= 2 it cut the paper-size model's e2e p99 from 39 to 30 ms here (docs/benchmarks.md) at
    # the cost of CPU time the other processes of the box then do not get; off by default
    spinning: bool = False
    trt_fp16: bool = False
    trt_cache_dir: str = "~/.cache/prml2/trt"
    stride: int = DEFAULT_STRIDE  # a new window every `stride` 50 Hz steps
    # the model on a worker thread: no 50 Hz step waits for an inference; its output is used when it arrives
    # (runtime/async_estimator.py). For a model slower than the step (the paper-size one on a CPU). Off by default
    async_inference: bool = False


@dataclass(frozen=True)
class InitialPoseConfig:
    source: str = "gnss"  # "gnss" (fix message on the bus), "config" (x/y/heading below), "file"
    x_m: float = 0.0  # east
    y_m: float = 0.0  # north
    heading_deg: float = 0.0  # clockwise from north (as GNSS receivers report it)
    file: str | None = None  # JSON/TOML with x_m, y_m, heading_deg


@dataclass(frozen=True)
class SinksConfig:
    jsonl: str | None = None
    csv: str | None = None
    tum: str | None = None
    mcap: str | None = None  # MCAP for Foxglove (runtime/mcap_sink.py)
    can_out: bool = False  # send PRML2_POSE / PRML2_DYNAMICS / PRML2_POSE_STD on the bus
    status_interval_s: float = 5.0  # periodic status line


@dataclass(frozen=True)
class CalibrationConfig:
    enabled: bool = True  # the filter's calibration states, raw yaw-rate / wheel cues, standstill updates
    file: str | None = None  # state file: restored at start when it matches the vehicle, saved every minute


@dataclass(frozen=True)
class GnssConfig:
    """Fixes from a receiver or a file instead of the CAN bus (runtime/gnss_input.py); flags override these."""

    receiver: str | None = None  # prml2 run (--gnss): gpsd://HOST[:PORT] or a serial NMEA receiver
    file: str | None = None  # prml2 replay (--gnss): an NMEA log, a CSV (t_s,x_m,y_m[,heading_deg]) or a TUM file
    origin: tuple[float, ...] | None = None  # [LAT, LON] of the local east/north frame (--gnss-origin); None: 1st fix
    time_offset_s: float = 0.0  # prml2 replay (--gnss-time-offset): seconds added to the file's fix times
    course: bool = True  # the fixes' angle is the course over ground (a receiver's); false: the car's yaw (an INS)


@dataclass(frozen=True)
class RuntimeConfig:
    can: CanConfig = field(default_factory=CanConfig)
    signals: SignalsConfig = field(default_factory=SignalsConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    initial_pose: InitialPoseConfig = field(default_factory=InitialPoseConfig)
    sinks: SinksConfig = field(default_factory=SinksConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    gnss: GnssConfig = field(default_factory=GnssConfig)


_INITIAL_POSE_SOURCES = ("gnss", "config", "file")
DRIVEN_AXLES = ("front", "rear", "all")


def _type_name(tp: object) -> str:
    return getattr(tp, "__name__", str(tp)).replace("NoneType", "none")


def _coerce(where: str, value: object, tp: object) -> object:
    """Check ``value`` against the annotation ``tp`` (simple types, Optional, tuple[str, ...])."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(where, value, arg)
            except ConfigError as exc:
                errors.append(exc)
        raise errors[0]
    if origin is tuple:
        (item,) = {a for a in typing.get_args(tp) if a is not Ellipsis}
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{where}: expected a list of {_type_name(item)}, got {value!r}")
        return tuple(_coerce(f"{where}[{i}]", v, item) for i, v in enumerate(value))
    if tp is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if tp in (int, float, str, bool):
        if isinstance(value, bool) and tp is not bool:
            raise ConfigError(f"{where}: expected {_type_name(tp)}, got {value!r}")
        if not isinstance(value, tp):  # type: ignore[arg-type]
            raise ConfigError(f"{where}: expected {_type_name(tp)}, got {value!r}")
        return value
    raise TypeError(f"unsupported config type {tp!r}")  # pragma: no cover - programming error


def _build(cls: type, table: dict, where: str):
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    reject_unknown_keys(table, names, "{where}: unknown key {key} (known: {known})", where=where)
    kwargs = {}
    for name, value in table.items():
        tp = hints[name]
        key = f"{where}.{name}" if where else name
        if dataclasses.is_dataclass(tp):
            if not isinstance(value, dict):
                raise ConfigError(f"[{key}]: expected a table, got {value!r}")
            kwargs[name] = _build(tp, value, key)
        else:
            kwargs[name] = _coerce(f"[{where}] {name}" if where else name, value, tp)
    return cls(**kwargs)


def validate(cfg: RuntimeConfig) -> RuntimeConfig:
    """Value checks that types alone cannot express."""
    if cfg.model.threads < 1:
        raise ConfigError(f"[model] threads must be >= 1, got {cfg.model.threads}")
    if cfg.model.stride < 1:
        raise ConfigError(f"[model] stride must be >= 1, got {cfg.model.stride}")
    if cfg.model.sha256 is not None and (len(cfg.model.sha256) != 64 or
                                         any(c not in "0123456789abcdef" for c in cfg.model.sha256.lower())):
        raise ConfigError("[model] sha256 must be 64 hex digits (sha256sum model.onnx)")
    if not cfg.signals.mu > 0:
        raise ConfigError(f"[signals] mu must be > 0, got {cfg.signals.mu}")
    if cfg.signals.driven_axle not in DRIVEN_AXLES:
        raise ConfigError(f"[signals] driven_axle must be one of {', '.join(DRIVEN_AXLES)} (FWD, RWD, AWD), "
                          f"got {cfg.signals.driven_axle!r}")
    if not cfg.signals.steering_ratio > 0:
        raise ConfigError(f"[signals] steering_ratio must be > 0, got {cfg.signals.steering_ratio}")
    if cfg.signals.stale_periods <= 0:
        raise ConfigError(f"[signals] stale_periods must be > 0, got {cfg.signals.stale_periods}")
    if cfg.initial_pose.source not in _INITIAL_POSE_SOURCES:
        raise ConfigError(f"[initial_pose] source must be one of {', '.join(_INITIAL_POSE_SOURCES)}, "
                          f"got {cfg.initial_pose.source!r}")
    if cfg.initial_pose.source == "file" and not cfg.initial_pose.file:
        raise ConfigError("[initial_pose] source = 'file' needs file = PATH")
    origin = cfg.gnss.origin
    if origin is not None and (len(origin) != 2 or not (-90 <= origin[0] <= 90 and -180 <= origin[1] <= 180)):
        raise ConfigError(f"[gnss] origin must be [LAT, LON] in degrees (latitude within +-90, longitude within "
                          f"+-180), e.g. [48.1351, 11.5820], got {list(origin)}")
    return cfg


def config_from_dict(data: dict, source: str = "config") -> RuntimeConfig:
    try:
        return validate(_build(RuntimeConfig, data, ""))
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def read_toml(path: str | Path, what: str = "config file") -> dict:
    """Parse a TOML file; a missing file or bad syntax is one :class:`ConfigError` line naming the file."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(f"{path}: {what} not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from exc


def load_config(path: str | Path) -> RuntimeConfig:
    """Read a runtime TOML file; every problem is one :class:`ConfigError` line naming the key."""
    return config_from_dict(read_toml(path), str(path))


def with_overrides(cfg: RuntimeConfig, **sections: dict) -> RuntimeConfig:
    """Apply command-line overrides, e.g. ``with_overrides(cfg, can={"channel": "can1"})``.

    ``None`` values mean "not given on the command line" and are skipped.
    """
    data = dataclasses.asdict(cfg)
    for section, values in sections.items():
        if section not in data:
            raise ConfigError(f"unknown config section {section!r}")
        data[section].update({k: v for k, v in values.items() if v is not None})
    return config_from_dict(data, "command line")


def sha256_file(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def verify_pinned_model(path: str | Path, expected_sha256: str | None) -> str:
    """Return the file's SHA-256; refuse it when a pin is set and differs."""
    digest = sha256_file(path)
    if expected_sha256 is not None and digest != expected_sha256.lower():
        raise ModelError(f"{path}: SHA-256 {digest} does not match the pinned {expected_sha256.lower()} "
                         "([model] sha256 in the config); refusing to load it")
    return digest
