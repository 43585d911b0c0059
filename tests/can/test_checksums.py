"""Production checksums, each on frames built by hand from the algorithm's published description
(opendbc's ``toyota_checksum``/``honda_checksum``, the panda safety code), not by the project's encoder."""

from __future__ import annotations

import can
import pytest

from prml2_edge.can.checksum import CHECKSUMS, crc8_sae_j1850, honda_checksum, toyota_checksum
from prml2_edge.can.signal_map import load_map_and_dbc, shipped_map_path
from prml2_edge.runtime.decode import FrameDecoder
from prml2_edge.runtime.status import FrameStatus


def test_known_algorithms():
    assert {"prml2_crc8", "toyota", "honda"} <= set(CHECKSUMS)
    assert crc8_sae_j1850(b"123456789") == 0x4B  # the catalogue check value


def test_toyota_worked_example():
    # SPEED 0xB4 at 50.00 km/h: raw 5000 = 0x1388 in bytes 5..6 (16 bits big endian from bit 47).
    # sum = length 8 + 0xB4 + 0x00 (ID high byte) + 0x13 + 0x88 = 8 + 180 + 19 + 136 = 343 -> 343 & 0xFF = 0x57
    data = bytes([0, 0, 0, 0, 0, 0x13, 0x88, 0x57])
    assert toyota_checksum(0xB4, data) == 0x57
    # an ID above 0xFF adds its high byte too: 0x224 -> 0x24 + 0x02; 6 bytes of 0x01 but the last: 6 + 38 + 5 = 49
    assert toyota_checksum(0x224, bytes([1, 1, 1, 1, 1, 0xEE])) == 49
    # the last byte (the checksum itself) never counts
    assert toyota_checksum(0xB4, data[:-1] + b"\x00") == 0x57


def test_toyota_checksum_gates_real_speed_frames(shared_dir):
    smap, db, _ = load_map_and_dbc(shipped_map_path("toyota_rav4_2018"),
                                   shared_dir / "dbc" / "opendbc" / "toyota_new_mc_pt_generated.dbc")
    dec = FrameDecoder(smap, db)
    good = dec.step(can.Message(arbitration_id=0xB4, is_extended_id=False, data=bytes([0, 0, 0, 0, 0, 0x13, 0x88,
                                                                                       0x57])))
    assert good.status is FrameStatus.USED and good.value_si[0] == pytest.approx(50.0 / 3.6)
    bad = dec.step(can.Message(arbitration_id=0xB4, is_extended_id=False, data=bytes([0, 0, 0, 0, 0, 0x13, 0x88,
                                                                                      0x58])))
    assert bad.status is FrameStatus.REJECTED_CHECKSUM


def test_honda_worked_examples():
    # 11-bit ID 0x158: ID nibbles 1 + 5 + 8 = 14; data nibbles 1+2, 3+4, 5+6, 7+8 = 3 + 7 + 11 + 15 = 36;
    # the last byte 0x2? contributes its high nibble (counter 2) only: 14 + 36 + 2 = 52; (8 - 52) & 0xF = 4
    assert honda_checksum(0x158, bytes([0x12, 0x34, 0x56, 0x78, 0, 0, 0, 0x2F])) == 4
    assert honda_checksum(0x158, bytes([0x12, 0x34, 0x56, 0x78, 0, 0, 0, 0x24])) == 4  # own nibble ignored
    # 29-bit ID 0x18DAF1: nibbles 1+8+13+10+15+1 = 48, last byte 0x10 -> 1: (8 - 49 + 3) & 0xF = 10
    assert honda_checksum(0x18DAF1, bytes([0, 0, 0, 0x10])) == 10
