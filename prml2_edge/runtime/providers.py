"""ONNX Runtime execution-provider selection: TensorRT -> CUDA -> CPU, whichever is offered.

On a Jetson Orin with the GPU build of onnxruntime, TensorRT gives the lowest latency; its
engine is built on first use for the fixed 1 x L x 9 input and cached on disk so later
starts are fast. CUDA is the fallback, the CPU provider always works.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from prml2_edge.errors import ConfigError

TENSORRT = "TensorrtExecutionProvider"
CUDA = "CUDAExecutionProvider"
CPU = "CPUExecutionProvider"
DEFAULT_ORDER = ("tensorrt", "cuda", "cpu")
_BY_SHORT_NAME = {"tensorrt": TENSORRT, "cuda": CUDA, "cpu": CPU}


@dataclass(frozen=True)
class ProviderChoice:
    providers: list[str | tuple[str, dict]]  # what onnxruntime.InferenceSession(providers=...) takes
    chosen: str  # first (preferred) provider actually used
    skipped: tuple[str, ...]  # requested but not offered by this onnxruntime build

    def describe(self) -> str:
        """One log line: what was chosen and why."""
        tail = f" (not offered by this onnxruntime: {', '.join(self.skipped)})" if self.skipped else ""
        order = " -> ".join(p if isinstance(p, str) else p[0] for p in self.providers)
        return f"execution providers: {order}{tail}"


def select_providers(order: Sequence[str] = DEFAULT_ORDER, available: Sequence[str] | None = None,
                     trt_cache_dir: str | Path = "~/.cache/prml2/trt", trt_fp16: bool = False,
                     device_id: int = 0) -> ProviderChoice:
    """Pick the providers in ``order`` that this onnxruntime offers; CPU is always last.

    ``order`` holds short names (``tensorrt``, ``cuda``, ``cpu``) or full provider names.
    ``available`` defaults to ``onnxruntime.get_available_providers()`` (tests pass a fake list).
    """
    if available is None:
        import onnxruntime

        available = onnxruntime.get_available_providers()
    wanted = []
    for name in order:
        full = _BY_SHORT_NAME.get(name.lower(), name)
        if full not in _BY_SHORT_NAME.values():
            raise ConfigError(f"unknown execution provider {name!r}; use tensorrt, cuda or cpu")
        if full not in wanted:
            wanted.append(full)
    if CPU not in wanted:
        wanted.append(CPU)
    providers: list[str | tuple[str, dict]] = []
    skipped = []
    for full in wanted:
        if full != CPU and full not in available:
            skipped.append(full)
            continue
        if full == TENSORRT:
            cache = Path(trt_cache_dir).expanduser()
            providers.append((TENSORRT, {
                "device_id": device_id,
                "trt_engine_cache_enable": True,
                "trt_engine_cache_path": str(cache),
                "trt_timing_cache_enable": True,
                "trt_timing_cache_path": str(cache),
                "trt_fp16_enable": bool(trt_fp16),
            }))
        elif full == CUDA:
            providers.append((CUDA, {"device_id": device_id}))
        else:
            providers.append(CPU)
    first = providers[0]
    return ProviderChoice(providers, first if isinstance(first, str) else first[0], tuple(skipped))
