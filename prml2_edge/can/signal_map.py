"""Signal maps: a TOML file that maps a vehicle's DBC onto the 9 canonical onboard signals.

Format (see ``dbc/maps/prml2_onboard.toml``)::

    [map]                      name, dbc (file name or path), description, strict (DBC strict load),
                               short_frames (accept payloads shorter than the DBC length)
    [signals.<canonical name>] message, signal, part_scale, scale, offset, rate_hz, valid, valid_value, sign
                               or: absent = true, substitute (a signal this car does not have)
    [messages.<message>]       counter, checksum, checksum_algorithm (integrity checks; a counter or checksum
                               split over several DBC signals is a list, low bits first)
    [gnss]                     message, x, y, heading, valid, dbc (optional GNSS fix input)

``value_SI = physical * scale + offset``, negated when the ``sign`` bit is set (VW style
unsigned magnitude plus sign bit). Unknown keys are refused with the key's name.

**Several DBC signals for one input:** ``signal = ["STEER_ANGLE", "STEER_FRACTION"]`` sums
the parts' physical values (each times its ``part_scale``, default 1) before ``scale`` and
``offset`` (Toyota's steering angle: 1.5 deg steps plus a 0.1 deg fraction).

**A signal the car lacks:** ``absent = true`` with ``substitute = VALUE`` (SI, default 0.0):
the runtime feeds that constant, always valid, in place of the signal; or ``substitute =
"wheel_deceleration"``: ``idle + per_mps2 * max(0, -a)`` with ``a`` the change of the mean wheel
speed over the last 0.2 s (defaults 0.85 bar and 10 bar per m/s^2, what the shipped model was
trained with). docs/bring-your-own-car.md says what each costs. Only ``brake_pressure_bar`` may
be absent: the model cannot do without speeds, steering, yaw rate or lateral acceleration.

**GNSS from the project DBC on a vehicle bus:** ``[gnss] dbc = "prml2_onboard.dbc"`` takes the
GNSS message from that DBC instead of merging it into the vehicle's; an ID that collides with a
vehicle message is refused at start-up, naming both.
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

_MAP_KEYS = {"name", "dbc", "description", "strict", "short_frames"}
_SIGNAL_KEYS = {"message", "signal", "part_scale", "scale", "offset", "rate_hz", "valid", "valid_value", "sign"}
_ABSENT_KEYS = {"absent", "substitute", "idle", "per_mps2", "rate_hz"}
SUBSTITUTES = ("wheel_deceleration",)  # besides a constant: derived substitutes the assembler computes
DECEL_IDLE_BAR = 0.85  # wheel_deceleration: the value at no deceleration (the simulated idle level)
DECEL_BAR_PER_MPS2 = 10.0  # ... and per m/s^2 of deceleration (the simulated car's brake gain)
OPTIONAL_SIGNALS = ("brake_pressure_bar",)  # signals a car may lack (absent = true)
_MESSAGE_KEYS = {"counter", "checksum", "checksum_algorithm"}
_GNSS_KEYS = {"message", "x", "y", "heading", "valid", "dbc"}
_TOP_KEYS = {"map", "signals", "messages", "gnss"}


@dataclass(frozen=True)
class SignalSpec:
    """Where one canonical signal lives in the DBC and how to convert it to SI."""

    name: str  # canonical name (schema.SIGNAL_NAMES)
    message: str
    signal: str  # the (first) DBC signal
    scale: float = 1.0
    offset: float = 0.0
    rate_hz: float = 50.0
    valid: str | None = None  # validity/quality signal; the value is valid when it equals valid_value
    valid_value: int = 1
    sign: str | None = None  # sign bit signal; set means negative
    parts: tuple[tuple[str, float], ...] = ()  # (DBC signal, part_scale) summed; () means ((signal, 1.0),)
    absent: bool = False  # the car lacks this signal: the runtime feeds ``substitute``
    substitute: float = 0.0  # SI value fed for an absent signal (wheel_deceleration: the idle value)
    substitute_kind: str = "constant"  # or "wheel_deceleration"
    substitute_per_mps2: float = 0.0  # wheel_deceleration: SI units per m/s^2 of deceleration

    @property
    def summed_parts(self) -> tuple[tuple[str, float], ...]:
        """The DBC signals summed into this one with their part scales (one part for a plain signal)."""
        return self.parts or ((self.signal, 1.0),)

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
    """Integrity checks of one message: counter and checksum signal names (a tuple: one field split over several
    signals, low bits first, :class:`prml2_edge.can.fields.SplitField`)."""

    message: str
    counter: str | tuple[str, ...] | None = None
    checksum: str | tuple[str, ...] | None = None
    checksum_algorithm: str | None = None

    @property
    def signal_names(self) -> tuple[str, ...]:
        """Every DBC signal the counter and the checksum occupy."""
        return tuple(n for f in (self.counter, self.checksum) if f is not None
                     for n in ((f,) if isinstance(f, str) else f))


def _check_field(where: str, key: str, value: object) -> object:
    """A ``[messages.*]`` value: a string, or for ``counter``/``checksum`` a non-empty list of signal names."""
    if key in ("counter", "checksum") and isinstance(value, list):
        if not value or not all(isinstance(v, str) for v in value):
            raise ConfigError(f"{where}: key {key!r} must be a DBC signal name or a list of them (low bits first)")
        return tuple(value)
    return _typed(where, key, value, str)


@dataclass(frozen=True)
class GnssSpec:
    """Optional GNSS fix message: x east [m], y north [m], heading clockwise from north [deg]."""

    message: str
    x: str
    y: str
    heading: str | None = None
    valid: str | None = None
    dbc: str | None = None  # take the GNSS message from this DBC (e.g. the project's) instead of the vehicle's


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
    short_frames: bool = False  # accept payloads shorter than the DBC length when they hold every mapped bit

    @property
    def message_names(self) -> tuple[str, ...]:
        """Messages that carry onboard signals, in first-use order."""
        return tuple(dict.fromkeys(s.message for s in self.signals if not s.absent))

    @property
    def present(self) -> tuple[SignalSpec, ...]:
        """The signals read from the bus (every one but the ``absent`` ones)."""
        return tuple(s for s in self.signals if not s.absent)

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


def _parts(where: str, names: list, scales: object) -> tuple[tuple[str, float], ...]:
    """``signal = [..]`` with its optional ``part_scale = [..]``: the (name, scale) pairs summed."""
    if not names or not all(isinstance(n, str) for n in names):
        raise ConfigError(f"{where}: key 'signal' must be a DBC signal name or a non-empty list of them")
    if scales is None:
        scales = [1.0] * len(names)
    if not isinstance(scales, list) or len(scales) != len(names):
        raise ConfigError(f"{where}: 'part_scale' must be a list of {len(names)} numbers, one per signal part")
    return tuple((n, float(_typed(where, "part_scale", v, float))) for n, v in zip(names, scales, strict=True))


def _absent_spec(where: str, name: str, t: dict) -> SignalSpec:
    """A signal the car does not have (``absent = true``): what the runtime feeds instead."""
    reject_unknown_keys(t, _ABSENT_KEYS, "{where}: unknown key {key} with absent = true (allowed: {known}); "
                        "an absent signal names no message or signal", where=where)
    if t["absent"] is not True:
        raise ConfigError(f"{where}: key 'absent' must be true (or left out), got {t['absent']!r}")
    if name not in OPTIONAL_SIGNALS:
        raise ConfigError(f"{where}: {name} cannot be absent (only {', '.join(OPTIONAL_SIGNALS)} may be): "
                          "the model cannot work without it; map it to a DBC signal")
    sig = schema.SIGNAL_BY_NAME[name]
    rate = float(_typed(where, "rate_hz", t.get("rate_hz", schema.SAMPLE_RATE_HZ), float))
    sub = t.get("substitute", 0.0)
    if isinstance(sub, str):
        if sub not in SUBSTITUTES:
            raise ConfigError(f"{where}: substitute {sub!r} unknown; give a number (SI) or one of "
                              f"{', '.join(SUBSTITUTES)}")
        idle = float(_typed(where, "idle", t.get("idle", DECEL_IDLE_BAR), float))
        gain = float(_typed(where, "per_mps2", t.get("per_mps2", DECEL_BAR_PER_MPS2), float))
        if not sig.min <= idle <= sig.max or gain < 0:
            raise ConfigError(f"{where}: idle must lie in [{sig.min}, {sig.max}] {sig.unit} and per_mps2 be >= 0")
        return SignalSpec(name=name, message="", signal="", rate_hz=rate, absent=True, substitute=idle,
                          substitute_kind=sub, substitute_per_mps2=gain)
    for key in ("idle", "per_mps2"):
        if key in t:
            raise ConfigError(f"{where}: {key!r} goes with substitute = \"wheel_deceleration\"")
    value = float(_typed(where, "substitute", sub, float))
    if not sig.min <= value <= sig.max:
        raise ConfigError(f"{where}: substitute {value} outside the signal's range [{sig.min}, {sig.max}] {sig.unit}")
    return SignalSpec(name=name, message="", signal="", rate_hz=rate, absent=True, substitute=value)


def load_signal_map(path: str | Path) -> SignalMap:
    """Read and validate a signal map TOML file (keys and types; not yet against a DBC)."""
    path = Path(path)
    doc = read_toml(path, "signal map")
    _check_keys(str(path), doc, _TOP_KEYS)
    head = _table(f"{path} [map]", doc.get("map", {}))
    _check_keys(f"{path} [map]", head, _MAP_KEYS)
    if "dbc" not in head:
        raise ConfigError(f"{path} [map]: missing key 'dbc' (the DBC file this map is written for)")
    specs = _signal_specs(path, _table(f"{path} [signals]", doc.get("signals", {})))
    messages = _message_checks(path, _table(f"{path} [messages]", doc.get("messages", {})))
    gnss = _gnss_spec(f"{path} [gnss]", doc["gnss"]) if "gnss" in doc else None
    return SignalMap(
        name=str(_typed(f"{path} [map]", "name", head.get("name", path.stem), str)),
        path=path,
        dbc=str(_typed(f"{path} [map]", "dbc", head["dbc"], str)),
        description=str(head.get("description", "")),
        strict=bool(_typed(f"{path} [map]", "strict", head.get("strict", True), bool)),
        short_frames=bool(_typed(f"{path} [map]", "short_frames", head.get("short_frames", False), bool)),
        signals=tuple(specs),
        messages=messages,
        gnss=gnss,
    )


def _signal_specs(path: Path, raw_signals: dict) -> list[SignalSpec]:
    """The ``[signals]`` table: every canonical signal once, no other, each read by :func:`_signal_spec`."""
    missing = [n for n in schema.SIGNAL_NAMES if n not in raw_signals]
    if missing:
        raise ConfigError(f"{path}: signal map lacks canonical signal(s) {', '.join(missing)}")
    extra = sorted(set(raw_signals) - set(schema.SIGNAL_NAMES))
    if extra:
        raise ConfigError(f"{path}: unknown signal {extra[0]!r}; canonical names: {', '.join(schema.SIGNAL_NAMES)}")
    return [_signal_spec(f"{path} [signals.{name}]", name, raw_signals[name]) for name in schema.SIGNAL_NAMES]


def _signal_spec(where: str, name: str, table: object) -> SignalSpec:
    """One ``[signals.NAME]`` table: where the signal is on the bus, or what stands in for an absent one."""
    t = _table(where, table)
    if t.get("absent", False) is not False:
        return _absent_spec(where, name, t)
    _check_keys(where, t, _SIGNAL_KEYS)
    for key in ("message", "signal"):
        if key not in t:
            raise ConfigError(f"{where}: missing key {key!r} (or absent = true for a signal this car lacks)")
    kwargs: dict = {}
    if isinstance(t["signal"], list):
        kwargs["parts"] = _parts(where, t["signal"], t.get("part_scale"))
        kwargs["signal"] = kwargs["parts"][0][0]
    elif "part_scale" in t:
        raise ConfigError(f"{where}: 'part_scale' needs signal = [list of DBC signals] to sum")
    for key, kind in (("message", str), ("signal", str), ("scale", float), ("offset", float),
                      ("rate_hz", float), ("valid", str), ("valid_value", int), ("sign", str)):
        if key in t and key not in kwargs:
            kwargs[key] = _typed(where, key, t[key], kind)
    if kwargs.get("scale", 1.0) == 0.0:
        raise ConfigError(f"{where}: scale must not be 0")
    if kwargs.get("rate_hz", 50.0) <= 0.0:
        raise ConfigError(f"{where}: rate_hz must be > 0")
    return SignalSpec(name=name, **kwargs)


def _message_checks(path: Path, raw_messages: dict) -> dict[str, MessageChecks]:
    """The ``[messages.NAME]`` tables: each message's counter and checksum signals."""
    messages = {}
    for msg_name, t in raw_messages.items():
        where = f"{path} [messages.{msg_name}]"
        t = _table(where, t)
        _check_keys(where, t, _MESSAGE_KEYS)
        t = {key: _check_field(where, key, value) for key, value in t.items()}
        algo = t.get("checksum_algorithm")
        if algo is not None and algo not in CHECKSUMS:
            raise ConfigError(f"{where}: unknown checksum_algorithm {algo!r}; known: {', '.join(sorted(CHECKSUMS))}")
        if ("checksum" in t) != ("checksum_algorithm" in t):
            raise ConfigError(f"{where}: 'checksum' and 'checksum_algorithm' go together")
        messages[msg_name] = MessageChecks(message=msg_name, **t)
    return messages


