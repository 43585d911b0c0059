"""Per-stage latency: ``time.perf_counter_ns`` samples -> p50/p95/p99/max and deadline misses.

Stages: ``decode`` and ``assemble`` per frame; ``plausibility`` (the cross-checks) per 50 Hz row;
``infer`` (onnxruntime) and ``guard`` per inference; ``filter`` (EKF step and GNSS fusion) and ``sinks`` per 50 Hz step;
``end_to_end`` per 50 Hz step, from the moment the frame that completed the row was received
to the moment every sink had the result. The 50 Hz deadline is 20 ms.
"""

from __future__ import annotations

from array import array

import numpy as np

from prml2_edge import schema

STAGES = ("decode", "assemble", "plausibility", "infer", "guard", "filter", "sinks", "end_to_end")
DEADLINE_MS = 1000.0 * schema.DT_S  # 20 ms at 50 Hz
PAPER_INFER_MS = (25.0, 32.0)  # paper Sec. V: PRML2 inference on an NVIDIA Orin
PAPER_NOTE = "paper: 25-32 ms inference on an NVIDIA Orin (d=512, 8 heads, 2 layers), ~30 Hz"


class LatencyRecorder:
    """Collect durations per stage (nanoseconds, int64) and summarise them in milliseconds.

    At most ``max_samples`` per stage are kept (the older half is dropped when full), so a
    service running for days has flat memory (the default, 2^17 samples, is 1 MiB per stage and
    at least 20 min of 50 Hz steps; the soak benchmark found the old 2 000 000 growing RSS by
    48 MiB over an hour); ``dropped`` counts what was discarded, summaries and :meth:`count`
    cover the kept (newest) samples, :meth:`total` counts every sample ever added.
    """

    def __init__(self, stages: tuple[str, ...] = STAGES, max_samples: int = 1 << 17) -> None:
        self._ns: dict[str, array] = {s: array("q") for s in stages}
        self._dropped: dict[str, int] = dict.fromkeys(stages, 0)  # per stage: kept + dropped = every sample added
        self.max_samples = int(max_samples)
        self.dropped = 0

    def add(self, stage: str, duration_ns: int) -> None:
        samples = self._ns[stage]  # (called several times per frame: one append, one length test)
        samples.append(duration_ns)
        if len(samples) > self.max_samples:
            half = len(samples) // 2
            del samples[:half]
            self._dropped[stage] += half
            self.dropped += half

    def clear(self, stage: str) -> None:
        """Forget ``stage``'s samples (the offline path, whose model stage does not run per row)."""
        del self._ns[stage][:]
        self._dropped[stage] = 0

    def samples_ms(self, stage: str) -> np.ndarray:
        """The kept samples of ``stage`` [ms], (n,) float64, oldest first."""
        return np.frombuffer(self._ns[stage], dtype=np.int64).astype(np.float64) / 1e6 if self._ns[stage] else \
            np.zeros(0)

    def count(self, stage: str) -> int:
        """Samples of ``stage`` kept."""
        return len(self._ns[stage])

    def total(self, stage: str) -> int:
        """Samples ever added to ``stage`` (kept or dropped)."""
        return len(self._ns[stage]) + self._dropped[stage]

    def stage_summary(self, stage: str, since: int = 0, since_total: int | None = None) -> dict:
        """``{count, mean_ms, p50_ms, p95_ms, p99_ms, max_ms}`` of ``stage``: the kept samples from index
        ``since``, or, with ``since_total`` (a :meth:`total` value), those added after it."""
        if since_total is not None:
            since = max(since_total - self._dropped[stage], 0)
        ms = self.samples_ms(stage)[since:]
        if ms.size == 0:
            return {"count": 0}
        p50, p95, p99 = np.percentile(ms, [50, 95, 99])
        return {"count": int(ms.size), "mean_ms": float(ms.mean()), "p50_ms": float(p50), "p95_ms": float(p95),
                "p99_ms": float(p99), "max_ms": float(ms.max())}

    def deadline_misses(self, stage: str = "end_to_end", deadline_ms: float = DEADLINE_MS) -> int:
        return int(np.count_nonzero(self.samples_ms(stage) > deadline_ms))

    def summary(self, deadline_ms: float = DEADLINE_MS) -> dict:
        out = {stage: self.stage_summary(stage) for stage in self._ns}
        e2e = out.get("end_to_end", {})
        if e2e.get("count"):
            e2e["deadline_ms"] = deadline_ms
            e2e["deadline_misses"] = self.deadline_misses("end_to_end", deadline_ms)
        return out

    def report_lines(self, deadline_ms: float = DEADLINE_MS) -> list[str]:
        """A fixed-width table for the terminal, with the paper's Orin figure beside it."""
        lines = [f"{'stage':<11} {'count':>7} {'p50 ms':>8} {'p95 ms':>8} {'p99 ms':>8} {'max ms':>8}"]
        for stage, s in self.summary(deadline_ms).items():
            if not s.get("count"):
                continue
            lines.append(f"{stage:<11} {s['count']:>7} {s['p50_ms']:>8.3f} {s['p95_ms']:>8.3f} {s['p99_ms']:>8.3f} "
                         f"{s['max_ms']:>8.3f}")
        n = self.count("end_to_end")
        if n:
            miss = self.deadline_misses("end_to_end", deadline_ms)
            lines.append(f"deadline {deadline_ms:.0f} ms (50 Hz): {miss} of {n} steps missed "
                         f"({100.0 * miss / n:.2f} %)")
        lines.append(PAPER_NOTE)
        return lines
