"""Trainer behaviours on a small network: gradient accumulation, early stopping, non-finite steps skipped."""
from __future__ import annotations

import math

import pytest
import torch
from stereo_training_fixtures import TinyStereoNet, one_thread, planar_scene, write_virtualtree_layout  # noqa: F401

from stereo.datasets import VirtualTreeDataset
from stereo.training.config import build_config
from stereo.training.finetune import freeze
from stereo.training.trainer import Trainer, seed_everything


pytestmark = pytest.mark.filterwarnings("ignore:Detected call of `lr_scheduler.step\\(\\)` before:UserWarning")


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    scenes = [planar_scene(seed, 64, 96, disp_range=(1.0, 12.0), sky_rows=0) for seed in range(5)]
    return write_virtualtree_layout(tmp_path_factory.mktemp("vt"), scenes, {"train": [0, 1, 2, 3], "val": [4]})


def make_trainer(root, out, *, frozen=("features",), validate=True, **train) -> Trainer:
    config = build_config({
        "model": {"max_disp": 16},
        "data": {"dataset": "virtualtree", "root": str(root), "crop": [64, 96], "num_workers": 0, "color_jitter": False},
        "optim": {"warmup_steps": 1, "lr": train.pop("lr", 1e-3)},
        "train": {"epochs": 1, "batch_size": 1, "precision": "fp32", "vis_count": 0, "out_dir": str(out), **train},
    })
    seed_everything(0)
    model = TinyStereoNet(max_disp=16)
    freeze(model, frozen)  # BatchNorm kept in eval mode: samples stay independent inside a batch
    val_set = VirtualTreeDataset(root, "val") if validate else None
    return Trainer(config, model, VirtualTreeDataset(root, "train"), val_set, frozen=frozen, show_progress=False)


def test_accumulating_two_micro_batches_equals_one_batch_of_two(root, tmp_path):
    accumulated = make_trainer(root, tmp_path / "a", batch_size=1, accumulate=2)
    batched = make_trainer(root, tmp_path / "b", batch_size=2, accumulate=1)
    assert accumulated.fit().steps == batched.fit().steps == 2
    for (name, a), b in zip(accumulated.model.named_parameters(), batched.model.parameters()):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6, msg=name)


def test_training_stops_after_patience_epochs_without_improvement(root, tmp_path):
    trainer = make_trainer(root, tmp_path, lr=1e-30, epochs=10, patience=2)  # the weights cannot move
    result = trainer.fit()
    assert result.stopped_early and not result.interrupted
    assert result.epochs_completed == 3 and result.best_epoch == 1
    epes = [row["val_epe"] for row in result.history]
    assert epes[0] == epes[1] == epes[2]
    assert (tmp_path / "best.pth").is_file() and (tmp_path / "metrics.csv").read_text().count("\n") == 4


def test_steps_with_non_finite_gradients_are_skipped_and_leave_weights_alone(root, tmp_path):
    trainer = make_trainer(root, tmp_path, frozen=(), validate=False)
    with torch.no_grad():
        trainer.model.heads[0].bias[3] = math.inf
    before = {n: p.detach().clone() for n, p in trainer.model.named_parameters()}
    result = trainer.fit()
    assert result.steps == 4 and trainer.progress["skipped_steps"] == 4
    assert result.history[0]["skipped_steps"] == 4
    for name, param in trainer.model.named_parameters():
        torch.testing.assert_close(param, before[name], equal_nan=True, msg=name)


@pytest.mark.parametrize("precision", ["fp16", "bf16"])
def test_mixed_precision_steps_train_and_fp16_uses_the_grad_scaler(root, tmp_path, precision):
    trainer = make_trainer(root, tmp_path, frozen=(), validate=False, precision=precision)
    before = {n: p.detach().clone() for n, p in trainer.model.named_parameters()}
    result = trainer.fit()
    assert result.steps == 4 and trainer.scaler.is_enabled() == (precision == "fp16")
    assert all(torch.isfinite(p).all() for p in trainer.model.parameters())
    assert result.history[0]["skipped_steps"] < 4
    assert any(not torch.equal(p, before[n]) for n, p in trainer.model.named_parameters())
    if precision == "fp16":
        assert torch.load(tmp_path / "last.pth", weights_only=True)["scaler"]["scale"] > 0
