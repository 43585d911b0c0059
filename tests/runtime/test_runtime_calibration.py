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
                                  "wrong_states"])
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
