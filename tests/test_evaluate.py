"""Evaluation pads top/right, un-pads before scoring, averages per image and writes JSON, text and panels;
a non-finite prediction fails its image without stopping the evaluation."""

from __future__ import annotations

import json
import logging
import math

import numpy as np
import pytest
import torch
from stereo_training_fixtures import (  # noqa: F401 (one_thread: autouse fixture)
    one_thread,
    planar_scene,
    single_torch_thread,
    write_virtualtree_layout,
)

from stereo import EMCStereo
from stereo.checkpoints import save_checkpoint
from stereo.cli import main
from stereo.datasets import VirtualTreeDataset
from stereo.datasets.transforms import to_network_input
from stereo.evaluation import disparity_panel, evaluate, format_table, predict_disparity
from stereo.io import colorize_disparity, read_rgb
from stereo.metrics import image_metrics


class FirstChannelEcho(torch.nn.Module):
    """Returns 10·(channel 0) + 50 of the left input: every output pixel says where it came from."""

    def forward(self, left, right):
        if left.shape[-2] % 32 or left.shape[-1] % 32 or min(left.shape[-2:]) < 256:
            raise ValueError(f"unpadded input {tuple(left.shape)}")
        return 10 * left[:, 0] + 50


def test_prediction_is_unpadded_top_and_right_back_to_the_input_size():
    left = torch.randn(1, 3, 200, 300)
    pred = predict_disparity(FirstChannelEcho(), left, torch.randn(1, 3, 200, 300))
    assert pred.shape == (1, 200, 300)
    torch.testing.assert_close(pred, 10 * left[:, 0] + 50)


@pytest.fixture(scope="module")
def pairs(tmp_path_factory):
    scenes = [planar_scene(seed, 250, 300, disp_range=(2.0, 40.0)) for seed in (11, 12)]
    root = write_virtualtree_layout(tmp_path_factory.mktemp("vt"), scenes, {"val": [0, 1], "test": [1]})
    torch.manual_seed(0)
    return root, EMCStereo(max_disp=48).eval()


@pytest.fixture(scope="module")
def val_predictions(pairs):
    """The model's un-padded prediction of each val pair, computed directly (not through `evaluate`)."""
    root, model = pairs
    dataset = VirtualTreeDataset(root, "val")
    with single_torch_thread():
        return [
            predict_disparity(model, *(to_network_input(dataset[i])[k][None] for k in ("left", "right")))[0].numpy()
            for i in range(len(dataset))
        ]


def test_metrics_are_averaged_over_images_and_panels_share_one_scale(pairs, val_predictions, tmp_path):
    root, model = pairs
    dataset = VirtualTreeDataset(root, "val")
    result = evaluate(model, dataset, max_disp=48, vis_dir=tmp_path, vis_count=1)
    per_image = [image_metrics(pred, dataset[i]["disparity"], max_disp=48) for i, pred in enumerate(val_predictions)]
    for key in ("epe", "d1_all", "bad_1", "bad_3", "rmse", "abs_rel", "delta1"):
        assert result.mean[key] == pytest.approx((per_image[0][key] + per_image[1][key]) / 2, rel=1e-6)
    assert [r["name"] for r in result.per_image] == ["left image/left_0.png", "left image/left_1.png"]
    panel = read_rgb(tmp_path / "0000.png")
    gt = dataset[0]["disparity"]
    assert panel.shape == (750, 300, 3) and not (tmp_path / "0001.png").exists()
    np.testing.assert_array_equal(panel[500:], colorize_disparity(gt, max_disp=float(gt.max())))
    np.testing.assert_array_equal(panel, disparity_panel(dataset[0]["left"], val_predictions[0], gt, 48))


def test_evaluate_command_writes_json_and_text_tables(pairs, val_predictions, tmp_path, capsys):
    root, model = pairs
    weights = save_checkpoint(model, tmp_path / "w.pth")
    out = tmp_path / "eval"
    status = main(
        [
            "evaluate",
            "--dataset",
            "virtualtree",
            "--root",
            str(root),
            "--weights",
            str(weights),
            "--split",
            "test",
            "--out",
            str(out),
            "--vis",
            "1",
            "--max-disp",
            "48",
            "--no-progress",
            "--device",
            "cpu",
        ]
    )
    assert status == 0
    report = json.loads((out / "metrics.json").read_text())
    test = report["splits"]["test"]
    assert test["images"] == 1 and test["per_image"][0]["name"] == "left image/left_1.png" and test["failed"] == []
    direct = image_metrics(val_predictions[1], VirtualTreeDataset(root, "test")[0]["disparity"], max_disp=48)["epe"]
    assert test["mean"]["epe"] == pytest.approx(direct, rel=1e-6)
    table = (out / "metrics.txt").read_text()
    assert "EPE" in table and "D1-all" in table and f"{direct:.4f}" in table
    assert f"{direct:.4f}" in capsys.readouterr().out
    assert (out / "vis" / "test" / "0000.png").is_file()


class NanOnFirstPair(torch.nn.Module):
    """Predicts NaN everywhere for the first pair it sees and 5 px for every later one."""

    def __init__(self):
        super().__init__()
        self.calls = 0

    def forward(self, left, right):
        self.calls += 1
        return torch.full((left.shape[0], *left.shape[-2:]), math.nan if self.calls == 1 else 5.0)


def test_nan_prediction_fails_its_image_with_a_warning_and_makes_the_selection_epe_infinite(pairs, caplog):
    root, _ = pairs
    dataset = VirtualTreeDataset(root, "val")
    with caplog.at_level(logging.WARNING, logger="stereo.evaluation"):
        result = evaluate(NanOnFirstPair(), dataset, max_disp=48)
    assert result.failed == ["left image/left_0.png"] and result.skipped == []
    assert "left image/left_0.png: the prediction is NaN/Inf" in caplog.text
    assert [r["name"] for r in result.per_image] == ["left image/left_1.png"]
    gt = dataset[1]["disparity"]
    assert result.mean["epe"] == pytest.approx(image_metrics(np.full_like(gt, 5.0), gt, max_disp=48)["epe"])
    assert result.selection_epe == math.inf
    assert result.to_dict()["failed"] == ["left image/left_0.png"]
    row = format_table({"val": result}).splitlines()[1].split()
    assert row[:3] == ["val", "1", "1"] and float(row[3]) == pytest.approx(result.mean["epe"], abs=1e-4)
    with caplog.at_level(logging.WARNING, logger="stereo.evaluation"):
        nothing = evaluate(NanOnFirstPair(), VirtualTreeDataset(root, "test"), max_disp=48)
    assert nothing.mean == {} and nothing.failed == ["left image/left_1.png"] and nothing.selection_epe == math.inf
    assert "no image of 1 could be scored" in caplog.text
