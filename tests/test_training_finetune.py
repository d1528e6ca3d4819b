"""`emcstereo finetune`: warm start from the authors' layout, a frozen backbone, self-supervised CLI path."""
from __future__ import annotations

import pytest
import torch
from stereo_training_fixtures import one_thread, planar_scene  # noqa: F401 (autouse fixture)

from stereo import EMCStereo
from stereo.checkpoints import save_checkpoint
from stereo.cli import main
from stereo.io import write_rgb
from stereo.model import ModelConfig
from stereo.training.config import ConfigError
from stereo.training.finetune import freeze, warm_start

CONFIG = """
[model]
ema = false
msf = false
coord = false
max_disp = 48
[data]
dataset = "virtualtree"
crop = [256, 256]
num_workers = 0
color_jitter = false
[train]
epochs = 1
batch_size = 1
precision = "fp32"
vis_count = 0
"""


@pytest.fixture(scope="module")
def authors_weights(tmp_path_factory):
    torch.manual_seed(1)
    model = EMCStereo(ema=False, msf=False, coord=False, max_disp=48)
    path = save_checkpoint(model, tmp_path_factory.mktemp("w") / "authors.pth", layout="authors")
    assert set(torch.load(path, weights_only=True)) == {"model"}
    return path, {k: v.clone() for k, v in model.state_dict().items()}


def test_warm_start_checks_the_variant_and_freeze_names_unknown_modules(authors_weights):
    path, state = authors_weights
    model = warm_start(path, ModelConfig(ema=False, msf=False, coord=False, max_disp=48))
    assert model.training
    for key, value in model.state_dict().items():
        torch.testing.assert_close(value, state[key])
    with pytest.raises(ConfigError, match=r"holds the variant .*'ema': False.* but \[model\] asks for .*'ema': True"):
        warm_start(path, ModelConfig(max_disp=48))
    with pytest.raises(ConfigError, match="no module named encoder; top-level modules are backbone, aggregation"):
        freeze(model, ["encoder"])


def test_finetune_command_self_supervised_with_frozen_backbone(authors_weights, tmp_path):
    path, state = authors_weights
    scene = planar_scene(9, 256, 288, disp_range=(2.0, 30.0), sky_rows=0)
    for sub in ("left", "right"):
        (tmp_path / "pairs" / sub).mkdir(parents=True)
    write_rgb(tmp_path / "pairs" / "left" / "a.png", scene.left)
    write_rgb(tmp_path / "pairs" / "right" / "a.png", scene.right)
    config = tmp_path / "ft.toml"
    config.write_text(CONFIG)
    out = tmp_path / "run"
    status = main(["finetune", "--config", str(config), "--weights", str(path), "--freeze", "backbone",
                   "--unlabelled", str(tmp_path / "pairs"), "--out", str(out), "--no-progress", "--device", "cpu"])
    assert status == 0
    trained = torch.load(out / "last.pth", weights_only=True)
    assert trained["progress"]["step"] == 1 and trained["config"]["ema"] is False
    backbone = [k for k in state if k.startswith("backbone.")]
    for key in backbone:  # weights and BatchNorm running statistics alike
        torch.testing.assert_close(trained["model"][key], state[key], msg=key)
    changed = [k for k in state if k.startswith("aggregation.") and not torch.equal(trained["model"][k], state[k])]
    assert changed, "the unfrozen aggregation must have been trained"
