"""Data-parallel training: 2 CPU processes (gloo) under torch.distributed.run end with identical weights."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

SCRIPT = r'''
import sys
from dataclasses import replace
sys.path.insert(0, {tests_dir!r})
import numpy as np
import torch
torch.set_num_threads(1)
from test_train_data import toy_windows
from prml2_edge.training import distributed as ddp
from prml2_edge.training.presets import get_preset
from prml2_edge.training.trainer import TrainData, fit, z_statistics

info = ddp.init("gloo")
assert info.enabled and info.world_size == 2, info
drives, train = toy_windows(n_drives=2, n=800, stride=25)
_, val = toy_windows(n_drives=1, n=500, stride=50, seed=10)
z_mean, z_std = z_statistics(np.concatenate([d.z_gt for d in drives]))
onboard = np.concatenate([d.onboard for d in drives])
data = TrainData(train=train, val=val, norm_mean=onboard.mean(0), norm_std=onboard.std(0), z_mean=z_mean,
                 z_std=z_std, fingerprint="toy")
preset = get_preset("tiny")
cfg = replace(preset.train, epochs=2, batch_size=8, max_train_windows=16, num_threads=1)
from prml2_edge.training.model import Prml2Model
torch.manual_seed(cfg.seed)  # what fit starts from
init = Prml2Model(preset.model, data.norm_mean, data.norm_std, data.z_mean, data.z_std)
if info.rank == 0:
    torch.save(init.state_dict(), {out!r} + "/init.pt")
torch.manual_seed(100 + info.rank)  # different global RNG per rank: DDP must still agree
result = fit(data, {out!r}, preset="tiny", model_cfg=preset.model, train_cfg=cfg, info=info, progress=False)
torch.save({{k: v.clone() for k, v in result.model.state_dict().items()}}, {out!r} + f"/rank{{info.rank}}.pt")
# one file per rank: two processes printing to one pipe interleave their lines
open({out!r} + f"/steps{{info.rank}}.txt", "w").write(str(result.counters["steps"]))
ddp.shutdown(info)
'''


def test_two_gloo_ranks_end_with_identical_weights(tmp_path):
    tests_dir = str(Path(__file__).resolve().parent)
    out = tmp_path / "ddp"
    out.mkdir()
    script = tmp_path / "ddp_train.py"
    script.write_text(SCRIPT.format(tests_dir=tests_dir, out=str(out)))
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PRML2_NO_PROGRESS": "1"}
    proc = subprocess.run(
        [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2", str(script)],
        capture_output=True, text=True, timeout=240, env=env,
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-4000:]
    w0 = torch.load(out / "rank0.pt", weights_only=True)
    w1 = torch.load(out / "rank1.pt", weights_only=True)
    assert w0.keys() == w1.keys()
    for key in w0:
        assert torch.equal(w0[key], w1[key]), key
    # 16 windows per epoch, global batch 8 -> 2 steps per epoch on each rank, and training changed the weights
    assert [(out / f"steps{r}.txt").read_text() for r in (0, 1)] == ["4", "4"]
    init = torch.load(out / "init.pt", weights_only=True)
    assert any(not torch.equal(init[k], w0[k]) for k in w0)
    assert (out / "metrics.jsonl").read_text().count("\n") == 2
