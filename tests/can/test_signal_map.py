"""Signal map loading and validation against DBCs."""

import pytest

from prml2_edge import schema
from prml2_edge.can.signal_map import load_map_and_dbc, load_signal_map, shipped_map_path
from prml2_edge.errors import ConfigError, DbcError


def test_shipped_project_map_loads_and_matches_dbc():
    smap, db, dbc_path = load_map_and_dbc(shipped_map_path("prml2_onboard"))
    assert [s.name for s in smap.signals] == list(schema.SIGNAL_NAMES)
    assert dbc_path.name == "prml2_onboard.dbc"
    assert smap.gnss is not None and smap.gnss.message == "GNSS_FIX"
    spec = smap.signals[1]
    phys, sign = spec.from_si(-0.5)
    assert spec.to_si(phys, sign) == pytest.approx(-0.5)


def _write(tmp_path, text):
    p = tmp_path / "m.toml"
    p.write_text(text)
    return p


def test_unknown_key_is_refused_with_its_name(tmp_path):
    src = shipped_map_path("prml2_onboard").read_text().replace('rate_hz = 25.0', 'rate_hz = 25.0\nratehz = 3')
    with pytest.raises(ConfigError, match="unknown key 'ratehz'"):
        load_signal_map(_write(tmp_path, src))


def test_missing_signal_is_named(tmp_path):
    src = shipped_map_path("prml2_onboard").read_text().replace("[signals.brake_pressure_bar]", "[x]")
    with pytest.raises(ConfigError, match="unknown key 'x'"):
        load_signal_map(_write(tmp_path, src))


def test_map_naming_signals_the_dbc_lacks_is_refused(tmp_path):
    src = shipped_map_path("prml2_onboard").read_text().replace('signal = "YAW_RATE"', 'signal = "YAW_RATE_X"')
    dbc = shipped_map_path("prml2_onboard").parent.parent / "prml2_onboard.dbc"
    p = _write(tmp_path, src.replace('dbc = "prml2_onboard.dbc"', f'dbc = "{dbc}"'))
    with pytest.raises(DbcError, match="ESP_YAW_LAT.YAW_RATE_X"):
        load_map_and_dbc(p)


def test_bad_dbc_and_bad_toml_are_one_line_errors(tmp_path):
    bad_dbc = tmp_path / "bad.dbc"
    bad_dbc.write_text("BO_ this is not a dbc\n")
    with pytest.raises(DbcError, match="does not parse"):
        load_map_and_dbc(shipped_map_path("prml2_onboard"), bad_dbc)
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_signal_map(_write(tmp_path, "[map\n"))


@pytest.mark.parametrize("name", ["vw_mqb", "hyundai_2015_ccan"])
def test_production_maps_load_against_the_real_opendbc_files(shared_dir, name):
    smap, db, dbc_path = load_map_and_dbc(shipped_map_path(name), shared_dir / "dbc" / "opendbc" / f"{name}.dbc")
    assert smap.name == name and [s.name for s in smap.signals] == list(schema.SIGNAL_NAMES)
    assert smap.gnss is None  # production buses carry no GNSS fix in the local frame
    for spec in smap.signals:  # every rate is a production rate of that bus
        assert spec.rate_hz in (50.0, 100.0)


def test_vw_map_converts_g_and_uses_sign_bits():
    smap = load_signal_map(shipped_map_path("vw_mqb"))
    by = {s.name: s for s in smap.signals}
    assert by["lat_accel_mps2"].scale == pytest.approx(schema.G_MPS2)
    assert by["yaw_rate_radps"].sign == "ESP_VZ_Gierrate" and by["steering_wheel_angle_rad"].sign
    assert by["yaw_rate_radps"].to_si(10.0, 1) == pytest.approx(-0.17453292519943295)
    assert not smap.strict


def test_unshipped_dbc_asks_for_dbc_option():
    with pytest.raises(DbcError, match="pass --dbc PATH"):
        load_map_and_dbc(shipped_map_path("vw_mqb"))
