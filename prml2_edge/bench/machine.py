"""Machine description and measured fp32 GEMM rate (the hardware reference for "fraction of peak").

The GEMM rate is NumPy ``float32`` matrix multiplication (OpenBLAS in the NumPy wheels) on
shapes like the model's, best of ``repeats``; it is measured in the same run as the model so
that the ratio is not skewed by a busy or throttled machine. The BLAS thread count is set
through OpenBLAS' own ``*_set_num_threads`` symbol when the library exposes it.
"""

from __future__ import annotations

import ctypes
import os
import platform
import shlex
import subprocess
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

# CPU flags worth reporting for inference speed (x86 and Arm names as /proc/cpuinfo spells them).
FLAGS_OF_INTEREST = ("avx2", "fma", "avx512f", "avx512bw", "avx512_vnni", "avx_vnni", "avx512_bf16", "amx_tile",
                     "amx_bf16", "amx_int8", "asimd", "asimddp", "bf16", "i8mm", "sve")


def _cpuinfo() -> dict[str, str]:
    info: dict[str, str] = {}
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return info
    for line in text.splitlines():
        if not line.strip():
            if info:
                break  # the first processor block is enough
            continue
        key, _, value = line.partition(":")
        info.setdefault(key.strip(), value.strip())
    return info


def load_average() -> list[float] | None:
    """1, 5 and 15-minute load averages, or None where the OS does not report them."""
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return None


IDLE_LOAD_PER_CORE = 0.3  # a 1-min load average above this per usable core at start or end: not idle


def load_label(before: list[float] | None, after: list[float] | None, cores: int | None = None) -> str:
    """``"idle (load X -> Y)"`` or ``"loaded (load X -> Y)"`` from the 1-min load averages at the start and
    end of a measurement (``"load unknown"`` where the OS reports none): a timing taken on a busy machine is
    never labelled idle."""
    if before is None or after is None:
        return "load unknown"
    cores = cores or usable_cores()
    busy = max(before[0], after[0]) > IDLE_LOAD_PER_CORE * cores
    return f"{'loaded' if busy else 'idle'} (load {before[0]:.2f} -> {after[0]:.2f})"


