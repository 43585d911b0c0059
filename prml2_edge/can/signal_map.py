"""Signal maps: a TOML file that maps a vehicle's DBC onto the 9 canonical onboard signals.

Format (see ``dbc/maps/prml2_onboard.toml``)::

    [map]                      name, dbc (file name or path), description, strict (DBC strict load)
    [signals.<canonical name>] message, signal, scale, offset, rate_hz, valid, valid_value, sign
    [messages.<message>]       counter, checksum, checksum_algorithm (integrity checks)
    [gnss]                     message, x, y, heading, valid (optional GNSS fix input)

``value_SI = physical * scale + offset``, negated when the ``sign`` bit is set (VW style
unsigned magnitude plus sign bit). Unknown keys are refused with the key's name.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import cantools

from prml2_edge import schema
from prml2_edge.can.checksum import CHECKSUMS
from prml2_edge.config import read_toml
from prml2_edge.errors import ConfigError, DbcError, first_line, reject_unknown_keys
from prml2_edge.resources import resource_path

_MAP_KEYS = {"name", "dbc", "description", "strict"}
_SIGNAL_KEYS = {"message", "signal", "scale", "offset", "rate_hz", "valid", "valid_value", "sign"}
_MESSAGE_KEYS = {"counter", "checksum", "checksum_algorithm"}
_GNSS_KEYS = {"message", "x", "y", "heading", "valid"}
_TOP_KEYS = {"map", "signals", "messages", "gnss"}


@dataclass(frozen=True)
class SignalSpec:
    """Where one canonical signal lives in the DBC and how to convert it to SI."""

    name: str  # canonical name (schema.SIGNAL_NAMES)
    message: str
    signal: str
    scale: float = 1.0
    offset: float = 0.0
    rate_hz: float = 50.0
    valid: str | None = None  # validity/quality signal; the value is valid when it equals valid_value
    valid_value: int = 1
    sign: str | None = None  # sign bit signal; set means negative

    def to_si(self, physical: float, sign_bit: int = 0) -> float:
        value = physical * self.scale + self.offset
        return -value if sign_bit else value

    def from_si(self, value_si: float) -> tuple[float, int]:
        """Inverse of :meth:`to_si`: (DBC physical value, sign bit)."""
        if self.sign is not None:
            return (abs(value_si) - self.offset) / self.scale, int(value_si < 0)
        return (value_si - self.offset) / self.scale, 0


@dataclass(frozen=True)
class MessageChecks:
    """Integrity checks of one message: counter and checksum signal names."""

    message: str
    counter: str | None = None
    checksum: str | None = None
    checksum_algorithm: str | None = None


@dataclass(frozen=True)
class GnssSpec:
    """Optional GNSS fix message: x east [m], y north [m], heading clockwise from north [deg]."""

    message: str
    x: str
    y: str
    heading: str | None = None
    valid: str | None = None


@dataclass(frozen=True)
class SignalMap:
    name: str
    path: Path
    dbc: str
    description: str = ""
    strict: bool = True
    signals: tuple[SignalSpec, ...] = ()  # canonical order
    messages: dict[str, MessageChecks] = field(default_factory=dict)
    gnss: GnssSpec | None = None

    @property
    def message_names(self) -> tuple[str, ...]:
        """Messages that carry onboard signals, in first-use order."""
        return tuple(dict.fromkeys(s.message for s in self.signals))

    def resolve_dbc(self, override: str | Path | None = None) -> Path:
        """The DBC to use: ``override``, else the map's ``dbc`` next to the map or among the shipped DBCs."""
        if override is not None:
            p = Path(override)
            if not p.is_file():
                raise DbcError(f"{p}: DBC file not found")
            return p
        p = Path(self.dbc)
        candidates = [p] if p.is_absolute() else [self.path.parent / p, self.path.parent.parent / p]
        for c in candidates:
            if c.is_file():
                return c
        try:
            return resource_path("dbc", p.name)
        except Exception:
            raise DbcError(
                f"{self.path}: DBC {self.dbc!r} not found next to the map or among the shipped DBCs; pass --dbc PATH"
            ) from None


