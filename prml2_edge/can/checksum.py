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

``hyundai_wheel_speed``: Hyundai/Kia WHL_SPD11 (0x386, 50 Hz wheel speeds; opendbc and the panda
safety code check it): the number of 1 bits in the frame, the top two bits of bytes 1, 3, 5 and 7
left out (the halves of the alive counter and of the checksum), XOR 9, low 4 bits. The checksum
is split like the counter: ``WHL_SPD_Checksum_LSB`` (byte 5) and ``WHL_SPD_Checksum_MSB`` (byte 7),
named in the map as a list (see :mod:`prml2_edge.can.fields`). Older models send no counter or
checksum there (openpilot's "legacy" Hyundai safety): leave ``[messages.WHL_SPD11]`` out for them.

``hyundai_nibble``: the Hyundai/Kia 4-bit nibble sum (EMS16 0x260 ``Checksum``, SCC12 0x421
``CR_VSM_ChkSum``): ``(16 - (sum of every 4-bit nibble of the payload) mod 16) mod 16`` with the
checksum's own nibble cleared. Not every Hyundai checksum is this one: SAS11.CheckSum and
ESP12.ESP12_Checksum follow a rule nobody has published (opendbc checks neither), so the shipped map
checks only their alive counters; TCS13 (0x394) leaves its byte 7 out of the sum and is not this
function either.

Each takes ``(frame_id, data)``, ``data`` being the payload with the checksum's own bits cleared
(the decoder clears them, the encoder computes before it sets them; the functions that skip the
checksum's byte or nibble anyway do not depend on it), and returns the value the checksum signal
must hold.
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
    """Checksum of a project-DBC frame; byte 0 of ``data`` (the checksum) is excluded.

    :func:`crc8_sae_j1850` of ``data[1:]`` followed by the ID's two bytes, run over them in place (once per
    frame on the hot path: no joined copy of the payload)."""
    table = _J1850_TABLE
    crc = 0xFF
    for i in range(1, len(data)):
        crc = table[crc ^ data[i]]
    crc = table[crc ^ (frame_id & 0xFF)]
    return table[crc ^ ((frame_id >> 8) & 0xFF)] ^ 0xFF


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


def hyundai_wheel_speed_checksum(frame_id: int, data: bytes) -> int:
    """Hyundai/Kia WHL_SPD11 checksum (4 bits): the frame's 1 bits but the top two of each odd byte, XOR 9."""
    ones = sum((b & 0x3F if i % 2 else b).bit_count() for i, b in enumerate(data))
    return (ones ^ 9) & 0xF


def hyundai_nibble_checksum(frame_id: int, data: bytes) -> int:
    """Hyundai/Kia nibble-sum checksum (4 bits) of a payload whose checksum nibble is cleared."""
    s = sum((b & 0xF) + (b >> 4) for b in data)
    return (16 - s % 16) % 16


CHECKSUMS: dict[str, Callable[[int, bytes], int]] = {"prml2_crc8": prml2_crc8, "toyota": toyota_checksum,
                                                      "honda": honda_checksum,
                                                      "hyundai_wheel_speed": hyundai_wheel_speed_checksum,
                                                      "hyundai_nibble": hyundai_nibble_checksum}


def checksum_function(name: str) -> Callable[[int, bytes], int]:
    """The checksum algorithm called ``name``; KeyError lists the known ones."""
    try:
        return CHECKSUMS[name]
    except KeyError:
        raise KeyError(f"unknown checksum algorithm {name!r}; known: {', '.join(sorted(CHECKSUMS))}") from None
