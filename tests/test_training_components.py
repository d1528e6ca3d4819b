"""Loss, optimiser groups, LR schedule, EMA, checkpoint RNG state and TOML recipes of the trainer."""

from __future__ import annotations

import math
import random
from pathlib import Path

import numpy as np
import pytest
import torch
from stereo_training_fixtures import TinyStereoNet

from stereo.training.checkpoint import capture_rng_state, restore_rng_state
from stereo.training.config import ConfigError, build_config, load_config
from stereo.training.ema import ModelEMA
from stereo.training.finetune import freeze
from stereo.training.loss import LossConfig, disparity_loss
from stereo.training.optim import WarmupCosine, build_optimizer, build_scheduler, parameter_groups

CONFIGS = Path(__file__).resolve().parents[1] / "stereo" / "configs"


def _gt():
    gt = torch.full((1, 4, 4), 10.0)
    gt[0, 0, 0] = 0.0  # invalid: zero
    gt[0, 0, 1] = 192.0  # invalid: at max_disp
    gt[0, 0, 2] = float("nan")  # invalid: non-finite
    return gt


def test_loss_is_weighted_smooth_l1_over_valid_pixels():
    gt = _gt()
    preds = [gt.nan_to_num(0) + 0.5, gt.nan_to_num(0) + 2.0, gt.nan_to_num(0).clone()]
    loss, terms = disparity_loss(preds, gt)
    assert terms == pytest.approx([0.125, 1.5, 0.0])
    assert loss.item() == pytest.approx(0.5 * 0.125 + 0.7 * 1.5)


def test_predictions_are_clamped_to_twice_max_disp():
    gt = torch.full((1, 2, 2), 10.0)
    loss, terms = disparity_loss([torch.full((1, 2, 2), 5000.0)] * 3, gt, LossConfig(loss_cap=0))
    assert terms[0] == pytest.approx(384.0 - 10.0 - 0.5)


def test_loss_above_cap_reports_the_cap_and_keeps_the_gradient_direction():
    gt = torch.full((1, 2, 2), 1.0)
    pred = torch.tensor([[[300.0, 200.0], [150.0, 100.0]]], requires_grad=True)
    capped, _ = disparity_loss([pred] * 3, gt, LossConfig(loss_cap=100.0))
    assert capped.item() == pytest.approx(100.0)
    capped.backward()
    capped_grad = pred.grad.clone()
    pred.grad = None
    raw, _ = disparity_loss([pred] * 3, gt, LossConfig(loss_cap=0.0))
    raw.backward()
    assert torch.allclose(capped_grad, pred.grad * 100.0 / raw.item(), rtol=1e-5)


def test_empty_mask_gives_zero_with_a_gradient_and_nan_heads_are_skipped():
    pred = torch.ones(1, 3, 3, requires_grad=True)
    loss, terms = disparity_loss([pred] * 3, torch.zeros(1, 3, 3))
    loss.backward()
    assert loss.item() == 0.0 and pred.grad is not None and all(math.isnan(t) for t in terms)
    gt = torch.full((1, 3, 3), 4.0)
    loss, terms = disparity_loss([torch.full((1, 3, 3), float("nan")), gt + 1, gt], gt)
    assert math.isnan(terms[0]) and loss.item() == pytest.approx(0.7 * 0.5)


def test_no_weight_decay_on_biases_and_norm_weights_and_frozen_tensors_left_out():
    model = TinyStereoNet(max_disp=8)
    freeze(model, ["heads.2"])
    decay, no_decay = parameter_groups(model, 1e-4)
    names = {id(p): n for n, p in model.named_parameters()}
    assert sorted(names[id(p)] for p in decay["params"]) == [
        "features.0.weight",
        "features.3.weight",
        "heads.0.weight",
        "heads.1.weight",
    ]
    assert "features.1.weight" in {names[id(p)] for p in no_decay["params"]}  # BatchNorm weight
    assert all(names[id(p)].endswith((".bias", "features.1.weight")) for p in no_decay["params"])
    assert decay["weight_decay"] == 1e-4 and no_decay["weight_decay"] == 0.0
    assert not any(names[id(p)].startswith("heads.2") for p in decay["params"] + no_decay["params"])


def test_warmup_then_per_iteration_cosine_to_zero():
    schedule = WarmupCosine(warmup_steps=4, total_steps=14)
    assert [schedule(s) for s in range(4)] == [0.25, 0.5, 0.75, 1.0]
    assert (
        schedule(4) == pytest.approx(1.0) and schedule(9) == pytest.approx(0.5) and schedule(14) == pytest.approx(0.0)
    )
    model = torch.nn.Linear(2, 2)
    optimizer = build_optimizer(model, lr=1e-3, weight_decay=0.0)
    scheduler = build_scheduler(optimizer, 4, 14)
    lrs = []
    for _ in range(14):
        lrs.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        scheduler.step()
    assert lrs[0] == pytest.approx(2.5e-4) and lrs[9] == pytest.approx(5e-4) and optimizer.param_groups[0]["lr"] == 0.0


def test_ema_blends_weights_and_copies_integer_buffers():
    model = torch.nn.Sequential(torch.nn.Linear(2, 1), torch.nn.BatchNorm1d(1))
    ema = ModelEMA(model, decay=0.9)
    before = model[0].weight.detach().clone()
    with torch.no_grad():
        model[0].weight.add_(1.0)
    model[1].num_batches_tracked += 5
    ema.update(model)
    torch.testing.assert_close(ema.module[0].weight, before + 0.1)
    assert ema.module[1].num_batches_tracked.item() == 5
    assert not any(p.requires_grad for p in ema.module.parameters())


