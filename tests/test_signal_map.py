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
