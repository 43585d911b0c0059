"""Sign conventions of ReV-StED-schema files: a file with any one convention flipped is refused naming the
column; the shipped sample and simulated drives pass."""

from __future__ import annotations

import json

import pytest

from prml2_edge.cli.main import main
from prml2_edge.data.conventions import check_drive
from prml2_edge.data.revsted import load_drive, write_drive_csv
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.errors import DataError

COLUMNS = ("rate_hor_z", "ins_yaw", "INS_velCOG_hor_y", "acc_hor_y", "LatAcc_obd", "Yawrate_obd", "SW_pos_obd")


def flip_column(src, dst, column):
    lines = src.read_text().splitlines()
    j = lines[0].split(",").index(column)
    out = [lines[0]]
    for line in lines[1:]:
        cells = line.split(",")
        v = float(cells[j])
        cells[j] = repr((-v) % 360.0 if column == "ins_yaw" else -v)
        out.append(",".join(cells))
    dst.write_text("\n".join(out) + "\n")
    return dst


@pytest.fixture(scope="module")
def drive_csv(tmp_path_factory):
    path = tmp_path_factory.mktemp("conv") / "drive.csv"
    write_drive_csv(simulate_drive(1.0, 1.0, 2, family="lateral"), path)
    return path


@pytest.mark.parametrize("column", COLUMNS)
def test_each_flipped_convention_is_refused_naming_the_column(drive_csv, tmp_path, column):
    bad = flip_column(drive_csv, tmp_path / f"flip_{column}.csv", column)
    with pytest.raises(DataError, match=rf"column '{column}': .*opposite sign.*negate the column"):
        load_drive(bad)


def test_shipped_sample_and_simulated_drives_pass(shared_dir, tmp_path):
    sample = load_drive(shared_dir / "data/revsted/OBD_Sample.csv")
    assert not [f for f in check_drive(sample) if f.result == "FAIL"]
    for seed, family in ((1, "mixed"), (3, "longitudinal"), (6, "snow")):
        path = tmp_path / f"{family}.csv"
        write_drive_csv(simulate_drive(1.0, 0.3 if family == "snow" else 1.0, seed, family=family), path)
        load_drive(path)  # no refusal


def test_doctor_data_reports_every_check(drive_csv, tmp_path, capsys):
    assert main(["doctor", "--data", str(drive_csv.parent)]) == 0
    assert "OK: every checked convention matches" in capsys.readouterr().out
    flip_column(drive_csv, tmp_path / "bad.csv", "acc_hor_y")
    assert main(["doctor", "--data", str(tmp_path), "--json"]) == 1
    doc = json.loads(capsys.readouterr().out)
    assert [c["column"] for c in doc["checks"] if c["result"] == "FAIL"] == ["acc_hor_y"]
