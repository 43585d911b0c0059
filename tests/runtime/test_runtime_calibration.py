"""The calibration state file: round trip, every bad-file case, and the pipeline saving and restoring it."""

from __future__ import annotations

import json
import logging
import math
import time

import numpy as np
import pytest

from prml2_edge.runtime.calibration import RESTORE_STD_FLOOR, CalibrationFile

CAL = np.array([math.radians(-0.4), 0.01, 0.001])
COV = np.diag([1e-8, 1e-6, 1e-6])


def test_round_trip_keeps_the_estimate_and_floors_the_covariance(tmp_path):
    f = CalibrationFile(tmp_path / "cal.json", "prml2_onboard (prml2_onboard.dbc)")
    assert f.load() is None  # first drive: no file, no warning
    assert f.save(CAL, COV, t_s=61.0)
    assert not list(tmp_path.glob(".cal.json.*"))  # the temporary file was renamed, not left behind
    cal, cov = CalibrationFile(tmp_path / "cal.json", f.identity).load()
    np.testing.assert_allclose(cal, CAL)
    np.testing.assert_allclose(np.diag(cov), np.diag(COV) + RESTORE_STD_FLOOR**2)
    doc = json.loads((tmp_path / "cal.json").read_text())
    assert doc["readable"]["yaw_rate_offset_dps"] == pytest.approx(-0.4)


@pytest.mark.parametrize("case", ["garbage", "wrong_format", "nan", "wrong_vehicle", "stale", "future",
                                  "wrong_states", "indefinite", "short"])
def test_a_bad_file_gives_one_warning_and_the_defaults(tmp_path, caplog, case):
    path = tmp_path / "cal.json"
    f = CalibrationFile(path, "car A")
    f.save(CAL, COV)
    doc = json.loads(path.read_text())
    if case == "garbage":
        path.write_bytes(b"\x00\xffnot json")
    else:
        if case == "wrong_format":
            doc["format"] = "something else"
        elif case == "nan":
            doc["cal"][0] = float("nan")
        elif case == "wrong_vehicle":
            doc["vehicle"] = "car B"
        elif case == "stale":
            doc["saved_unix_s"] = time.time() - 400 * 86400
        elif case == "future":
            doc["saved_unix_s"] = time.time() + 10 * 86400
        elif case == "wrong_states":
            doc["state_names"] = ["a", "b", "c"]
        elif case == "indefinite":  # positive variances, correlation beyond 1: no Gaussian has it
            doc["cov"][0][1] = doc["cov"][1][0] = 10.0 * math.sqrt(COV[0, 0] * COV[1, 1])
        elif case == "short":
            doc["cal"] = doc["cal"][:2]
        path.write_text(json.dumps(doc))
    with caplog.at_level(logging.WARNING):
        assert CalibrationFile(path, "car A").load() is None
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "default calibration" in warnings[0].getMessage()
    assert "\n" not in warnings[0].getMessage()


def test_an_unwritable_place_is_reported_not_raised(tmp_path):
    (tmp_path / "a_file").write_text("")  # its "folder" is a file: mkdir fails, even for root
    f = CalibrationFile(tmp_path / "a_file" / "cal.json", "car")
    assert not f.save(CAL, COV) and "cannot write" in f.last_error and f.n_saves == 0


def test_the_cue_offsets_section_round_trips_and_a_bad_one_is_refused_alone(tmp_path, caplog):
    """The cues' own offsets go to the next drive; a file without the section (an older runtime's) loads as
    before; a malformed one is refused with one warning line and the rest of the file still restores."""
    from prml2_edge.runtime.cue_offset import NUISANCE_NAMES

    section = {"names": list(NUISANCE_NAMES), "values": [0.1, 0.001, 0.0002], "cov": np.diag([1e-4, 1e-8, 1e-8])}
    section["cov"] = section["cov"].tolist()
    f = CalibrationFile(tmp_path / "cal.json", "car")
    assert f.save(CAL, COV, cue_offsets=section)
    g = CalibrationFile(tmp_path / "cal.json", "car")
    assert g.load() is not None and g.last_error is None
    np.testing.assert_allclose(g.cue_offsets[0], section["values"])
    np.testing.assert_allclose(g.cue_offsets[1], section["cov"])
    assert f.save(CAL, COV)
    h = CalibrationFile(tmp_path / "cal.json", "car")
    assert h.load() is not None and h.cue_offsets is None and h.last_error is None
    for broken in ({"names": ["a", "b", "c"]}, {"values": [0.1, float("nan"), 0.0]}, {"cov": [[1.0]]},
                   {"values": "many"}):
        assert f.save(CAL, COV, cue_offsets=section | broken)
        caplog.clear()
        bad = CalibrationFile(tmp_path / "cal.json", "car")
        with caplog.at_level(logging.WARNING):
            assert bad.load() is not None and bad.cue_offsets is None
        assert "cue_offsets section refused" in bad.last_error
        assert len(caplog.records) == 1 and "start from their priors" in caplog.text
