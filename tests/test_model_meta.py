import pytest

from prml2_edge import schema
from prml2_edge.errors import ModelError
from prml2_edge.model_meta import ModelMetadata


def _meta(**kw):
    base = dict(version="0", preset="tiny", norm_mean=[0.0] * 9, norm_std=[1.0] * 9, dataset_fingerprint="x")
    base.update(kw)
    return ModelMetadata(**base)


def test_round_trip_and_schema_check():
    m = _meta()
    back = ModelMetadata.from_json(m.to_json())
    assert back == m
    back.check_schema()
    assert back.L == schema.WINDOW_LEN and back.guard["v_max_mps"] == schema.V_MAX_MPS


def test_mismatches_are_refused_with_what_differs():
    names = list(schema.SIGNAL_NAMES)
    names[5], names[6] = names[6], names[5]
    with pytest.raises(ModelError, match="#5: model 'wheel_speed_fr_mps'"):
        _meta(signal_names=names).check_schema()
    with pytest.raises(ModelError, match="schema hash"):
        _meta(schema_hash="0" * 16).check_schema()
    with pytest.raises(ModelError, match="not a PRML2 model"):
        ModelMetadata.from_json('{"format": "other"}')
    with pytest.raises(ModelError, match="unknown PRML2 metadata key"):
        ModelMetadata.from_json(_meta().to_json().replace('"preset"', '"zzz": 1, "preset"'))
