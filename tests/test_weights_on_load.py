"""Registered weights are checked against their SHA-256 on every load, hashed once per file version;
local files of other names load unchecked, and `verify_sha256=False` / `--no-verify-weights` overrides."""

from __future__ import annotations

import dataclasses
import hashlib
import os
from pathlib import Path

import pytest
import torch

import stereo.weights
from stereo import EMCStereo, load_model
from stereo.backends import make_backend
from stereo.checkpoints import WeightsMismatchError, save_checkpoint
from stereo.cli import main
from stereo.weights import REGISTRY, WeightsInfo

RELEASE = REGISTRY["emcstereo-virtualtree"]


def small_model(seed: int) -> EMCStereo:
    torch.manual_seed(seed)
    return EMCStereo(ema=False, msf=False, coord=False, max_disp=16)


@pytest.fixture()
def registered(tmp_path: Path) -> tuple[Path, dict[str, WeightsInfo]]:
    """A small checkpoint on disk and a test registry that lists it by file name and SHA-256."""
    path = save_checkpoint(small_model(0), tmp_path / "tiny.pth")
    info = WeightsInfo(
        name="tiny",
        filename="tiny.pth",
        sha256=hashlib.sha256(path.read_bytes()).hexdigest(),
        layout="ours",
        url="http://127.0.0.1:9/never-fetched",
    )
    return path, {info.name: info}


def test_registered_file_with_its_checksum_loads(registered):
    path, registry = registered
    model = load_model(path, registry=registry)
    expected = small_model(0).state_dict()
    assert all(torch.equal(model.state_dict()[k], expected[k]) for k in expected)


def test_registered_name_with_other_contents_is_refused_naming_file_and_both_hashes(registered):
    path, registry = registered
    save_checkpoint(small_model(1), path)  # same name, other weights: a readable checkpoint, not the release
    actual = hashlib.sha256(path.read_bytes()).hexdigest()
    with pytest.raises(WeightsMismatchError) as err:
        load_model(path, registry=registry)
    message = str(err.value)
    assert str(path) in message and actual in message and registry["tiny"].sha256 in message
    assert "--no-verify-weights" in message


def test_override_loads_a_local_file_that_carries_a_registered_name(registered):
    path, registry = registered
    save_checkpoint(small_model(1), path)
    model = load_model(path, registry=registry, verify_sha256=False)
    assert torch.equal(
        model.state_dict()["aggregation.classif3.1.weight"],
        small_model(1).state_dict()["aggregation.classif3.1.weight"],
    )


def test_file_of_an_unregistered_name_loads_unchecked(registered, tmp_path, monkeypatch):
    _, registry = registered
    local = save_checkpoint(small_model(2), tmp_path / "my_finetune.pth")
    hashed: list[Path] = []
    monkeypatch.setattr(stereo.weights, "sha256_of", lambda p: hashed.append(p) or "0" * 64)
    load_model(local, registry=registry)
    assert hashed == []


def test_each_file_version_is_hashed_once(registered, monkeypatch):
    path, registry = registered
    real = stereo.weights.sha256_of
    hashed: list[Path] = []
    monkeypatch.setattr(stereo.weights, "sha256_of", lambda p: hashed.append(p) or real(p))
    load_model(path, registry=registry)
    load_model(path, registry=registry)
    assert len(hashed) == 1
    # One byte changed in place, same size: the new mtime makes it a new version, hashed and refused.
    data = bytearray(path.read_bytes())
    data[-100] ^= 0xFF
    path.write_bytes(bytes(data))
    stat = path.stat()
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000_000))
    with pytest.raises(WeightsMismatchError):
        load_model(path, registry=registry)
    assert len(hashed) == 2


def test_backend_checks_registered_weights_unless_told_not_to(tmp_path):
    path = save_checkpoint(small_model(0), tmp_path / RELEASE.filename)  # the release's name, not its bytes
    with pytest.raises(WeightsMismatchError, match=RELEASE.sha256):
        make_backend("emcstereo", weights=path, max_disp=16)
    backend = make_backend("emcstereo", weights=path, max_disp=16, verify_sha256=False)
    expected = small_model(0).state_dict()["aggregation.classif3.1.weight"]
    assert torch.equal(backend.model.state_dict()["aggregation.classif3.1.weight"], expected)


def test_cli_refuses_a_mismatching_release_and_loads_it_with_no_verify_weights(tmp_path, capsys):
    path = save_checkpoint(small_model(0), tmp_path / RELEASE.filename)
    out = tmp_path / "tiny.onnx"
    args = ["export", "--onnx", str(out), "--weights", str(path), "--height", "256", "--width", "256"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert f"SHA-256 {hashlib.sha256(path.read_bytes()).hexdigest()} does not match {RELEASE.sha256}" in err
    assert not out.exists()
    assert main([*args, "--no-verify-weights"]) == 0
    assert out.is_file()


def test_stereo_config_passes_verify_weights_to_the_backend(tmp_path):
    from branchrange.core.pipeline import StereoConfig

    path = save_checkpoint(small_model(0), tmp_path / RELEASE.filename)
    config = StereoConfig(backend="emcstereo", weights=str(path), max_disp=16, mode="full")
    with pytest.raises(WeightsMismatchError, match=RELEASE.sha256):
        config.build_backend()
    loaded = dataclasses.replace(config, verify_weights=False).build_backend()
    assert loaded.max_disparity == 16
