"""Evaluation pads top/right, un-pads before scoring, averages per image and writes JSON, text and panels."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from stereo_training_fixtures import one_thread, planar_scene, write_virtualtree_layout  # noqa: F401 (autouse fixture)

from stereo import EMCStereo
from stereo.checkpoints import save_checkpoint
from stereo.cli import main
from stereo.datasets import VirtualTreeDataset
from stereo.datasets.transforms import to_network_input
from stereo.evaluation import disparity_panel, evaluate, predict_disparity
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


def test_metrics_are_averaged_over_images_and_panels_share_one_scale(pairs, tmp_path):
    root, model = pairs
    dataset = VirtualTreeDataset(root, "val")
    result = evaluate(model, dataset, max_disp=48, vis_dir=tmp_path, vis_count=1)
    per_image = []
    for index in range(2):
        raw = dataset[index]
        sample = to_network_input(raw)
        pred = predict_disparity(model, sample["left"][None], sample["right"][None])[0].numpy()
        per_image.append(image_metrics(pred, raw["disparity"], max_disp=48))
    for key in ("epe", "d1_all", "bad_1", "bad_3", "rmse", "abs_rel", "delta1"):
        assert result.mean[key] == pytest.approx((per_image[0][key] + per_image[1][key]) / 2, rel=1e-6)
    assert [r["name"] for r in result.per_image] == ["left image/left_0.png", "left image/left_1.png"]
    panel = read_rgb(tmp_path / "0000.png")
    gt = dataset[0]["disparity"]
    assert panel.shape == (750, 300, 3) and not (tmp_path / "0001.png").exists()
    np.testing.assert_array_equal(panel[500:], colorize_disparity(gt, max_disp=float(gt.max())))
    prediction = predict_disparity(model, *(to_network_input(dataset[0])[k][None] for k in ("left", "right")))[0]
    np.testing.assert_array_equal(panel, disparity_panel(dataset[0]["left"], prediction.numpy(), gt, 48))


def test_evaluate_command_writes_json_and_text_tables(pairs, tmp_path, capsys):
    root, model = pairs
    weights = save_checkpoint(model, tmp_path / "w.pth")
    out = tmp_path / "eval"
    status = main(["evaluate", "--dataset", "virtualtree", "--root", str(root), "--weights", str(weights),
                   "--split", "test", "--out", str(out), "--vis", "1", "--max-disp", "48", "--no-progress",
                   "--device", "cpu"])
    assert status == 0
    report = json.loads((out / "metrics.json").read_text())
    test = report["splits"]["test"]
    assert test["images"] == 1 and test["per_image"][0]["name"] == "left image/left_1.png"
    direct = evaluate(model, VirtualTreeDataset(root, "test"), max_disp=48)
    assert test["mean"]["epe"] == pytest.approx(direct.mean["epe"], rel=1e-6)
    table = (out / "metrics.txt").read_text()
    assert "EPE" in table and "D1-all" in table and f"{direct.mean['epe']:.4f}" in table
    assert f"{direct.mean['epe']:.4f}" in capsys.readouterr().out
    assert (out / "vis" / "test" / "0000.png").is_file()
