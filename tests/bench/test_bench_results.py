from __future__ import annotations

import json
import math

import numpy as np
import pytest

from prml2_edge.bench.results import write_json


def test_write_json_makes_the_folder_and_writes_numpy_values_as_plain_json(tmp_path):
    doc = {"p99": np.float32(2.5), "n": np.int64(3), "rows": np.arange(3), "nan": float("nan"),
           "data": tmp_path / "drives"}
    out = write_json(doc, tmp_path / "deep" / "er" / "result.json")
    text = out.read_text()
    assert text.endswith("}\n")
    back = json.loads(text)
    assert back["p99"] == 2.5 and back["n"] == 3 and back["rows"] == [0, 1, 2]
    assert math.isnan(back["nan"]) and back["data"] == str(tmp_path / "drives")


def test_write_json_refuses_what_json_cannot_hold_instead_of_writing_its_repr(tmp_path):
    with pytest.raises(TypeError, match="set"):
        write_json({"cars": {"reference"}}, tmp_path / "r.json")