def _check_keys(where: str, table: dict, allowed: set[str]) -> None:
    reject_unknown_keys(table, allowed, "{where}: unknown key {key} (allowed: {known})", where=where)


def _table(where: str, value: object) -> dict:
    if not isinstance(value, dict):
        raise ConfigError(f"{where}: expected a table, got {type(value).__name__}")
    return value


def _typed(where: str, key: str, value: object, kind: type) -> object:
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool:
        raise ConfigError(f"{where}: key {key!r} must be {kind.__name__}, got {value!r}")
    if kind is float and not math.isfinite(value):  # type: ignore[arg-type]
        raise ConfigError(f"{where}: key {key!r} must be finite, got {value!r}")
    return value


def load_signal_map(path: str | Path) -> SignalMap:
    """Read and validate a signal map TOML file (keys and types; not yet against a DBC)."""
    path = Path(path)
    doc = read_toml(path, "signal map")
    _check_keys(str(path), doc, _TOP_KEYS)
    head = _table(f"{path} [map]", doc.get("map", {}))
    _check_keys(f"{path} [map]", head, _MAP_KEYS)
    if "dbc" not in head:
        raise ConfigError(f"{path} [map]: missing key 'dbc' (the DBC file this map is written for)")

    raw_signals = _table(f"{path} [signals]", doc.get("signals", {}))
    missing = [n for n in schema.SIGNAL_NAMES if n not in raw_signals]
    if missing:
        raise ConfigError(f"{path}: signal map lacks canonical signal(s) {', '.join(missing)}")
    extra = sorted(set(raw_signals) - set(schema.SIGNAL_NAMES))
    if extra:
        raise ConfigError(f"{path}: unknown signal {extra[0]!r}; canonical names: {', '.join(schema.SIGNAL_NAMES)}")
    specs = []
    for name in schema.SIGNAL_NAMES:
        where = f"{path} [signals.{name}]"
        t = _table(where, raw_signals[name])
        _check_keys(where, t, _SIGNAL_KEYS)
        for key in ("message", "signal"):
            if key not in t:
                raise ConfigError(f"{where}: missing key {key!r}")
        kwargs = {}
        for key, kind in (("message", str), ("signal", str), ("scale", float), ("offset", float),
                          ("rate_hz", float), ("valid", str), ("valid_value", int), ("sign", str)):
            if key in t:
                kwargs[key] = _typed(where, key, t[key], kind)
        if kwargs.get("scale", 1.0) == 0.0:
            raise ConfigError(f"{where}: scale must not be 0")
        if kwargs.get("rate_hz", 50.0) <= 0.0:
            raise ConfigError(f"{where}: rate_hz must be > 0")
        specs.append(SignalSpec(name=name, **kwargs))

    messages = {}
    for msg_name, t in _table(f"{path} [messages]", doc.get("messages", {})).items():
        where = f"{path} [messages.{msg_name}]"
        t = _table(where, t)
        _check_keys(where, t, _MESSAGE_KEYS)
        for key in t:
            _typed(where, key, t[key], str)
        algo = t.get("checksum_algorithm")
        if algo is not None and algo not in CHECKSUMS:
            raise ConfigError(f"{where}: unknown checksum_algorithm {algo!r}; known: {', '.join(sorted(CHECKSUMS))}")
        if ("checksum" in t) != ("checksum_algorithm" in t):
            raise ConfigError(f"{where}: 'checksum' and 'checksum_algorithm' go together")
        messages[msg_name] = MessageChecks(message=msg_name, **t)

    gnss = None
    if "gnss" in doc:
        where = f"{path} [gnss]"
        t = _table(where, doc["gnss"])
        _check_keys(where, t, _GNSS_KEYS)
        for key in ("message", "x", "y"):
            if key not in t:
                raise ConfigError(f"{where}: missing key {key!r}")
        for key in t:
            _typed(where, key, t[key], str)
        gnss = GnssSpec(**t)

    return SignalMap(
        name=str(_typed(f"{path} [map]", "name", head.get("name", path.stem), str)),
        path=path,
        dbc=str(_typed(f"{path} [map]", "dbc", head["dbc"], str)),
        description=str(head.get("description", "")),
        strict=bool(_typed(f"{path} [map]", "strict", head.get("strict", True), bool)),
        signals=tuple(specs),
        messages=messages,
        gnss=gnss,
    )