def usable_cores() -> int:
    """Cores this process may run on (the affinity mask, not the host's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def _version(module: str) -> str | None:
    try:
        mod = __import__(module)
    except ImportError:
        return None
    return str(getattr(mod, "__version__", "unknown"))


def provenance() -> dict:
    """``{"commit", "command"}``: what produced a result, so that a table rendered from it can say so.

    ``commit`` is the short hash of the git checkout this package runs from, ``+dirty`` when tracked files have
    uncommitted changes, None outside a checkout (an installed wheel). ``command`` is this process's command line,
    a script as ``python PATH`` relative to the checkout, the console script as ``prml2``.
    """
    root = Path(__file__).resolve().parents[2]
    commit = None

    def git(*args: str) -> str | None:
        try:
            out = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.SubprocessError):
            return None
        return out.stdout.strip() if out.returncode == 0 else None

    top = git("rev-parse", "--show-toplevel")
    if top and Path(top).resolve() == root:
        commit = git("rev-parse", "--short", "HEAD")
        if commit and git("status", "--porcelain", "--untracked-files=no"):
            commit += "+dirty"
    argv = list(sys.argv) or [""]
    prog = Path(argv[0]).resolve() if argv[0] else None
    if prog is not None and prog.is_relative_to(root / "prml2_edge"):
        head = ["prml2"]  # python -m prml2_edge.cli.main
    elif prog is not None and prog.suffix == ".py":
        head = ["python", str(prog.relative_to(root)) if prog.is_relative_to(root) else argv[0]]
    else:
        head = [Path(argv[0]).name or "python"]
    return {"commit": commit, "command": shlex.join(head + argv[1:])}


def machine_info(with_torch: bool = False) -> dict:
    """CPU model, cores, SIMD flags, memory, OS, Python and library versions, load average (plain data), and the
    commit and command that ran (:func:`provenance`).

    ``with_torch`` also reports torch's version and threads (training-side scripts only: the
    edge bench must not import torch).
    """
    cpu = _cpuinfo()
    flags = set((cpu.get("flags") or cpu.get("Features") or "").split())
    model = cpu.get("model name") or cpu.get("Model") or platform.processor() or platform.machine()
    mem_kb = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                mem_kb = int(line.split()[1])
    except OSError:
        pass
    import onnxruntime as ort

    info = {
        "cpu_model": model,
        "machine": platform.machine(),
        "cores_usable": usable_cores(),
        "cores_online": os.cpu_count(),
        "flags": sorted(f for f in FLAGS_OF_INTEREST if f in flags),
        "memory_gib": round(mem_kb / 2**20, 1) if mem_kb else None,
        "os": platform.platform(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "onnxruntime": ort.__version__,
        "onnxruntime_providers": ort.get_available_providers(),
        "blas": blas_info(),
        "load_average": load_average(),
        **provenance(),
    }
    if with_torch:
        import torch

        info["torch"] = torch.__version__
        info["torch_threads"] = torch.get_num_threads()
    else:
        info["torch"] = None
    return info


@dataclass
class _Blas:
    lib: ctypes.CDLL | None
    set_threads: object | None
    get_threads: object | None
    corename: object | None


def _find_blas() -> _Blas:
    """The OpenBLAS library NumPy loaded, with its thread-count and core-name functions (if found)."""
    candidates: list[Path] = []
    np_dir = Path(np.__file__).resolve().parent
    for folder in (np_dir.parent / "numpy.libs", np_dir / ".dylibs", np_dir.parent / "scipy_openblas64" / "lib",
                   np_dir.parent / "scipy_openblas32" / "lib"):
        if folder.is_dir():
            candidates.extend(sorted(folder.glob("*openblas*")))
    for path in candidates:
        try:
            lib = ctypes.CDLL(str(path))
        except OSError:
            continue
        found = {}
        for role, names in (("set", ("scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads",
                                     "openblas_set_num_threads64_", "openblas_set_num_threads")),
                            ("get", ("scipy_openblas_get_num_threads64_", "scipy_openblas_get_num_threads",
                                     "openblas_get_num_threads64_", "openblas_get_num_threads")),
                            ("core", ("scipy_openblas_get_corename64_", "scipy_openblas_get_corename",
                                      "openblas_get_corename64_", "openblas_get_corename"))):
            for name in names:
                fn = getattr(lib, name, None)
                if fn is not None:
                    found[role] = fn
                    break
        if "set" in found:
            if "core" in found:
                found["core"].restype = ctypes.c_char_p
            return _Blas(lib, found.get("set"), found.get("get"), found.get("core"))
    return _Blas(None, None, None, None)


_BLAS: _Blas | None = None


def _blas() -> _Blas:
    global _BLAS
    if _BLAS is None:
        _BLAS = _find_blas()
    return _BLAS


def blas_info() -> dict:
    """BLAS library and kernel (``core``) NumPy uses, where OpenBLAS tells."""
    b = _blas()
    core = None
    if b.corename is not None:
        core = b.corename().decode(errors="replace")  # type: ignore[operator]
    return {"library": Path(b.lib._name).name if b.lib is not None else None, "core": core,
            "threads": int(b.get_threads()) if b.get_threads is not None else None}  # type: ignore[operator]


def set_blas_threads(n: int) -> bool:
    """Set the BLAS thread count; False when it cannot be controlled (the rate is then per process)."""
    b = _blas()
    if b.set_threads is None:
        return False
    b.set_threads(int(n))  # type: ignore[operator]
    return True


def gemm_rate(shapes: Iterable[tuple[int, int, int]], threads: int = 1, repeats: int = 20,
              seed: int = 0) -> dict:
    """Best-of-``repeats`` fp32 GEMM rate [GFLOP/s] for each ``(m, k, n)`` (``A (m, k) @ B (k, n)``).

    Returns ``{"threads", "threads_controlled", "by_shape": [{"m", "k", "n", "gflops"}], "best_gflops",
    "flop_weighted_gflops"}``: the last is total FLOPs over total best times, the rate a model made of
    these products in equal measure would reach at 100 % efficiency.
    """
    rng = np.random.default_rng(seed)
    controlled = set_blas_threads(threads)
    rows = []
    total_flop = total_s = 0.0
    try:
        for m, k, n in shapes:
            a = rng.standard_normal((m, k), dtype=np.float32)
            b = rng.standard_normal((k, n), dtype=np.float32)
            out = np.empty((m, n), dtype=np.float32)
            np.matmul(a, b, out=out)  # warm-up (threads, pages)
            best = float("inf")
            for _ in range(repeats):
                t0 = time.perf_counter()
                np.matmul(a, b, out=out)
                best = min(best, time.perf_counter() - t0)
            flop = 2.0 * m * k * n
            rows.append({"m": m, "k": k, "n": n, "gflops": flop / best / 1e9})
            total_flop += flop
            total_s += best
    finally:
        set_blas_threads(usable_cores())
    return {"threads": threads, "threads_controlled": controlled, "repeats": repeats, "by_shape": rows,
            "best_gflops": max(r["gflops"] for r in rows),
            "flop_weighted_gflops": total_flop / total_s / 1e9 if total_s > 0 else float("nan")}
