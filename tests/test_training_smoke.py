"""Smoke training of the full EMCStereo on scenes from `emcstereo synth`: loss falls, held-out EPE improves.

Full model (EMA + MSF + CoordAtt), max_disp 48, 256×256 crops of 320×256 synthetic scenes, batch 1,
fp32, one thread: 2 training scenes × 3 epochs = 6 steps; 2 held-out scenes scored before and after
(≈ 30 s of CPU).
Longer runs: benchmarks/smoke_train.py.
"""
from __future__ import annotations

import torch

from stereo import EMCStereo
from stereo_training_fixtures import one_thread  # noqa: F401 (autouse fixture)
from stereo.datasets import SyntheticDataset
from stereo.evaluation import evaluate
from stereo.synth.writer import split_line, write_dataset
from stereo.training.config import build_config
from stereo.training.trainer import Trainer, seed_everything


def test_full_model_loss_falls_and_held_out_epe_improves_on_synthetic_scenes(tmp_path):
    root = write_dataset(tmp_path / "synth", scenes=4, seed=5, width=320, height=256, progress=False).root
    (root / "smoke_train.txt").write_text(split_line(0) + "\n" + split_line(1) + "\n")
    (root / "smoke_heldout.txt").write_text(split_line(2) + "\n" + split_line(3) + "\n")
    train_set, held_out = SyntheticDataset(root, "smoke_train"), SyntheticDataset(root, "smoke_heldout")
    config = build_config({
        "model": {"max_disp": 48},
        "data": {"dataset": "synthetic", "root": str(root), "crop": [256, 256], "num_workers": 0},
        "optim": {"lr": 1e-3, "warmup_steps": 1},
        "train": {"epochs": 3, "batch_size": 1, "precision": "fp32", "patience": 0, "vis_count": 0,
                  "out_dir": str(tmp_path / "run")},
    })
    seed_everything(0)
    model = EMCStereo(max_disp=48)
    untrained = evaluate(model, held_out, max_disp=48).mean["epe"]
    result = Trainer(config, model, train_set, None, show_progress=False).fit()
    losses = [row["train_loss"] for row in result.history]
    trained = evaluate(model, held_out, max_disp=48).mean["epe"]
    print(f"train loss per epoch {losses}; held-out EPE {untrained:.3f} → {trained:.3f} px")
    assert result.steps == 6 and len(losses) == 3
    # Measured when written (three runs): loss 35–37 → 6.2–6.9 → 1.8–2.4; held-out EPE 21.1–21.3 →
    # 14.2–15.6 px (the synthetic scenes were still being tuned between runs). The held-out
    # score lags the training loss because eval-mode BatchNorm statistics are still mostly their
    # initial values after 6 steps (momentum 0.1).
    assert losses[-1] < 0.2 * losses[0], losses
    assert trained < 0.85 * untrained, (untrained, trained)
    assert (tmp_path / "run" / "training_curve.png").is_file()