def _gnss_spec(where: str, table: object) -> GnssSpec:
    """The ``[gnss]`` table: the message and signals of the GNSS fix on the bus."""
    t = _table(where, table)
    _check_keys(where, t, _GNSS_KEYS)
    for key in ("message", "x", "y"):
        if key not in t:
            raise ConfigError(f"{where}: missing key {key!r}")
    for key in t:
        _typed(where, key, t[key], str)
    return GnssSpec(**t)


def shipped_map_path(name: str) -> Path:
    """Path of a map shipped in ``dbc/maps`` (:data:`SHIPPED_MAPS`)."""
    return resource_path("dbc", "maps", f"{name}.toml")


SHIPPED_MAPS = ("prml2_onboard", "vw_mqb", "hyundai_2015_ccan", "toyota_rav4_2018")


def resolve_map(name_or_path: str | Path) -> Path:
    """A shipped map name (:data:`SHIPPED_MAPS`) or a path to a map TOML."""
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
        hint = ""
        if strict and "overlapping" in first:
            hint = ("; production DBCs often have overlapping placeholder signals: set strict = false in the "
                    "signal map's [map] table to load it")
        raise DbcError(f"{path}: DBC does not parse ({first}){hint}") from exc
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

    for spec in signal_map.present:
        if not has(spec.message):
            problems.append(f"{spec.name}: message {spec.message!r} not in DBC")
            continue
        for sig in (*(p for p, _ in spec.summed_parts), spec.valid, spec.sign):
            if sig is not None and not has(spec.message, sig):
                problems.append(f"{spec.name}: signal {spec.message}.{sig} not in DBC")
    for checks in signal_map.messages.values():
        if not has(checks.message):
            problems.append(f"[messages.{checks.message}]: message not in DBC")
            continue
        for sig in checks.signal_names:
            if not has(checks.message, sig):
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


