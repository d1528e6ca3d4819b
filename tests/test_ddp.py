"""torchrun with two CPU processes (gloo): DistributedDataParallel keeps ranks in step, rank 0 alone writes."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import torch
from stereo_training_fixtures import planar_scene, write_virtualtree_layout

PROJECT = Path(__file__).resolve().parents[1]
CONFIG = """
[model]
max_disp = 16
[data]
dataset = "virtualtree"
root = "{root}"
crop = [64, 96]
num_workers = 0
[optim]
warmup_steps = 1
[train]
epochs = 1
batch_size = 1
precision = "fp32"
vis_count = 0
"""


def test_two_process_ddp_trains_identical_replicas_on_disjoint_shards(tmp_path):
    scenes = [planar_scene(seed, 64, 112, disp_range=(1.0, 12.0), sky_rows=4) for seed in range(5)]
    root = write_virtualtree_layout(tmp_path / "vt", scenes, {"train": [0, 1, 2, 3], "val": [4]})
    config = tmp_path / "ddp.toml"
    config.write_text(CONFIG.format(root=root), encoding="utf-8")
    out = tmp_path / "out"
    out.mkdir()
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(PROJECT)}
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
               str(PROJECT / "tests" / "ddp_train_worker.py"), str(config), str(out)]
    done = subprocess.run(command, cwd=PROJECT, env=env, capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stderr[-3000:]
    ranks = [torch.load(out / f"rank{r}.pt", weights_only=True) for r in (0, 1)]
    assert [r["world_size"] for r in ranks] == [2, 2]
    assert ranks[0]["steps"] == ranks[1]["steps"] == 2, "4 pairs / 2 processes / batch 1 = 2 steps per epoch"
    assert set(ranks[0]["seen"]).isdisjoint(ranks[1]["seen"])
    assert sorted(ranks[0]["seen"] + ranks[1]["seen"]) == [0, 1, 2, 3]
    for name, value in ranks[0]["params"].items():
        torch.testing.assert_close(value, ranks[1]["params"][name], msg=name)
        torch.testing.assert_close(ranks[0]["initial"][name], ranks[1]["initial"][name])
    assert any(not torch.equal(ranks[0]["params"][n], ranks[0]["initial"][n]) for n in ranks[0]["params"])
    assert (out / "run_rank0" / "last.pth").is_file() and (out / "run_rank0" / "metrics.csv").is_file()
    assert (out / "run_rank0" / "best.pth").is_file()
    assert not (out / "run_rank1").exists() or not any((out / "run_rank1").iterdir())
    checkpoint = torch.load(out / "run_rank0" / "last.pth", weights_only=True)
    assert checkpoint["progress"]["step"] == 2 and len(checkpoint["progress"]["history"]) == 1
    for name, value in ranks[0]["params"].items():
        torch.testing.assert_close(checkpoint["model"][name], value)
