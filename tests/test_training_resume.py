"""Exact resume of the real EMCStereo: k steps + resume == N steps in one go, also after a SIGKILL.

Small but real: the full network (EMA + MSF + CoordAtt) with max_disp 48, 256×256 crops, batch 1,
two training pairs (two steps per epoch, so N = 3 crosses an epoch end with its validation),
fp32 on one CPU thread so the comparison is deterministic.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from stereo_training_fixtures import one_thread, planar_scene, write_virtualtree_layout  # noqa: F401 (autouse fixture)

from stereo.training.config import build_config
from stereo.training.run import run_training

PROJECT = Path(__file__).resolve().parents[1]
N_STEPS = 3


@pytest.fixture(scope="module")
def data_root(tmp_path_factory):
    scenes = [planar_scene(seed, 272, 288, disp_range=(2.0, 40.0)) for seed in range(3)]
    return write_virtualtree_layout(tmp_path_factory.mktemp("vt"), scenes, {"train": [0, 1], "val": [2]})


def recipe_tree(data_root: Path, out_dir: Path, **train) -> dict:
    return {
        "model": {"max_disp": 48},
        "data": {"dataset": "virtualtree", "root": str(data_root), "crop": [256, 256], "num_workers": 0},
        "optim": {"warmup_steps": 2},
        "train": {"epochs": 2, "batch_size": 1, "precision": "fp32", "out_dir": str(out_dir), "vis_count": 0,
                  "log_every": 1, **train},
    }


def _toml(tree: dict) -> str:
    def value(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return '"' + v.replace("\\", "\\\\") + '"'
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return repr(v)
    return "\n".join(f"[{s}]\n" + "\n".join(f"{k} = {value(v)}" for k, v in t.items()) for s, t in tree.items()) + "\n"


@pytest.fixture(scope="module")
def one_go(data_root, tmp_path_factory):
    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("one_go")
    result = run_training(build_config(recipe_tree(data_root, out, max_steps=N_STEPS)), show_progress=False)
    assert result.steps == N_STEPS and result.epochs_completed == 1
    return torch.load(out / "last.pth", weights_only=True)


def assert_same_state(a: dict, b: dict) -> None:
    assert a["progress"]["step"] == b["progress"]["step"] == N_STEPS
    assert a["progress"]["batch_in_epoch"] == b["progress"]["batch_in_epoch"] == 1
    assert a["scheduler"]["last_epoch"] == b["scheduler"]["last_epoch"] == N_STEPS
    assert a["progress"]["history"][0]["train_loss"] == pytest.approx(b["progress"]["history"][0]["train_loss"], rel=1e-5)
    assert a["progress"]["history"][0]["val_epe"] == pytest.approx(b["progress"]["history"][0]["val_epe"], rel=1e-5)
    assert a["model"].keys() == b["model"].keys()
    for key in a["model"]:
        torch.testing.assert_close(a["model"][key], b["model"][key], rtol=1e-5, atol=1e-6, msg=key)
    for index, state in a["optimizer"]["state"].items():
        torch.testing.assert_close(state["exp_avg_sq"], b["optimizer"]["state"][index]["exp_avg_sq"], rtol=1e-4, atol=1e-9)


def test_k_steps_then_resume_equals_n_steps_in_one_go(data_root, tmp_path, one_go):
    first = run_training(build_config(recipe_tree(data_root, tmp_path, max_steps=1)), show_progress=False)
    assert first.interrupted and first.steps == 1
    start = torch.load(tmp_path / "last.pth", weights_only=True)
    assert start["progress"]["step"] == 1 and start["progress"]["batch_in_epoch"] == 1
    resumed = run_training(build_config(recipe_tree(data_root, tmp_path, max_steps=N_STEPS)), resume="auto",
                           show_progress=False)
    assert resumed.steps == N_STEPS
    final = torch.load(tmp_path / "last.pth", weights_only=True)
    assert_same_state(final, one_go)
    moved = sum(float((final["model"][k].float() - start["model"][k].float()).abs().sum()) for k in final["model"])
    assert moved > 0, "the resumed steps must change the weights"


def test_resume_after_sigkill_mid_run_matches_the_uninterrupted_run(data_root, tmp_path, one_go):
    tree = recipe_tree(data_root, tmp_path / "run", max_steps=N_STEPS, checkpoint_every=1)
    config_file = tmp_path / "run.toml"
    config_file.write_text(_toml(tree), encoding="utf-8")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(PROJECT)}
    command = [sys.executable, "-m", "stereo.cli", "train", "--config", str(config_file), "--no-progress", "--device", "cpu"]
    process = subprocess.Popen(command, cwd=PROJECT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    last = tmp_path / "run" / "last.pth"
    killed_at = None
    deadline = time.monotonic() + 240
    try:
        while time.monotonic() < deadline and process.poll() is None:
            if last.is_file():
                killed_at = torch.load(last, weights_only=True)["progress"]["step"]
                if killed_at >= 1:
                    process.send_signal(signal.SIGKILL)
                    break
            time.sleep(0.05)
    finally:
        if process.poll() is None:
            process.kill()
        stderr = process.communicate()[1].decode(errors="replace")
    assert process.returncode == -signal.SIGKILL, f"training ended on its own before the kill: {stderr[-2000:]}"
    assert killed_at is not None and 1 <= killed_at < N_STEPS
    resumed = run_training(build_config(tree), resume="auto", show_progress=False)
    assert resumed.steps == N_STEPS
    assert_same_state(torch.load(last, weights_only=True), one_go)