def check_frame_ids(signal_map: SignalMap, db: cantools.database.can.Database, dbc_path: str | Path = "") -> None:
    """Refuse a map whose messages share an arbitration ID with another message of ``db``.

    cantools keeps the later of two messages with one ID (it only logs "Overwriting message"), so
    frames of the earlier one would be decoded with the wrong layout (e.g. the project's GNSS_FIX
    0x610 merged into a Toyota DBC, where 0x610 is BODY_CONTROL_STATE_2).
    """
    by_id: dict[tuple[int, bool], list[str]] = {}
    for m in db.messages:
        by_id.setdefault((m.frame_id, bool(m.is_extended_frame)), []).append(m.name)
    used = list(signal_map.message_names) + ([signal_map.gnss.message] if signal_map.gnss else [])
    for name in used:
        m = db.get_message_by_name(name)
        names = by_id.get((m.frame_id, bool(m.is_extended_frame)), [])
        others = [n for n in names if n != name]
        if others:
            raise DbcError(f"DBC {dbc_path or signal_map.dbc}: message {name} (ID {m.frame_id:#x}) shares its ID with "
                           f"{others[0]}; frames of one would be decoded as the other: give the message an unused "
                           "ID (for GNSS, prml2 replay/run --gnss takes fixes from a receiver instead)")


