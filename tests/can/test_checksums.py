"""Production checksums, each on frames built by hand from the algorithm's published description
(opendbc's ``toyota_checksum``/``honda_checksum``, the panda safety code), not by the project's encoder."""

from __future__ import annotations

import can
import pytest

from prml2_edge.can.checksum import (
    CHECKSUMS,
    crc8_sae_j1850,
    honda_checksum,
    hyundai_nibble_checksum,
    hyundai_wheel_speed_checksum,
    toyota_checksum,
)
from prml2_edge.can.fields import SplitField
from prml2_edge.can.signal_map import load_dbc, load_map_and_dbc, shipped_map_path
from prml2_edge.errors import ConfigError
from prml2_edge.runtime.decode import FrameDecoder
from prml2_edge.runtime.status import FrameStatus


def test_known_algorithms():
    assert {"prml2_crc8", "toyota", "honda", "hyundai_wheel_speed", "hyundai_nibble"} <= set(CHECKSUMS)
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


# Hyundai/Kia WHL_SPD11 (0x386) at 50 km/h on every wheel: raw 50 / 0.03125 = 1600 = 0x640 in 14 bits per wheel
# (bytes 0x40 0x06 each); alive counter 5 = 0b0101: LSB 0b01 in byte 1's top bits, MSB 0b01 in byte 3's. The
# checksum counts the 1 bits outside the top two bits of bytes 1, 3, 5, 7: 0x640 has 3, four wheels 12;
# 12 ^ 9 = 5 = 0b0101: LSB 0b01 in byte 5's top bits, MSB 0b01 in byte 7's.
WHL_SPD_50KMH = bytes([0x40, 0x46, 0x40, 0x46, 0x40, 0x46, 0x40, 0x46])


def test_hyundai_wheel_speed_worked_example():
    assert hyundai_wheel_speed_checksum(0x386, WHL_SPD_50KMH) == 5
    cleared = bytes([0x40, 0x46, 0x40, 0x46, 0x40, 0x06, 0x40, 0x06])  # its own bits cleared: the same
    assert hyundai_wheel_speed_checksum(0x386, cleared) == 5
    assert hyundai_wheel_speed_checksum(0x386, bytes(8)) == 9  # no 1 bits at all: 0 ^ 9


def test_hyundai_nibble_worked_examples(shared_dir):
    # EMS16 (0x260): Checksum in byte 7's low nibble, AliveCounter above it. Nibbles 1+2+3+4 and counter 2 = 12;
    # (16 - 12) % 16 = 4, so byte 7 = 0x24, and then every nibble of the frame sums to 0 mod 16
    assert hyundai_nibble_checksum(0x260, bytes([0x12, 0x34, 0, 0, 0, 0, 0, 0x20])) == 4
    assert hyundai_nibble_checksum(0x260, bytes(8)) == 0
    db = load_dbc(shared_dir / "dbc" / "opendbc" / "hyundai_2015_ccan.dbc")
    for name, checksum, counter in (("EMS16", "Checksum", "AliveCounter"), ("SCC12", "CR_VSM_ChkSum",
                                                                            "CR_VSM_Alive")):
        msg = db.get_message_by_name(name)
        field = SplitField.of(msg, checksum)
        values = {sig.name: 0 for sig in msg.signals} | {counter: 3}
        first = next(sig for sig in msg.signals if sig.name not in (checksum, counter) and sig.length >= 8)
        values[first.name] = 0x5A
        raw = msg.encode(values, scaling=False, strict=False)
        field.write(values, hyundai_nibble_checksum(msg.frame_id, raw))
        frame = msg.encode(values, scaling=False, strict=False)
        assert sum((b & 0xF) + (b >> 4) for b in frame) % 16 == 0, name  # the rule, read off the whole frame
        assert field.read(msg.decode(frame, scaling=False)) == hyundai_nibble_checksum(msg.frame_id, raw)


def test_split_fields_of_whl_spd11(shared_dir):
    db = load_dbc(shared_dir / "dbc" / "opendbc" / "hyundai_2015_ccan.dbc")
    msg = db.get_message_by_name("WHL_SPD11")
    counter = SplitField.of(msg, ("WHL_SPD_AliveCounter_LSB", "WHL_SPD_AliveCounter_MSB"))
    checksum = SplitField.of(msg, ("WHL_SPD_Checksum_LSB", "WHL_SPD_Checksum_MSB"))
    assert counter.bits == checksum.bits == 4
    assert checksum.mask(msg) == bytes([0, 0, 0, 0, 0, 0xC0, 0, 0xC0])
    decoded = msg.decode(WHL_SPD_50KMH)
    assert counter.read(decoded) == 5 and checksum.read(decoded) == 5
    values = {s.name: 0 for s in msg.signals} | {f"WHL_SPD_{w}": 50.0 for w in ("FL", "FR", "RL", "RR")}
    counter.write(values, 5)
    checksum.write(values, 5)
    assert msg.encode(values) == WHL_SPD_50KMH


