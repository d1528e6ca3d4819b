"""Checkpoint loading: the authors' release layout, PSMNet's, ours; strictness and bad files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from stereo import EMCStereo, load_model
from stereo.checkpoints import CheckpointError, read_checkpoint, save_checkpoint


def state_from_listing(listing: Path, seed: int = 0) -> dict[str, torch.Tensor]:
    """Random tensors with exactly the names and shapes of a reference key list."""
    gen = torch.Generator().manual_seed(seed)
    state = {}
    for line in listing.read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        key, shape_text = line.split()
        shape = [int(s) for s in shape_text.strip("[]").split(",") if s]
        if key.endswith("num_batches_tracked"):
            state[key] = torch.tensor(7)
        elif key.endswith("running_var"):
            state[key] = torch.rand(shape, generator=gen) + 0.5
        else:
            state[key] = torch.randn(shape, generator=gen) * 0.05
    return state


@pytest.fixture()
def authors_checkpoint(tmp_path, reference_docs) -> tuple[Path, dict[str, torch.Tensor]]:
    state = state_from_listing(reference_docs / "emcstereo_authors_state_dict.txt")
    # The authors' layout with other bytes than the release: under the release's file name it would be
    # refused by the registry's SHA-256 check (tests/test_weights_on_load.py).
    path = tmp_path / "authors_layout.pth"
    metrics = {"epe": np.float64(1.314849), "d1_all": np.float32(0.058)}  # as training scripts store them
    torch.save({"model": state, "optimizer": {}, "epoch": 252, "global_step": 279312, "val_metrics": metrics}, path)
    return path, state


def test_authors_release_layout_loads_every_tensor(authors_checkpoint):
    path, state = authors_checkpoint
    model = load_model(path)
    assert model.config.to_dict() == {
        "ema": True,
        "msf": True,
        "coord": True,
        "max_disp": 192,
        "hourglass_wiring": "openstereo",
        "align_corners": True,
    }
    ours = model.state_dict()
    torch.testing.assert_close(ours["backbone.ema.conv3x3.weight"], state["Backbone.ema.conv3x3.weight"])
    torch.testing.assert_close(
        ours["aggregation.classif3.1.weight"], state["CostProcessor.aggregator.classif3.1.weight"]
    )
    assert not model.training


def test_authors_noattention_variant_is_detected_from_keys(tmp_path, reference_docs):
    state = state_from_listing(reference_docs / "emcstereo_authors_noattn_state_dict.txt")
    path = tmp_path / "none.pth"
    torch.save({"model": state}, path)
    model = load_model(path)
    assert (model.config.ema, model.config.msf, model.config.coord) == (False, False, False)
    assert model.backbone.lastconv[0][0].weight.shape == (128, 320, 3, 3)


@pytest.mark.parametrize("prefix", ["", "module."])
def test_psmnet_checkpoint_loads_into_no_attention_variant(tmp_path, reference_docs, prefix):
    state = state_from_listing(reference_docs / "psmnet_stackhourglass_state_dict.txt", seed=3)
    path = tmp_path / "pretrained_sceneflow.tar"
    torch.save({"epoch": 10, "state_dict": {prefix + k: v for k, v in state.items()}}, path)
    model = load_model(path)
    ours = model.state_dict()
    assert sum(p.numel() for p in model.parameters()) == 5_225_152
    # PSMNet's code: the third hourglass takes pre1; its F.upsample leaves align_corners=False.
    assert (model.config.hourglass_wiring, model.config.align_corners) == ("psmnet", False)
    # PSMNet's shortcut convs have no bias and its regression is 0..191: the added tensors keep its output.
    assert float(ours["backbone.layer2.0.downsample.0.bias"].abs().sum()) == 0.0
    assert float(ours["backbone.layer3.0.downsample.0.bias"].abs().sum()) == 0.0
    torch.testing.assert_close(ours["regression.weight"].flatten(), torch.arange(192, dtype=torch.float32))
    torch.testing.assert_close(ours["backbone.firstconv.2.0.weight"], state["feature_extraction.firstconv.4.0.weight"])
    torch.testing.assert_close(
        ours["backbone.layer2.5.conv1.1.running_var"], state["feature_extraction.layer2.5.conv1.0.1.running_var"]
    )
    torch.testing.assert_close(ours["aggregation.dres4.conv3.0.weight"], state["dres4.conv3.0.0.weight"])
    torch.testing.assert_close(ours["aggregation.classif2.1.weight"], state["classif2.2.weight"])
    torch.testing.assert_close(ours["backbone.lastconv.1.weight"], state["feature_extraction.lastconv.2.weight"])


@pytest.mark.parametrize("layout", ["ours", "authors"])
def test_our_checkpoints_round_trip_in_both_layouts(tmp_path, layout):
    torch.manual_seed(5)
    model = EMCStereo(ema=True, msf=False, coord=True, max_disp=96)
    path = save_checkpoint(model, tmp_path / f"{layout}.pth", layout=layout, extra={"epoch": 3})
    loaded = load_model(path)
    assert loaded.config == model.config
    for key, value in model.state_dict().items():
        torch.testing.assert_close(loaded.state_dict()[key], value)
    raw = torch.load(path, weights_only=True)
    assert raw["epoch"] == 3
    if layout == "authors":
        assert next(iter(raw["model"])) == "Backbone.firstconv.0.0.weight"


def test_truncated_checkpoint_is_rejected_with_its_size(tmp_path, authors_checkpoint):
    path, _ = authors_checkpoint
    cut = tmp_path / "cut.pth"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 3])
    with pytest.raises(CheckpointError, match=r"cut\.pth.*bytes.*truncated"):
        load_model(cut)


def test_foreign_checkpoint_names_what_it_found(tmp_path):
    path = tmp_path / "resnet.pth"
    torch.save({"conv1.weight": torch.zeros(2), "fc.bias": torch.zeros(1)}, path)
    with pytest.raises(CheckpointError, match=r"unrecognised checkpoint \(2 tensors, e\.g\. conv1\.weight"):
        load_model(path)


def test_non_dict_checkpoint_is_rejected(tmp_path):
    path = tmp_path / "list.pth"
    torch.save([torch.zeros(1)], path)
    with pytest.raises(CheckpointError, match="expected a dict of tensors, found list"):
        load_model(path)


def test_missing_and_misshapen_tensors_are_listed(tmp_path, authors_checkpoint):
    _, state = authors_checkpoint
    state = dict(state)
    del state["Backbone.coord_att.conv_h.bias"]
    state["Backbone.ema.conv1x1.weight"] = torch.zeros(8, 8, 3, 3)
    path = tmp_path / "broken.pth"
    torch.save({"model": state}, path)
    with pytest.raises(CheckpointError) as err:
        load_model(path)
    message = str(err.value)
    assert "1 missing" in message and "coord_att.conv_h.bias" in message
    assert "1 wrong shape" in message and "(8, 8, 3, 3)" in message


def test_missing_file_is_reported(tmp_path):
    with pytest.raises(CheckpointError, match="no such checkpoint file"):
        read_checkpoint(tmp_path / "absent.pth")


def test_pickle_that_needs_code_is_refused_in_one_line(tmp_path):
    path = tmp_path / "code.pth"
    torch.save({"model": {}, "hook": pathlib_purepath()}, path)
    with pytest.raises(CheckpointError) as err:
        load_model(path)
    assert "not a weights-only torch checkpoint" in str(err.value) and "\n" not in str(err.value)
    assert "Unsupported global" in str(err.value)


def pathlib_purepath():
    """An object whose unpickling needs a class import: what weights-only loading refuses."""
    from pathlib import PurePosixPath

    return PurePosixPath("/x")


def test_a_file_that_is_not_a_torch_checkpoint_is_rejected_with_its_size(tmp_path):
    path = tmp_path / "notes.pth"
    path.write_text("junk\n")
    with pytest.raises(CheckpointError, match=r"notes\.pth: not a readable torch checkpoint \(5 bytes"):
        load_model(path)