def _add_gnss_message(signal_map: SignalMap, db: cantools.database.can.Database, dbc_path: Path) -> None:
    """``[gnss] dbc = ...``: take the GNSS message from that DBC into ``db``, refusing an ID the vehicle uses."""
    g = signal_map.gnss
    assert g is not None and g.dbc is not None
    p = Path(g.dbc)
    candidates = [p] if p.is_absolute() else [signal_map.path.parent / p, signal_map.path.parent.parent / p]
    path = next((c for c in candidates if c.is_file()), None)
    if path is None:
        try:
            path = resource_path("dbc", p.name)
        except Exception:
            raise DbcError(f"{signal_map.path} [gnss]: DBC {g.dbc!r} not found next to the map or among the "
                           "shipped DBCs") from None
    gnss_db = load_dbc(path)
    try:
        msg = gnss_db.get_message_by_name(g.message)
    except KeyError:
        raise DbcError(f"{signal_map.path} [gnss]: message {g.message!r} not in {path}") from None
    for other in db.messages:
        if other.frame_id == msg.frame_id and bool(other.is_extended_frame) == bool(msg.is_extended_frame):
            raise DbcError(f"GNSS message {msg.name} (ID {msg.frame_id:#x}, {path.name}) collides with vehicle "
                           f"message {other.name} (ID {other.frame_id:#x}, {dbc_path.name}): the bus already "
                           "uses that ID; feed fixes with --gnss (NMEA, CSV, TUM, gpsd) instead")
        if other.name == msg.name:
            raise DbcError(f"GNSS message {msg.name} ({path.name}) has the name of a vehicle message in "
                           f"{dbc_path.name}")
    db.messages.append(msg)
    db.refresh()


def load_map_and_dbc(map_path: str | Path, dbc_override: str | Path | None = None):
    """Load a map, its DBC (or ``dbc_override``), and check them against each other.

    Returns ``(signal_map, db, dbc_path)``.
    """
    signal_map = load_signal_map(map_path)
    dbc_path = signal_map.resolve_dbc(dbc_override)
    db = load_dbc(dbc_path, strict=signal_map.strict)
    if signal_map.gnss is not None and signal_map.gnss.dbc is not None:
        _add_gnss_message(signal_map, db, dbc_path)
    check_against_dbc(signal_map, db, dbc_path)
    check_frame_ids(signal_map, db, dbc_path)
    return signal_map, db, dbc_path