def test_hyundai_wheel_speed_checksum_gates_real_frames(shared_dir):
    """The shipped Hyundai map checks WHL_SPD11's split counter and checksum: the worked frame passes, the same frame
    with one wheel-speed bit flipped or with its checksum's high half changed is refused."""
    smap, db, _ = load_map_and_dbc(shipped_map_path("hyundai_2015_ccan"),
                                   shared_dir / "dbc" / "opendbc" / "hyundai_2015_ccan.dbc")
    dec = FrameDecoder(smap, db)

    def frame(data):
        return can.Message(arbitration_id=0x386, is_extended_id=False, data=data)

    good = dec.step(frame(WHL_SPD_50KMH))
    assert good.status is FrameStatus.USED and good.value_si == [pytest.approx(50.0 / 3.6)] * 4
    flipped = bytearray(WHL_SPD_50KMH)
    flipped[4] ^= 0x01  # rear left 50.03 km/h, checksum unchanged
    assert dec.step(frame(bytes(flipped))).status is FrameStatus.REJECTED_CHECKSUM
    wrong = bytearray(WHL_SPD_50KMH)
    wrong[7] ^= 0x80  # the checksum's high half
    assert dec.step(frame(bytes(wrong))).status is FrameStatus.REJECTED_CHECKSUM
    nxt = bytearray(WHL_SPD_50KMH)  # counter 6 = 0b0110: LSB 0b10 in byte 1, MSB 0b01 in byte 3; checksum still 5
    nxt[1] = 0x86
    assert dec.step(frame(bytes(nxt))).status is FrameStatus.USED
    assert dec.step(frame(bytes(nxt))).status is FrameStatus.REJECTED_COUNTER  # a repeat


def test_encoded_hyundai_wheel_frames_carry_the_checksum(tmp_path, shared_dir):
    """The encoder writes WHL_SPD11's counter and checksum into their split halves; the frames it writes check out
    by the bit count done here by hand."""
    from prml2_edge.can.encode import encode_drive_to_log
    from prml2_edge.data.simulate import simulate_drive

    encode_drive_to_log(simulate_drive(0.05, 1.0, 2), tmp_path / "h.log",
                        signal_map_path=shipped_map_path("hyundai_2015_ccan"),
                        dbc_path=shared_dir / "dbc" / "opendbc" / "hyundai_2015_ccan.dbc")
    wheels = [m.data for m in can.LogReader(str(tmp_path / "h.log")) if m.arbitration_id == 0x386]
    assert len(wheels) > 100
    counters = []
    for d in wheels:
        ones = sum(bin(b & (0x3F if i in (1, 3, 5, 7) else 0xFF)).count("1") for i, b in enumerate(d))
        assert ((d[7] >> 6) << 2 | d[5] >> 6) == (ones ^ 9) & 0xF
        counters.append((d[3] >> 6) << 2 | d[1] >> 6)
    assert counters[:17] == [*range(16), 0]


def test_split_checks_in_a_map_are_named_on_error(tmp_path, shared_dir):
    text = shipped_map_path("hyundai_2015_ccan").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace('"WHL_SPD_Checksum_MSB"]', '"WHL_SPD_Checksum_HI"]'))
    with pytest.raises(Exception, match=r"\[messages.WHL_SPD11\]: signal 'WHL_SPD_Checksum_HI' not in DBC"):
        load_map_and_dbc(bad, shared_dir / "dbc" / "opendbc" / "hyundai_2015_ccan.dbc")
    bad.write_text(text.replace('checksum = ["WHL_SPD_Checksum_LSB", "WHL_SPD_Checksum_MSB"]', "checksum = [1, 2]"))
    with pytest.raises(ConfigError, match=r"\[messages.WHL_SPD11\]: key 'checksum' must be a DBC signal name or a "
                                          r"list of them"):
        load_map_and_dbc(bad, shared_dir / "dbc" / "opendbc" / "hyundai_2015_ccan.dbc")
