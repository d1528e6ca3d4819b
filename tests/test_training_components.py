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
    gt[0, 0, 0] = 0.0            # invalid: zero
    gt[0, 0, 1] = 192.0          # invalid: at max_disp
    gt[0, 0, 2] = float("nan")   # invalid: non-finite
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
        "features.0.weight", "features.3.weight", "heads.0.weight", "heads.1.weight"]
    assert "features.1.weight" in {names[id(p)] for p in no_decay["params"]}  # BatchNorm weight
    assert all(names[id(p)].endswith((".bias", "features.1.weight")) for p in no_decay["params"])
    assert decay["weight_decay"] == 1e-4 and no_decay["weight_decay"] == 0.0
    assert not any(names[id(p)].startswith("heads.2") for p in decay["params"] + no_decay["params"])


def test_warmup_then_per_iteration_cosine_to_zero():
    schedule = WarmupCosine(warmup_steps=4, total_steps=14)
    assert [schedule(s) for s in range(4)] == [0.25, 0.5, 0.75, 1.0]
    assert schedule(4) == pytest.approx(1.0) and schedule(9) == pytest.approx(0.5) and schedule(14) == pytest.approx(0.0)
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


def test_every_recipe_loads_and_the_sceneflow_recipe_matches_the_paper():
    recipes = {p.stem: load_config(p) for p in CONFIGS.glob("*.toml")}
    ablations = [c for name, c in recipes.items() if name.startswith("ablation_") and name != "ablation_base"]
    assert len(ablations) == 8
    assert len({(c.model.ema, c.model.msf, c.model.coord) for c in ablations}) == 8
    assert all(c.train.epochs == 100 and c.data.crop == (256, 512) for c in ablations)
    sf = recipes["sceneflow"]
    assert sf.data.crop == (288, 576) and sf.train.batch_size * sf.train.accumulate == 24
    assert sf.train.ema_decay == 0.9995 and sf.train.loss_weights == (0.25, 0.5, 1.0)
    head = recipes["virtualtree_headline"]
    assert (head.optim.lr, head.optim.weight_decay, head.optim.warmup_steps, head.train.grad_clip) == (5e-4, 1e-4, 500, 1.0)
    assert recipes["eth3d_finetune"].train.epochs == 1 and recipes["eth3d_finetune"].finetune.weights
    assert recipes["kitti2015"].train.patience == 50 and recipes["middlebury"].data.split == "paper"


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
