"""Damaged or hostile checkpoints: bad `config`, NaN/Inf and bit-flipped weights, float64 tensors,
garbage for `--resume`; and the wiring settings each checkpoint source implies."""

from __future__ import annotations

import pytest
import torch
from stereo_training_fixtures import one_thread, planar_scene, write_virtualtree_layout  # noqa: F401

from stereo import EMCStereo, load_model
from stereo.checkpoints import FORMAT, CheckpointError, save_checkpoint
from stereo.cli import main


@pytest.fixture(scope="module")
def small_state() -> dict[str, torch.Tensor]:
    torch.manual_seed(0)
    return EMCStereo(ema=False, msf=False, coord=False, max_disp=16).state_dict()


def write_ours(path, state, config) -> str:
    torch.save({"format": FORMAT, "config": config, "model": state}, path)
    return str(path)


VARIANT = {"ema": False, "msf": False, "coord": False, "max_disp": 16}


@pytest.mark.parametrize(
    ("config", "message"),
    [
        ({**VARIANT, "dropout": 0.1}, r"unknown model setting\(s\) 'dropout'"),
        ({**VARIANT, "max_disp": "lots"}, r"max_disp must be a positive multiple of 16 up to 1024, got 'lots'"),
        ({**VARIANT, "max_disp": 10**12}, r"max_disp must be .* got 1000000000000"),
        ({**VARIANT, "ema": "yes"}, r"ema must be true or false, got 'yes'"),
        ({**VARIANT, "hourglass_wiring": "pre3"}, r"hourglass_wiring must be one of psmnet, openstereo"),
        ([1, 2], r"`config` is a list"),
    ],
)
def test_bad_config_in_our_checkpoint_is_refused_naming_the_key(tmp_path, small_state, capsys, config, message):
    path = write_ours(tmp_path / "bad.pth", small_state, config)
    with pytest.raises(CheckpointError, match=message):
        load_model(path)
    assert main(["export", "--onnx", str(tmp_path / "x.onnx"), "--weights", path]) == 2
    err = capsys.readouterr().err
    assert err.startswith("emcstereo export: error: ") and "bad.pth" in err and "Traceback" not in err


@pytest.mark.parametrize(
    ("value", "what"), [(float("nan"), "NaN/Inf"), (float("inf"), "NaN/Inf"), (3.4e38, "above the plausible")]
)
def test_non_finite_and_bit_flipped_weights_are_refused_naming_the_tensor(tmp_path, small_state, value, what):
    state = {k: v.clone() for k, v in small_state.items()}
    state["aggregation.dres2.conv3.0.weight"].view(-1)[7] = value
    path = write_ours(tmp_path / "flip.pth", state, VARIANT)
    with pytest.raises(CheckpointError, match=rf"tensor aggregation\.dres2\.conv3\.0\.weight holds .*{what}"):
        load_model(path)


def test_float64_weights_load_as_float32_with_a_warning_naming_them(tmp_path, small_state):
    state = {k: v.double() if v.is_floating_point() else v for k, v in small_state.items()}
    path = write_ours(tmp_path / "f64.pth", state, VARIANT)
    with pytest.warns(UserWarning, match=r"cast to float32, e\.g\. backbone\.firstconv\.0\.0\.weight \(float64\)"):
        model = load_model(path)
    assert all(p.dtype == torch.float32 for p in model.parameters())
    torch.testing.assert_close(
        model.state_dict()["aggregation.classif3.1.weight"], small_state["aggregation.classif3.1.weight"]
    )


def test_wiring_follows_the_source_is_stored_in_ours_and_can_be_overridden(tmp_path, small_state):
    legacy = load_model(write_ours(tmp_path / "old.pth", small_state, VARIANT))  # written before the settings
    assert (legacy.config.hourglass_wiring, legacy.config.align_corners) == ("psmnet", True)
    model = EMCStereo(**VARIANT, hourglass_wiring="psmnet", align_corners=False)
    stored = load_model(save_checkpoint(model, tmp_path / "ours.pth"))
    assert stored.config == model.config and stored.aggregation.wiring == "psmnet"
    authors = load_model(save_checkpoint(model, tmp_path / "authors.pth", layout="authors"))
    assert (authors.config.hourglass_wiring, authors.config.align_corners) == ("openstereo", True)
    overridden = load_model(tmp_path / "authors.pth", hourglass_wiring="psmnet", align_corners=False)
    assert overridden.config == model.config
    with pytest.raises(CheckpointError, match="hourglass_wiring must be one of"):
        load_model(tmp_path / "authors.pth", hourglass_wiring="other")


TRAIN_CONFIG = """
[model]
ema = false
msf = false
coord = false
max_disp = 16
[data]
dataset = "virtualtree"
root = "{root}"
crop = [256, 256]
num_workers = 0
[train]
epochs = 1
batch_size = 1
precision = "fp32"
out_dir = "{out}"
"""


@pytest.mark.parametrize("damage", ["garbage", "truncated", "not a training checkpoint"])
def test_train_resume_from_a_damaged_file_is_one_error_line_and_exit_2(tmp_path, small_state, capsys, damage):
    scenes = [planar_scene(seed, 256, 256, disp_range=(1.0, 12.0), sky_rows=0) for seed in range(2)]
    root = write_virtualtree_layout(tmp_path / "vt", scenes, {"train": [0], "val": [1]})
    config = tmp_path / "run.toml"
    config.write_text(TRAIN_CONFIG.format(root=root, out=tmp_path / "out"), encoding="utf-8")
    resume = tmp_path / "last.pth"
    good = write_ours(tmp_path / "good.pth", small_state, VARIANT)
    if damage == "garbage":
        resume.write_bytes(b"\x80\x02garbage" * 50)
    elif damage == "truncated":
        resume.write_bytes(open(good, "rb").read()[:5000])
    else:
        resume.write_bytes(open(good, "rb").read())
    assert main(["train", "--config", str(config), "--resume", str(resume), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("emcstereo train: error: ") and "last.pth" in err and "Traceback" not in err
    assert err.count("\n") == 1


def test_model_settings_in_a_training_recipe_are_checked_as_config_errors():
    from stereo.training.config import ConfigError, build_config

    config = build_config({"model": {"hourglass_wiring": "psmnet", "align_corners": False}})
    assert (config.model.hourglass_wiring, config.model.align_corners) == ("psmnet", False)
    with pytest.raises(ConfigError, match=r"\[model\] hourglass_wiring must be one of psmnet, openstereo"):
        build_config({"model": {"hourglass_wiring": "pre3"}})
    with pytest.raises(ConfigError, match=r"\[model\] max_disp must be a positive multiple of 16 up to 1024"):
        build_config({"model": {"max_disp": 10**12}})
