"""`emcstereo finetune`: warm start from the authors' and PSMNet's layouts, a frozen backbone,
self-supervised CLI path."""

from __future__ import annotations

import re

import pytest
import torch
from stereo_training_fixtures import one_thread, planar_scene  # noqa: F401 (autouse fixture)
from test_checkpoints import state_from_listing

from stereo import EMCStereo
from stereo.checkpoints import save_checkpoint
from stereo.cli import main
from stereo.io import write_rgb
from stereo.model import ModelConfig
from stereo.training.config import ConfigError, build_config
from stereo.training.finetune import freeze, warm_start
from stereo.training.run import build_model

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


def test_finetune_warm_starts_from_a_psmnet_checkpoint_into_the_no_attention_variant(tmp_path, reference_docs):
    psmnet = state_from_listing(reference_docs / "psmnet_stackhourglass_state_dict.txt", seed=4)
    path = tmp_path / "pretrained_sceneflow.tar"
    torch.save({"epoch": 10, "state_dict": {"module." + k: v for k, v in psmnet.items()}}, path)
    tree = {
        "model": {"ema": False, "msf": False, "coord": False, "max_disp": 192},
        "finetune": {"weights": str(path), "freeze": ["backbone"]},
    }
    model = build_model(build_config(tree))  # what `emcstereo finetune --weights` runs
    assert model.training and sum(p.numel() for p in model.parameters()) == 5_225_152
    ours = model.state_dict()
    torch.testing.assert_close(ours["backbone.firstconv.2.0.weight"], psmnet["feature_extraction.firstconv.4.0.weight"])
    torch.testing.assert_close(
        ours["backbone.layer2.5.conv1.1.running_var"], psmnet["feature_extraction.layer2.5.conv1.0.1.running_var"]
    )
    torch.testing.assert_close(ours["aggregation.dres4.conv3.0.weight"], psmnet["dres4.conv3.0.0.weight"])
    torch.testing.assert_close(ours["aggregation.classif3.1.weight"], psmnet["classif3.2.weight"])
    frozen = freeze(model, ["backbone"])
    assert frozen and all(name.startswith("backbone.") for name in frozen)
    with pytest.raises(
        ConfigError, match=r"pretrained_sceneflow.tar: holds the variant .*'ema': False.*'max_disp': 192"
    ):
        build_model(build_config({**tree, "model": {"max_disp": 192}}))


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
    status = main(
        [
            "finetune",
            "--config",
            str(config),
            "--weights",
            str(path),
            "--freeze",
            "backbone",
            "--unlabelled",
            str(tmp_path / "pairs"),
            "--out",
            str(out),
            "--no-progress",
            "--device",
            "cpu",
        ]
    )
    assert status == 0
    trained = torch.load(out / "last.pth", weights_only=True)
    assert trained["progress"]["step"] == 1 and trained["config"]["ema"] is False
    backbone = [k for k in state if k.startswith("backbone.")]
    for key in backbone:  # weights and BatchNorm running statistics alike
        torch.testing.assert_close(trained["model"][key], state[key], msg=key)
    changed = [k for k in state if k.startswith("aggregation.") and not torch.equal(trained["model"][k], state[k])]
    assert changed, "the unfrozen aggregation must have been trained"


def test_train_finetune_and_evaluate_report_bad_input_without_a_traceback_and_status_2(
    authors_weights, tmp_path, capsys
):
    path, _ = authors_weights
    config = tmp_path / "ft.toml"
    config.write_text(CONFIG)
    cases = [
        (
            ["train", "--config", str(tmp_path / "missing.toml")],
            "emcstereo train: error: .*missing.toml: configuration file not found",
        ),
        (
            ["train", "--config", str(config), "--set", "train.epochs=many"],
            "train.epochs: expected an integer, got 'many'",
        ),
        (
            ["finetune", "--config", str(config), "--weights", str(path), "--data-root", str(tmp_path / "none")],
            "emcstereo finetune: error: .*none: folder not found; expected a VirtualTree-layout dataset",
        ),
        (["finetune", "--config", str(config), "--weights", str(config)], "ft.toml: not a .*torch checkpoint"),
        (
            [
                "evaluate",
                "--dataset",
                "eth3d",
                "--root",
                str(tmp_path),
                "--weights",
                str(path),
                "--out",
                str(tmp_path / "e"),
            ],
            "emcstereo evaluate: error: .*two_view_training: folder not found; expected ETH3D scenes",
        ),
    ]
    for argv, message in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith(f"emcstereo {argv[0]}: error: ") and "Traceback" not in err and re.search(message, err), (
            err
        )
