"""Integrity fields (alive counters, checksums) that a DBC may store in one signal or split over several.

Most messages hold a counter or a checksum in one signal. Some do not: Hyundai/Kia's WHL_SPD11
keeps its 4-bit alive counter in ``WHL_SPD_AliveCounter_LSB`` (2 bits, byte 1) and
``WHL_SPD_AliveCounter_MSB`` (2 bits, byte 3), its checksum likewise in bytes 5 and 7. A map names
such a field as a list, low bits first (``counter = ["..._LSB", "..._MSB"]``); :class:`SplitField`
reads and writes it as one integer through cantools' decoded values.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SplitField:
    """One integer stored in the DBC signals ``parts`` (name, bit width), the first part its lowest bits."""

    parts: tuple[tuple[str, int], ...]

    @classmethod
    def of(cls, message, names: str | tuple[str, ...] | None) -> SplitField | None:
        """The field of cantools ``message`` that ``names`` (one signal or several, low bits first) make up."""
        if names is None:
            return None
        names = (names,) if isinstance(names, str) else tuple(names)
        return cls(tuple((n, int(message.get_signal_by_name(n).length)) for n in names))

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(n for n, _ in self.parts)

    @property
    def bits(self) -> int:
        return sum(w for _, w in self.parts)

    def read(self, decoded: dict) -> int:
        """The field's value from cantools' decoded (raw-scaled, factor 1) signal values."""
        if len(self.parts) == 1:  # the usual case (once per frame on the hot path): no loop
            name, width = self.parts[0]
            return int(decoded[name]) & ((1 << width) - 1)
        value, shift = 0, 0
        for name, width in self.parts:
            value |= (int(decoded[name]) & ((1 << width) - 1)) << shift
            shift += width
        return value

    def write(self, values: dict, value: int) -> None:
        """Put ``value`` into the signal values ``values`` (to be encoded by cantools), part by part."""
        for name, width in self.parts:
            values[name] = value & ((1 << width) - 1)
            value >>= width

    def mask(self, message) -> bytes:
        """The payload bits this field occupies in cantools ``message`` (set bits), to clear it before a checksum."""
        raw = {s.name: 0 for s in message.signals}
        for name, width in self.parts:
            raw[name] = (1 << width) - 1
        return bytes(message.encode(raw, scaling=False, strict=False))
