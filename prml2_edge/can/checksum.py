"""Frame checksums named by signal maps (``checksum_algorithm``).

``prml2_crc8``: CRC-8/SAE-J1850 (poly 0x1D, init 0xFF, xor-out 0xFF) over data bytes
1..7 followed by the 11-bit frame ID as two little-endian bytes; the checksum itself
sits in byte 0 (as on VW MQB). Mixing in the ID catches frames sent with the right
layout on the wrong ID.

``toyota``: Toyota's byte sum (opendbc ``toyota_checksum``, the panda safety code): the
frame's length plus each byte of the 11-bit ID (``id & 0xFF`` and ``id >> 8``) plus every
data byte but the last, modulo 256; the checksum is the last byte (``SPEED`` 0xB4 byte 7 on
the RAV4). The length is that of the frame as sent, so a short payload still checks.

``honda``: Honda's nibble sum (opendbc ``honda_checksum``): every 4-bit nibble of the ID
plus every nibble of the data, the last byte's low nibble (the checksum itself) left out;
the checksum is ``(8 - sum) & 0xF`` (``+ 3`` more for a 29-bit ID) in the last byte's low
nibble.

Each takes ``(frame_id, data)`` and returns the value the checksum signal must hold.
"""

from __future__ import annotations

from collections.abc import Callable


def _make_table(poly: int) -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ poly) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


_J1850_TABLE = _make_table(0x1D)


def crc8_sae_j1850(data: bytes) -> int:
    """CRC-8/SAE-J1850 of ``data`` (check value of b"123456789" is 0x4B)."""
    crc = 0xFF
    for b in data:
        crc = _J1850_TABLE[crc ^ b]
    return crc ^ 0xFF


def prml2_crc8(frame_id: int, data: bytes) -> int:
    """Checksum of a project-DBC frame; byte 0 of ``data`` (the checksum) is excluded."""
    return crc8_sae_j1850(bytes(data[1:]) + bytes((frame_id & 0xFF, (frame_id >> 8) & 0xFF)))


def toyota_checksum(frame_id: int, data: bytes) -> int:
    """Toyota byte-sum checksum of a frame; the last byte of ``data`` (the checksum) is excluded."""
    s = len(data)
    address = frame_id
    while address:
        s += address & 0xFF
        address >>= 8
    return (s + sum(data[:-1])) & 0xFF


def honda_checksum(frame_id: int, data: bytes) -> int:
    """Honda nibble-sum checksum (4 bits); the low nibble of the last byte (the checksum) is excluded."""
    s = 0
    address = frame_id
    while address:
        s += address & 0xF
        address >>= 4
    for i, b in enumerate(data):
        if i == len(data) - 1:
            b >>= 4
        s += (b & 0xF) + (b >> 4)
    s = 8 - s
    if frame_id > 0x7FF:
        s += 3
    return s & 0xF


CHECKSUMS: dict[str, Callable[[int, bytes], int]] = {"prml2_crc8": prml2_crc8, "toyota": toyota_checksum,
                                                      "honda": honda_checksum}


def checksum_function(name: str) -> Callable[[int, bytes], int]:
    """The checksum algorithm called ``name``; KeyError lists the known ones."""
    try:
        return CHECKSUMS[name]
    except KeyError:
        raise KeyError(f"unknown checksum algorithm {name!r}; known: {', '.join(sorted(CHECKSUMS))}") from None
