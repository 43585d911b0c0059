"""Execution-provider fallback with the provider list faked."""

import pytest

from prml2_edge.errors import ConfigError
from prml2_edge.runtime.providers import CPU, CUDA, TENSORRT, select_providers

ORIN = [TENSORRT, CUDA, CPU]


def test_orin_gets_tensorrt_with_engine_cache(tmp_path):
    choice = select_providers(available=ORIN, trt_cache_dir=tmp_path, trt_fp16=True)
    assert choice.chosen == TENSORRT
    name, opts = choice.providers[0]
    assert opts["trt_engine_cache_enable"] and opts["trt_fp16_enable"]
    assert opts["trt_engine_cache_path"] == str(tmp_path)
    assert [p if isinstance(p, str) else p[0] for p in choice.providers] == ORIN
    assert "TensorrtExecutionProvider -> CUDAExecutionProvider -> CPUExecutionProvider" in choice.describe()


def test_falls_back_to_cuda_then_cpu():
    assert select_providers(available=[CUDA, CPU]).chosen == CUDA
    choice = select_providers(available=[CPU])
    assert choice.chosen == CPU and choice.providers == [CPU]
    assert set(choice.skipped) == {TENSORRT, CUDA}
    assert "not offered" in choice.describe()


def test_cpu_is_always_appended_and_unknown_names_refused():
    assert select_providers(order=["cuda"], available=ORIN).providers[-1] == CPU
    with pytest.raises(ConfigError, match="unknown execution provider 'rocm'"):
        select_providers(order=["rocm"], available=ORIN)


def test_real_onnxruntime_offers_cpu():
    assert select_providers().providers[-1] == CPU
