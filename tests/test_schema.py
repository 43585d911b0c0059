import math

import pytest

from prml2_edge import schema


def test_canonical_order_matches_paper():
    # method.md: [v_s, delta_sw, psi_dot, a_y, p_br, v_fl, v_fr, v_rl, v_rr]
    assert [s.symbol for s in schema.SIGNALS] == [
        "v_s", "delta_sw", "psi_dot", "a_y", "p_br", "v_fl", "v_fr", "v_rl", "v_rr"]
    assert [s.index for s in schema.SIGNALS] == list(range(9))
    assert schema.NUM_SIGNALS == 9


def test_states_and_ekf_layout_agree():
    assert schema.STATE_NAMES == ("v_x_mps", "v_y_mps", "a_x_mps2", "a_y_mps2", "omega_z_radps")
    ekf = schema.EkfState
    assert ekf.DIM == len(ekf.NAMES) == 8
    # H maps z (in z order) onto the EKF state slots with the same meaning and unit.
    for z_index, ekf_index in enumerate(schema.Z_TO_EKF_INDEX):
        assert schema.STATES[z_index].name == ekf.NAMES[ekf_index]
    assert ekf.NAMES[ekf.YAW.start] == "psi_rad"


def test_ranges_are_physical():
    for s in schema.SIGNALS:
        assert s.min < s.max, s.name
        assert s.revsted_step > 0 and s.revsted_scale != 0
        assert s.rate_hz >= schema.SAMPLE_RATE_HZ / 2
    assert schema.WINDOW_LEN - schema.ENCODER_LEN == schema.DECODER_LEN == 100


def test_accel_limit_follows_kamms_circle():
    assert schema.accel_limit_mps2(1.0) == 10.0
    assert schema.accel_limit_mps2(0.5) == 5.0
    assert schema.accel_limit_mps2(0.3) == 5.0
    with pytest.raises(ValueError):
        schema.accel_limit_mps2(0.0)
    with pytest.raises(ValueError):
        schema.accel_limit_mps2(math.nan)


def test_schema_hash_is_stable_and_sensitive(monkeypatch):
    h = schema.schema_hash()
    assert h == schema.SCHEMA_HASH and len(h) == 16
    swapped = list(schema.SIGNALS)
    swapped[5], swapped[6] = swapped[6], swapped[5]
    monkeypatch.setattr(schema, "SIGNALS", tuple(swapped))
    assert schema.schema_hash() != h
