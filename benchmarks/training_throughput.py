"""Training throughput: windows/s of NLL pretraining and of EKF fine-tuning, with the real trainer.

Runs :func:`prml2_edge.training.trainer.fit` for three epochs (two pretraining, the first of them
a warm-up that is not reported, then one fine-tuning) on ``--windows`` training windows of the
benchmark dataset, the preset's batch size (capped at ``--windows``) and ``--threads`` torch
threads, and reads the trainer's own
``train_windows_per_s`` per stage (optimizer steps only; validation runs on a small fixed subset
and is not counted).

Usage::

    .venv/bin/python benchmarks/training_throughput.py [--presets edge,paper] [--windows 256]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from prml2_edge.bench.machine import load_average, machine_info
from prml2_edge.data.datasets import load_dataset
from prml2_edge.training.presets import get_preset
from prml2_edge.training.trainer import fit, prepare_data

sys.path.insert(0, str(Path(__file__).resolve().parent))
import report  # noqa: E402

HERE = Path(__file__).resolve().parent
DATASET = HERE.parent / "data" / "bench"


class _Subset:
    """The first ``n`` windows of a window source."""

    def __init__(self, source, n: int) -> None:
        self.source = source
        self.n = min(n, len(source))

    def __len__(self) -> int:
        return self.n

    def get(self, idx: np.ndarray):
        return self.source.get(idx)


def measure(preset_name: str, dataset, windows: int, val_windows: int, threads: int, seed: int) -> dict:
    preset = get_preset(preset_name)
    cfg = replace(preset.train, epochs=3, pretrain_frac=2.0 / 3.0, finetune=True, max_train_windows=windows,
                  batch_size=min(preset.train.batch_size, windows), num_threads=threads, seed=seed)
    torch.set_num_threads(threads)
    data = prepare_data(dataset, preset.model, cfg)
    data.val = _Subset(data.val, val_windows)
    with tempfile.TemporaryDirectory(prefix="prml2-train-bench-") as tmp:
        res = fit(data, tmp, preset=preset_name, model_cfg=preset.model, train_cfg=cfg, progress=False)
    by_stage = {h["stage"]: h for h in res.history}
    return {"preset": preset_name, "batch_size": cfg.batch_size, "windows_per_epoch": by_stage["pretrain"][
        "train_windows"], "threads": threads,
            "pretrain_windows_per_s": by_stage["pretrain"]["train_windows_per_s"],
            "finetune_windows_per_s": by_stage["finetune"]["train_windows_per_s"],
            "pretrain_s": by_stage["pretrain"]["train_time_s"], "finetune_s": by_stage["finetune"]["train_time_s"]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", default="edge,paper")
    ap.add_argument("--windows", type=int, default=500, help="training windows per epoch")
    ap.add_argument("--paper-windows", type=int, default=64, help="training windows per epoch for the paper preset")
    ap.add_argument("--val-windows", type=int, default=16)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(HERE / "results" / "training.json"))
    args = ap.parse_args(argv)
    t_start = time.time()
    machine = machine_info(with_torch=True)
    dataset = load_dataset(DATASET)
    presets = []
    for name in [p.strip() for p in args.presets.split(",") if p.strip()]:
        n = args.paper_windows if name == "paper" else args.windows
        print(f"[training] {name}: {n} windows per stage, load {load_average()}", file=sys.stderr, flush=True)
        presets.append(measure(name, dataset, n, args.val_windows, args.threads, args.seed))
        print(json.dumps(presets[-1]))
    doc = {"benchmark": "training", "started": time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(t_start)),
           "machine": machine, "load_average_end": load_average(), "dataset": str(DATASET), "presets": presets}
    out = report.save(doc, args.out)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