def test_rng_state_round_trips_through_a_weights_only_checkpoint(tmp_path):
    state = capture_rng_state()
    torch.save(state, tmp_path / "rng.pth")
    expected = (random.random(), np.random.rand(), torch.rand(1).item())
    restore_rng_state(torch.load(tmp_path / "rng.pth", weights_only=True))
    assert (random.random(), np.random.rand(), torch.rand(1).item()) == expected


#: The headline recipe, key by key (paper Table "Training configuration", reference facts §4, §5, §7).
HEADLINE = {
    "model": {
        "ema": True,
        "msf": True,
        "coord": True,
        "max_disp": 192,
        "hourglass_wiring": "openstereo",
        "align_corners": True,
    },
    "data": {
        "dataset": "virtualtree",
        "split": "files",
        "train_split": "virtualtree_train.txt",
        "val_split": "virtualtree_val.txt",
        "val_fraction": 0.1,
        "split_seed": 0,
        "group_pattern": "",
        "crop": [256, 512],
        "color_jitter": True,
        "num_workers": 8,
    },
    "optim": {"lr": 5e-4, "weight_decay": 1e-4, "betas": [0.9, 0.999], "warmup_steps": 500},
    "train": {
        "epochs": 300,
        "batch_size": 4,
        "accumulate": 1,
        "precision": "fp16",
        "grad_clip": 1.0,
        "loss_weights": [0.5, 0.7, 1.0],
        "clamp_factor": 2.0,
        "loss_cap": 1000.0,
        "ema_decay": 0.0,
        "patience": 50,
        "seed": 0,
        "log_every": 10,
        "vis_count": 10,
        "checkpoint_every": 0,
        "max_steps": 0,
        "val_max_images": 0,
        "drop_last": True,
    },
    "finetune": {"weights": "", "freeze": []},
}
PAPER_SPLIT = {"split": "paper", "val_fraction": 0.1, "split_seed": 0}
#: How every other recipe differs from the headline one.
RECIPE_CHANGES = {
    **{
        f"ablation_{name}": {
            "model": {"ema": "ema" in name, "msf": "msf" in name, "coord": "coord" in name},
            "train": {"epochs": 100},
        }
        for name in ("none", "ema", "msf", "coord", "ema_msf", "ema_coord", "msf_coord", "ema_msf_coord")
    },
    "ablation_base": {"train": {"epochs": 100}},
    # Paper §Implementation: 288×576, lr 4e-4, 200-iteration warm-up, weights (0.25, 0.5, 1.0), effective
    # batch 24, weight EMA 0.9995, EMA weights of epoch 108; facts §7: bf16, 8 per GPU, no early stopping.
    "sceneflow": {
        "data": {"dataset": "sceneflow", **PAPER_SPLIT, "crop": [288, 576]},
        "optim": {"lr": 4e-4, "warmup_steps": 200},
        "train": {
            "epochs": 108,
            "batch_size": 8,
            "accumulate": 3,
            "precision": "bf16",
            "loss_weights": [0.25, 0.5, 1.0],
            "ema_decay": 0.9995,
            "patience": 0,
        },
    },
    "kitti2012": {"data": {"dataset": "kitti2012", **PAPER_SPLIT}},
    "kitti2015": {"data": {"dataset": "kitti2015", **PAPER_SPLIT}},
    "middlebury": {"data": {"dataset": "middlebury", **PAPER_SPLIT}},
    "eth3d_finetune": {
        "data": {"dataset": "eth3d", **PAPER_SPLIT},
        "optim": {"warmup_steps": 0},
        "train": {"epochs": 1, "patience": 0},
        "finetune": {"weights": "runs/sceneflow/best.pth"},
    },
    "synthetic": {
        "data": {"dataset": "synthetic", "train_split": "train", "val_split": "val"},
        "train": {"epochs": 50, "patience": 10},
    },
}


@pytest.mark.parametrize("name", ["virtualtree_headline", *RECIPE_CHANGES])
def test_every_recipe_file_holds_the_paper_numbers(name):
    recipe = load_config(CONFIGS / f"{name}.toml").to_dict()
    recipe["data"].pop("root")
    recipe["train"].pop("out_dir")
    changes = RECIPE_CHANGES.get(name, {})
    expected = {section: {**values, **changes.get(section, {})} for section, values in HEADLINE.items()}
    assert recipe == expected


def test_the_recipe_folder_holds_exactly_the_pinned_recipes():
    assert sorted(p.stem for p in CONFIGS.glob("*.toml")) == sorted(["virtualtree_headline", *RECIPE_CHANGES])
    sceneflow = load_config(CONFIGS / "sceneflow.toml").train
    assert sceneflow.batch_size * sceneflow.accumulate == 24


def test_config_errors_name_the_key(tmp_path):
    with pytest.raises(ConfigError, match=r"unknown key\(s\) train.epoch;"):
        build_config({"train": {"epoch": 3}})
    with pytest.raises(ConfigError, match=r"train.batch_size: expected an integer, got '4'"):
        build_config({"train": {"batch_size": "4"}})
    with pytest.raises(ConfigError, match="data.group_pattern: required"):
        build_config({"data": {"split": "group"}})
    base = tmp_path / "base.toml"
    base.write_text("[train]\nepochs = 7\nseed = 3\n")
    child = tmp_path / "child.toml"
    child.write_text('extends = "base.toml"\n[train]\nepochs = 9\n')
    config = load_config(child, ["optim.lr=0.001", 'data.root="/x y"'])
    assert (config.train.epochs, config.train.seed, config.optim.lr, config.data.root) == (9, 3, 0.001, "/x y")
