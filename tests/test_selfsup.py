"""Self-supervised fine-tuning: warping, the occlusion mask, and EPE falling with ground truth withheld."""

from __future__ import annotations

import numpy as np
import torch
from stereo_training_fixtures import TinyStereoNet, one_thread, planar_scene  # noqa: F401 (autouse fixture)

from stereo.datasets import RectifiedPairsDataset
from stereo.evaluation import evaluate
from stereo.io import write_rgb
from stereo.training.config import build_config
from stereo.training.selfsup import (
    SelfSupConfig,
    SelfSupervisedTrainer,
    left_right_consistent,
    photometric_error,
    warp_right_to_left,
)
from stereo.training.trainer import seed_everything


def test_warping_the_right_view_with_true_disparity_rebuilds_the_left_view():
    scene = planar_scene(4, 48, 96, disp_range=(2.0, 9.0), sky_rows=0)
    to_tensor = lambda a: torch.from_numpy(a).permute(2, 0, 1)[None].float() / 255  # noqa: E731
    left, right = to_tensor(scene.left), to_tensor(scene.right)
    disparity = torch.from_numpy(scene.disparity)[None]
    warped, inside = warp_right_to_left(right, disparity)
    interior = inside[0, 0].clone()
    interior[:, :12] = False
    err_true = photometric_error(left, warped)[0, 0][interior].mean()
    err_off = photometric_error(left, warp_right_to_left(right, disparity + 3)[0])[0, 0][interior].mean()
    assert err_true < 0.02 < err_off
    assert not inside[0, 0, :, 0].any() and inside[0, 0, :, -1].all()


def test_left_right_check_rejects_pixels_the_right_view_contradicts():
    left_disp = torch.full((1, 8, 40), 4.0)
    right_disp = torch.full((1, 8, 40), 4.0)
    right_disp[..., 10:14] = 9.0  # seen by left pixels x = 14..17
    mask = left_right_consistent(left_disp, right_disp)[0, 0]
    assert not mask[:, :4].any(), "the warp leaves the image"
    assert not mask[:, 14:18].any() and mask[:, 4:14].all() and mask[:, 18:].all()


def test_self_supervised_fine_tuning_lowers_epe_with_ground_truth_withheld(tmp_path):
    """Smallest honest setup: TinyStereoNet, 6 unlabelled 96×160 pairs, 64×128 crops, 200 steps.

    Measured when written: EPE 6.21 px before, 1.11 px after (≈ 12 s on one thread).
    """
    scenes = [planar_scene(100 + i, 96, 160, disp_range=(3.0, 20.0), sky_rows=0) for i in range(6)]
    for sub in ("left", "right"):
        (tmp_path / sub).mkdir()
    for i, scene in enumerate(scenes):
        write_rgb(tmp_path / "left" / f"{i}.png", scene.left)
        write_rgb(tmp_path / "right" / f"{i}.png", scene.right)
    unlabelled = RectifiedPairsDataset(tmp_path)
    assert all(not unlabelled[i]["disparity"].any() for i in range(len(unlabelled)))

    class WithGroundTruth:  # scoring only; the trainer never sees it
        def __len__(self):
            return len(unlabelled)

        def __getitem__(self, i):
            return {**unlabelled[i], "disparity": scenes[i].disparity}

    config = build_config(
        {
            "model": {"max_disp": 32},
            "data": {"dataset": "virtualtree", "crop": [64, 128], "num_workers": 0, "color_jitter": False},
            "optim": {"lr": 1e-3, "warmup_steps": 10},
            "train": {
                "epochs": 34,
                "batch_size": 1,
                "precision": "fp32",
                "max_steps": 200,
                "patience": 0,
                "vis_count": 0,
                "out_dir": str(tmp_path / "run"),
            },
        }
    )
    seed_everything(0)
    model = TinyStereoNet(max_disp=32)
    before = evaluate(model, WithGroundTruth(), max_disp=32).mean["epe"]
    result = SelfSupervisedTrainer(config, model, unlabelled, None, selfsup=SelfSupConfig(), show_progress=False).fit()
    after = evaluate(model, WithGroundTruth(), max_disp=32).mean["epe"]
    assert result.steps == 200
    assert before > 4.0 and after < 0.4 * before, f"EPE {before:.2f} → {after:.2f} px"
    assert np.isfinite(result.history[-1]["train_loss"])
