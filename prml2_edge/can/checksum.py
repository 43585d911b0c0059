"""Frame checksums named by signal maps (``checksum_algorithm``).

``prml2_crc8``: CRC-8/SAE-J1850 (poly 0x1D, init 0xFF, xor-out 0xFF) over data bytes
1..7 followed by the 11-bit frame ID as two little-endian bytes; the checksum itself
sits in byte 0 (as on VW MQB). Mixing in the ID catches frames sent with the right
layout on the wrong ID.
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


CHECKSUMS: dict[str, Callable[[int, bytes], int]] = {"prml2_crc8": prml2_crc8}


def checksum_function(name: str) -> Callable[[int, bytes], int]:
    """The checksum algorithm called ``name``; KeyError lists the known ones."""
    try:
        return CHECKSUMS[name]
    except KeyError:
        raise KeyError(f"unknown checksum algorithm {name!r}; known: {', '.join(sorted(CHECKSUMS))}") from None
