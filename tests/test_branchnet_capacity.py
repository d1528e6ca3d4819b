"""BranchNet's extra capacity (`deep_blocks`): inverted residual blocks at the encoder's coarse scales only, the
shipped network unchanged without them, and a network with them exported, read back and fine-tuned like any."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from branchrange.core.segmentation.learned import SHIPPED_MODEL
from branchrange.core.segmentation.network_input import STRIDE
from branchrange.core.segmentation.onnx_model import OnnxSegmenterError
from branchrange.learning.branchnet import BranchNet, InvertedResidual

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import branchnet_capacity  # noqa: E402


def test_without_deep_blocks_the_network_is_the_shipped_one_layer_for_layer():
    from branchrange.learning.from_onnx import branchnet_from_onnx

    meta = json.loads(SHIPPED_MODEL.with_suffix(".json").read_text())
    shipped = branchnet_from_onnx(SHIPPED_MODEL, meta["width"], meta["fine_width"])  # checks its logits too
    plain = BranchNet(meta["width"], meta["fine_width"], deep_blocks=0)
    assert {k: v.shape for k, v in plain.state_dict().items()} == {k: v.shape for k, v in shipped.state_dict().items()}
    assert not any(isinstance(m, InvertedResidual) for m in plain.modules())


def test_deep_blocks_add_capacity_at_the_coarse_scales_only():
    plain, deep = BranchNet(12, 8), BranchNet(12, 8, deep_blocks=2)
    added = {k: v for k, v in deep.state_dict().items() if k not in plain.state_dict()}
    assert added and all(k.startswith(("down2.", "down3.", "down4.")) for k in added)  # 1/4, 1/8, 1/16
    assert sum(isinstance(m, InvertedResidual) for m in deep.modules()) == 6  # two at each of three scales
    assert {k: v.shape for k, v in plain.state_dict().items()} == {
        k: v.shape for k, v in deep.state_dict().items() if k in plain.state_dict()
    }  # the shipped layers keep their names: an earlier stage's weights start a deep one (`init_weights`)
    parameters = sum(p.numel() for p in deep.parameters())
    assert sum(p.numel() for p in plain.parameters()) < parameters < 1_000_000  # still under 4 MB of float32
    x = torch.randn(1, 5, 2 * STRIDE, 3 * STRIDE)
    assert deep.eval()(x).shape == (1, 3, 2 * STRIDE, 3 * STRIDE)


def test_an_inverted_residual_block_adds_to_its_input_and_starts_as_the_identity():
    block = InvertedResidual(8, dilation=2).eval()
    x = torch.randn(1, 8, 16, 16)
    assert torch.equal(block(x), x)  # a fresh block's projection scales by zero
    with torch.no_grad():
        block.project[1].weight.fill_(1.0)
    assert not torch.allclose(block(x), x)  # trained, it adds its branch to the input


def test_blocks_added_to_a_trained_network_leave_its_logits_as_they_were():
    from branchrange.learning.training import load_matching_weights

    plain = branchnet_capacity.random_network(4, 4, 0)
    deep = BranchNet(4, 4, deep_blocks=2)
    fresh = load_matching_weights(deep, plain.state_dict())
    assert fresh and all(".expand." in n or ".depthwise." in n or ".project." in n for n in fresh)
    x = torch.randn(1, 5, 2 * STRIDE, 3 * STRIDE)
    with torch.inference_mode():
        assert torch.allclose(deep.eval()(x), plain(x), atol=1e-6)


@pytest.mark.parametrize("deep_blocks", [1, 2])
def test_a_deep_network_exported_to_onnx_reads_back_with_the_same_logits(tmp_path, deep_blocks):
    pytest.importorskip("onnx")
    from branchrange.learning.from_onnx import branchnet_from_onnx
    from branchrange.learning.training import export_onnx

    model = branchnet_capacity.random_network(4, 4, deep_blocks)  # random batch-norm statistics to fold
    export_onnx(model, tmp_path / "deep.onnx")
    read = branchnet_from_onnx(tmp_path / "deep.onnx", 4, 4, deep_blocks)  # raises unless its logits match
    x = torch.from_numpy(np.random.default_rng(1).normal(size=(1, 5, 32, 48)).astype(np.float32))
    with torch.inference_mode():
        assert torch.allclose(read(x), model(x), atol=1e-4)
    with pytest.raises(OnnxSegmenterError, match="convolutions"):  # read as the shipped encoder: a count that differs
        branchnet_from_onnx(tmp_path / "deep.onnx", 4, 4, 0)


def test_training_with_deep_blocks_records_them_and_refuses_too_many(tmp_path):
    from branchrange.commands.train_segmenter import training_config
    from branchrange.learning.training import train_branchnet

    settings = ["train_seeds=[1, 3]", "val_seeds=[3, 4]", "steps=1", "batch=2", "crop=64", "width=4", "threads=1"]
    meta = train_branchnet(training_config(None, [*settings, "deep_blocks=1"]), tmp_path / "run", tmp_path / "data")
    assert meta["deep_blocks"] == 1 and meta["config"]["deep_blocks"] == 1
    weights = torch.load(tmp_path / "run" / "branchnet.pt")
    assert any(".expand.0.weight" in name for name in weights)
    with pytest.raises(ValueError, match="deep_blocks must lie in"):
        training_config(None, [*settings, "deep_blocks=5"])


def test_the_capacity_benchmark_times_each_variant_against_the_shipped_model(tmp_path, capsys):
    pytest.importorskip("onnx")
    out = tmp_path / "capacity.json"
    argv = ["--deep-blocks", "0", "1", "--repeats", "1", "--threads", "1", "--data", str(tmp_path / "data")]
    assert branchnet_capacity.main([*argv, "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    models = report["models"]
    assert list(models) == ["shipped", "deep_blocks=0", "deep_blocks=1"]
    assert models["shipped"]["int8_ratio_to_shipped"] == 1.0
    assert models["deep_blocks=0"]["parameters"] < models["deep_blocks=1"]["parameters"]
    assert all(row["int8"]["median_ms"] > 0 and row["fp32"]["median_ms"] > 0 for row in models.values())
    assert "deep_blocks=1" in capsys.readouterr().out
    assert branchnet_capacity.main(["--deep-blocks", "5"]) == 2