def shipped_map_path(name: str) -> Path:
    """Path of a map shipped in ``dbc/maps`` (``prml2_onboard``, ``vw_mqb``, ``hyundai_2015_ccan``)."""
    return resource_path("dbc", "maps", f"{name}.toml")


SHIPPED_MAPS = ("prml2_onboard", "vw_mqb", "hyundai_2015_ccan")


def resolve_map(name_or_path: str | Path) -> Path:
    """A shipped map name (``prml2_onboard``, ``vw_mqb``, ``hyundai_2015_ccan``) or a path to a map TOML."""
    text = str(name_or_path)
    if text.endswith(".toml") or "/" in text or "\\" in text:
        path = Path(text)
        if not path.is_file():
            raise ConfigError(f"{path}: signal map not found")
        return path
    try:
        return shipped_map_path(text)
    except Exception:
        raise ConfigError(f"unknown signal map {text!r}; shipped maps: {', '.join(SHIPPED_MAPS)} "
                          "(or give a path to a map .toml)") from None


def load_dbc(path: str | Path, strict: bool = True) -> cantools.database.can.Database:
    """Load a DBC with cantools; any parse problem becomes one :class:`DbcError` line."""
    path = Path(path)
    if not path.is_file():
        raise DbcError(f"{path}: DBC file not found")
    try:
        db = cantools.database.load_file(str(path), database_format="dbc", strict=strict)
    except Exception as exc:  # cantools raises several unrelated types on bad input
        first = first_line(exc)
        raise DbcError(f"{path}: DBC does not parse ({first})") from exc
    return db


def check_against_dbc(signal_map: SignalMap, db: cantools.database.can.Database, dbc_path: str | Path = "") -> None:
    """Refuse a map that names messages or signals the DBC lacks, with everything that differs."""
    problems = []

    def has(msg_name: str, sig_name: str | None = None) -> bool:
        try:
            msg = db.get_message_by_name(msg_name)
        except KeyError:
            return False
        if sig_name is None:
            return True
        return any(s.name == sig_name for s in msg.signals)

    for spec in signal_map.signals:
        if not has(spec.message):
            problems.append(f"{spec.name}: message {spec.message!r} not in DBC")
            continue
        for sig in (spec.signal, spec.valid, spec.sign):
            if sig is not None and not has(spec.message, sig):
                problems.append(f"{spec.name}: signal {spec.message}.{sig} not in DBC")
    for checks in signal_map.messages.values():
        if not has(checks.message):
            problems.append(f"[messages.{checks.message}]: message not in DBC")
            continue
        for sig in (checks.counter, checks.checksum):
            if sig is not None and not has(checks.message, sig):
                problems.append(f"[messages.{checks.message}]: signal {sig!r} not in DBC")
    if signal_map.gnss is not None:
        g = signal_map.gnss
        if not has(g.message):
            problems.append(f"[gnss]: message {g.message!r} not in DBC")
        else:
            for sig in (g.x, g.y, g.heading, g.valid):
                if sig is not None and not has(g.message, sig):
                    problems.append(f"[gnss]: signal {g.message}.{sig} not in DBC")
    if problems:
        more = f" (+{len(problems) - 3} more)" if len(problems) > 3 else ""
        raise DbcError(
            f"signal map {signal_map.path} does not match DBC {dbc_path or signal_map.dbc}: "
            + "; ".join(problems[:3]) + more
        )


def load_map_and_dbc(map_path: str | Path, dbc_override: str | Path | None = None):
    """Load a map, its DBC (or ``dbc_override``), and check them against each other.

    Returns ``(signal_map, db, dbc_path)``.
    """
    signal_map = load_signal_map(map_path)
    dbc_path = signal_map.resolve_dbc(dbc_override)
    db = load_dbc(dbc_path, strict=signal_map.strict)
    check_against_dbc(signal_map, db, dbc_path)
    return signal_map, db, dbc_path
