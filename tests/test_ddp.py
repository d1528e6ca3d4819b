"""torchrun with two CPU processes (gloo): DistributedDataParallel keeps ranks in step, rank 0 alone writes.

One launch of tests/ddp_train_worker.py: first the Trainer on a small network, so that both ranks'
weights and sampled indices can be compared; then, in the same process group, the real
`emcstereo train` entry point on the real network (sharding, the rank-0 report and files, and
`--set` switching CoordAtt off).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from stereo_training_fixtures import planar_scene, write_virtualtree_layout

PROJECT = Path(__file__).resolve().parents[1]
CONFIG = """
[model]
max_disp = 16
[data]
dataset = "virtualtree"
root = "{root}"
crop = {crop}
num_workers = 0
[optim]
warmup_steps = 1
[train]
epochs = 1
batch_size = 1
precision = "fp32"
vis_count = 0
"""


@pytest.fixture(scope="module")
def job(tmp_path_factory) -> dict:
    """One torchrun launch: the worker's small-network run, then `emcstereo train` on the real network."""
    tmp = tmp_path_factory.mktemp("ddp")
    scenes = [planar_scene(seed, 64, 112, disp_range=(1.0, 12.0), sky_rows=4) for seed in range(5)]
    small = write_virtualtree_layout(tmp / "small", scenes, {"train": [0, 1, 2, 3], "val": [4]})
    (tmp / "small.toml").write_text(CONFIG.format(root=small, crop="[64, 96]"), encoding="utf-8")
    scenes = [planar_scene(seed, 256, 256, disp_range=(1.0, 12.0), sky_rows=4) for seed in range(3)]
    full = write_virtualtree_layout(tmp / "full", scenes, {"train": [0, 1], "val": [2]})
    (tmp / "full.toml").write_text(CONFIG.format(root=full, crop="[256, 256]"), encoding="utf-8")
    out, cli_out = tmp / "out", tmp / "cli_run"
    out.mkdir()
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(PROJECT)}
    command = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc_per_node",
        "2",
        str(PROJECT / "tests" / "ddp_train_worker.py"),
        str(tmp / "small.toml"),
        str(out),
        "train",
        "--config",
        str(tmp / "full.toml"),
        "--out",
        str(cli_out),
        "--no-progress",
        "--device",
        "cpu",
        "--set",
        "model.coord=false",
    ]
    done = subprocess.run(command, cwd=PROJECT, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    return {"out": out, "cli_out": cli_out, "stdout": done.stdout}


def test_two_process_ddp_trains_identical_replicas_on_disjoint_shards(job):
    out = job["out"]
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


def test_emcstereo_train_under_torchrun_shards_the_data_and_reports_once(job):
    out = job["cli_out"]
    reports = [line for line in job["stdout"].splitlines() if line.startswith("finished:")]
    assert len(reports) == 1 and reports[0].startswith("finished: 1 steps, 1 epochs"), job["stdout"]
    checkpoint = torch.load(out / "last.pth", weights_only=True)
    assert checkpoint["progress"]["step"] == 1, "2 pairs / 2 processes / batch 1 = 1 step per epoch"
    assert checkpoint["config"] == {
        "ema": True,
        "msf": True,
        "coord": False,
        "max_disp": 16,
        "hourglass_wiring": "openstereo",
        "align_corners": True,
    }
    assert len(checkpoint["progress"]["history"]) == 1 and (out / "metrics.csv").is_file()
    best = torch.load(out / "best.pth", weights_only=True)
    assert best["epoch"] == 1 and best["val_metrics"]["epe"] == checkpoint["progress"]["history"][0]["val_epe"]
    for key, value in best["model"].items():
        torch.testing.assert_close(value, checkpoint["model"][key], msg=key)
