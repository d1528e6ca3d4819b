"""Trainer behaviours on a small network: gradient accumulation, early stopping, non-finite steps skipped,
a diverged (NaN) validation that is never the best, and exact resume of every piece of training state."""

from __future__ import annotations

import json
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


def make_trainer(root, out, *, frozen=("features",), validate=True, jitter=False, **train) -> Trainer:
    config = build_config(
        {
            "model": {"max_disp": 16},
            "data": {
                "dataset": "virtualtree",
                "root": str(root),
                "crop": [64, 96],
                "num_workers": 0,
                "color_jitter": jitter,
            },
            "optim": {"warmup_steps": 1, "lr": train.pop("lr", 1e-3)},
            "train": {"epochs": 1, "batch_size": 1, "precision": "fp32", "vis_count": 0, "out_dir": str(out), **train},
        }
    )
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


def test_nan_validation_is_counted_as_failed_never_best_and_training_goes_on(root, tmp_path):
    trainer = make_trainer(root, tmp_path, frozen=(), epochs=5, patience=2)
    with torch.no_grad():
        trainer.model.heads[2].bias.fill_(math.nan)  # every prediction NaN, in training and validation
    result = trainer.fit()
    assert result.stopped_early and result.epochs_completed == 2, "failed epochs count towards patience"
    assert [row["val_epe"] for row in result.history] == [math.inf, math.inf]
    assert [row["val_failed"] for row in result.history] == [1, 1]
    assert result.best_epe == math.inf and result.best_epoch == -1
    assert not (tmp_path / "best.pth").exists()
    rows = json.loads((tmp_path / "metrics.json").read_text(), parse_constant=lambda c: pytest.fail(f"non-JSON {c}"))
    assert [row["val_epe"] for row in rows] == [None, None]


def _training_state(trainer: Trainer) -> dict:
    return {
        "model": trainer.model.state_dict(),
        "ema": trainer.ema.state_dict(),
        "scaler": trainer.scaler.state_dict(),
        "optimizer": trainer.optimizer.state_dict()["state"],
        "lr": trainer.optimizer.param_groups[0]["lr"],
        "progress": {k: v for k, v in trainer.progress.items() if k != "history"},
        "history": [{k: v for k, v in row.items() if k != "seconds"} for row in trainer.progress["history"]],
    }


def test_k_steps_then_resume_equals_n_steps_in_one_go_with_ema_scaler_and_jitter(root, tmp_path):
    """In-process interruption (max_steps) mid-epoch, resumed across an epoch end with validation.

    The real network's resume, after a SIGKILL, is pinned in test_training_resume.py.
    """
    settings = dict(frozen=(), jitter=True, epochs=2, precision="fp16", ema_decay=0.9)
    one_go = make_trainer(root, tmp_path / "one", max_steps=6, **settings)
    assert one_go.fit().steps == 6
    first = make_trainer(root, tmp_path / "split", max_steps=3, **settings).fit()
    assert first.interrupted and first.steps == 3 and first.epochs_completed == 0
    saved = torch.load(tmp_path / "split" / "last.pth", weights_only=True)["progress"]
    assert (saved["step"], saved["batch_in_epoch"]) == (3, 3)
    resumed = make_trainer(root, tmp_path / "split", max_steps=6, **settings)
    resumed.resume(tmp_path / "split" / "last.pth")
    assert resumed.fit().steps == 6
    expected, actual = _training_state(one_go), _training_state(resumed)
    assert actual["progress"] == expected["progress"] and actual["history"] == expected["history"]
    assert actual["lr"] == expected["lr"] and actual["scaler"] == expected["scaler"]
    for part in ("model", "ema"):
        for key, value in expected[part].items():
            torch.testing.assert_close(actual[part][key], value, msg=f"{part}.{key}")
    for index, state in expected["optimizer"].items():
        torch.testing.assert_close(actual["optimizer"][index]["exp_avg"], state["exp_avg"])


def test_gradient_norm_is_clipped_to_grad_clip_before_each_optimiser_step(root, tmp_path):
    norms: dict[float, list[float]] = {}
    for clip in (0.0, 1e-3):  # 0 = no clipping
        trainer = make_trainer(root, tmp_path / str(clip), frozen=(), validate=False, grad_clip=clip)
        seen = norms.setdefault(clip, [])
        trainer.optimizer.register_step_pre_hook(
            lambda opt, args, kwargs, seen=seen: seen.append(
                math.sqrt(
                    sum(
                        float(p.grad.pow(2).sum())
                        for group in opt.param_groups
                        for p in group["params"]
                        if p.grad is not None
                    )
                )
            )
        )
        assert trainer.fit().steps == 4
    assert len(norms[1e-3]) == 4 and max(norms[1e-3]) <= 1e-3 * (1 + 1e-4)
    assert min(norms[0.0]) > 1e-2, norms[0.0]
