"""`emcstereo export --onnx` and the `onnx` backend against the emcstereo backend on a real pair."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from stereo import EMCStereo, save_checkpoint
from stereo.backends import BackendConfigError, StereoInputError, make_backend
from stereo.backends.emcstereo import EMCStereoBackend
from stereo.cli import main as emcstereo_main
from stereo.export import ExportError, export_onnx
from stereo.io.images import read_rgb

pytest.importorskip("onnxruntime", reason="onnxruntime (a dependency of branchrange) is not installed")

#: Small export: 256×256 padded input, 32 px range (8 cost-volume slices), so export takes seconds.
SIZE, RANGE = 256, 32


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> tuple[EMCStereo, str]:
    """A seeded model, its checkpoint, and the ONNX file the command wrote from that checkpoint."""
    folder = tmp_path_factory.mktemp("onnx")
    torch.manual_seed(0)
    model = EMCStereo().eval()
    checkpoint = save_checkpoint(model, folder / "model.pt")
    onnx_path = folder / "model.onnx"
    status = emcstereo_main(
        [
            "export",
            "--onnx",
            str(onnx_path),
            "--weights",
            str(checkpoint),
            "--height",
            str(SIZE),
            "--width",
            str(SIZE),
            "--max-disp",
            str(RANGE),
        ]
    )
    assert status == 0 and onnx_path.is_file()
    return model, str(onnx_path)


def test_onnx_backend_equals_emcstereo_backend_on_a_real_pair(exported, shared_data):
    model, onnx_path = exported
    folder = shared_data / "stereo" / "middlebury2001_tsukuba"
    left, right = (np.ascontiguousarray(read_rgb(folder / name)[:240, :250]) for name in ("imL.png", "imR.png"))
    backend = make_backend("onnx", weights=onnx_path, max_disp=RANGE)
    assert (backend.name, backend.max_disparity, backend.height, backend.width) == ("onnx", RANGE, SIZE, SIZE)
    got = backend.compute(left, right)
    expected = EMCStereoBackend(model, max_disp=RANGE).compute(left, right)
    assert got.disparity.shape == (240, 250)
    # Both pad to 256×256 at the top and right, so the network sees the same input.
    assert float(np.abs(got.disparity - expected.disparity).max()) <= 0.01
    assert float(np.abs(got.confidence - expected.confidence).mean()) <= 1e-4
    assert set(got.timing_ms) >= {"network", "total"}


def test_onnx_backend_refuses_a_pair_larger_than_its_graph(exported):
    _, onnx_path = exported
    big = np.zeros((SIZE + 1, SIZE, 3), np.uint8)
    with pytest.raises(StereoInputError, match="exported for"):
        make_backend("onnx", weights=onnx_path, max_disp=RANGE).compute(big, big)


def test_onnx_backend_refuses_a_range_other_than_the_exported_one(exported):
    _, onnx_path = exported
    with pytest.raises(BackendConfigError, match="exported for max_disp 32"):
        make_backend("onnx", weights=onnx_path, max_disp=192)


def test_export_refuses_a_size_the_network_cannot_take(tmp_path):
    with pytest.raises(ExportError, match="250×256"):
        export_onnx(EMCStereo(ema=False, msf=False, coord=False), tmp_path / "x.onnx", 250, 256)


def test_export_command_reports_a_bad_checkpoint_without_a_traceback(tmp_path, capsys):
    bad = tmp_path / "bad.pt"
    bad.write_text("junk\n")
    status = emcstereo_main(["export", "--onnx", str(tmp_path / "x.onnx"), "--weights", str(bad)])
    assert status == 2
    err = capsys.readouterr().err
    assert err.startswith("emcstereo export: error: ") and "bad.pt: not a readable torch checkpoint" in err
    assert not (tmp_path / "x.onnx").exists()
