"""The learned segmenter: the shipped BranchNet on held-out synthetic scenes, its checksum, training and export."""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from torch.nn import functional as F

from branchrange.commands.train_segmenter import training_config
from branchrange.core.confidence import (
    ConfidenceCalibration,
    expected_calibration_error,
    fit_calibration,
    highest_inclusive_threshold,
    lowest_reliable_threshold,
)
from branchrange.core.cutpoints import estimate_cut_points
from branchrange.core.geometry import StereoGeometry
from branchrange.core.light_check import LIGHTS
from branchrange.core.masks import BranchMasks
from branchrange.core.pipeline import Pipeline, untracked_whole_frame
from branchrange.core.segmentation.choose import make_segmenter
from branchrange.core.segmentation.learned import (
    MAX_NETWORK_WIDTH,
    SHIPPED_MODEL,
    LearnedSegmenter,
    LearnedSegmenterConfig,
    band_seen_width,
    resampled_logits,
    trunk_and_branch_probabilities,
)
from branchrange.core.segmentation.network_input import CLASSES, network_input
from branchrange.core.segmentation.onnx_model import OnnxSegmenterError
from branchrange.learning.branchnet import BranchNet
from branchrange.learning.samples import BRANCH, IGNORE, TRUNK, classes_from_instances

#: torch's TorchScript exporter builds the ONNX file in the training test; its deprecation notice is not ours
pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
HELD_OUT_SEED = 50_007  # benchmark seeds start at 50,000; training never uses them


@pytest.fixture(scope="module")
def scene():
    from stereo.backends import make_backend
    from stereo.synth import SynthCamera, render_scene

    rendered = render_scene(HELD_OUT_SEED, SynthCamera.zed_mini(640, 360))
    stereo = make_backend("sgbm", max_disp=128).compute(rendered.left, rendered.right)
    return rendered, stereo


def test_classes_from_instances_maps_renderer_ids():
    instances = np.array([[0, 1, 7, 65533, 65534, 65535]], dtype=np.uint16)
    assert classes_from_instances(instances).tolist() == [[0, BRANCH, BRANCH, 0, IGNORE, TRUNK]]


def test_evaluation_scenes_of_another_size_are_cached_apart_and_matched_over_a_range_as_wide(tmp_path):
    from branchrange.learning.samples import evaluation_max_disp, evaluation_scene, scene_in_light

    assert (evaluation_max_disp(640), evaluation_max_disp(1280)) == (192, 384)  # the same depths at twice the width
    small = evaluation_scene(7, tmp_path, size=(320, 180))
    usual = evaluation_scene(7, tmp_path)
    assert small["left"].shape == (180, 320, 3) and usual["left"].shape == (360, 640, 3)
    scene_in_light(small, 7, "dusk", tmp_path)
    scene_in_light(usual, 7, "dusk", tmp_path)
    names = sorted(p.name for p in tmp_path.glob("*.npz"))
    assert names == ["light_dusk_320x180_7.npz", "light_dusk_7.npz", "scene_320x180_7.npz", "scene_7.npz"]
    again = scene_in_light(evaluation_scene(7, tmp_path, size=(320, 180)), 7, "dusk", tmp_path)  # from the cache
    assert again["left"].shape == (180, 320, 3)


def test_network_input_is_scale_free_in_disparity():
    left = np.full((32, 48, 3), 128, np.uint8)
    disparity = np.linspace(1, 40, 32 * 48, dtype=np.float32).reshape(32, 48)
    disparity[0, :5] = 0
    a, b = network_input(left, disparity), network_input(left, 3.0 * disparity)
    assert a.shape == (5, 32, 48)
    np.testing.assert_allclose(a, b, atol=1e-5)  # another focal length or baseline: the same input
    assert a[4, 0, :5].tolist() == [0] * 5 and a[3, 0, :5].tolist() == [0] * 5


def test_shipped_model_finds_trunk_and_branches_of_a_held_out_scene(scene):
    rendered, stereo = scene
    geometry = StereoGeometry(
        rendered.camera.focal_px, rendered.camera.baseline_m, rendered.camera.cx, rendered.camera.cy
    )
    masks = LearnedSegmenter().segment(rendered.left, stereo.disparity, geometry, stereo.confidence)
    truth = classes_from_instances(rendered.instance_mask)
    trunk = masks.trunk()
    assert trunk is not None
    true_trunk = truth == TRUNK
    assert (trunk & true_trunk).sum() / (trunk | true_trunk).sum() > 0.5
    found_branch = np.isin(masks.labels, masks.branch_ids())
    # most of what it calls branch lies on a branch or twig (within 1 px: stems are 1–4 px wide, and
    # sgbm's disparity is fattened), and it covers a fair share of the branches
    woody = cv2.dilate(np.isin(truth, (BRANCH, IGNORE)).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    assert (found_branch & woody).sum() / found_branch.sum() > 0.7
    assert (found_branch & (truth == BRANCH)).sum() / (truth == BRANCH).sum() > 0.3
    # a score is the piece's mean branch probability (≥ the 0.5 threshold) times its trunk attachment (≤ 1)
    assert set(masks.scores) == set(masks.branch_ids()) and all(0 < s <= 1 for s in masks.scores.values())
    assert max(masks.scores.values()) >= 0.5


def test_pipeline_with_learned_segmenter_gives_a_cut_point_near_the_truth(scene):
    rendered, stereo = scene
    cam = rendered.camera
    pipeline = Pipeline(
        untracked_whole_frame(),
        focal_px=cam.focal_px,
        baseline_m=cam.baseline_m,
        principal_point=(cam.cx, cam.cy),
        segmenter=make_segmenter("learned"),
    )
    result = pipeline.process_disparity(rendered.left, stereo.disparity, stereo.confidence, backend="sgbm")
    truth = [np.asarray(b.cut_point_m) for b in rendered.branches if b.cut_visible]
    errors = [min(np.linalg.norm(np.asarray(b.cut_point_m) - t) for t in truth) for b in result.branches]
    assert errors and min(errors) < 0.05


def test_segment_score_scales_the_cut_point_confidence(scene):
    rendered, stereo = scene
    cam = rendered.camera
    geometry = StereoGeometry(cam.focal_px, cam.baseline_m, cam.cx, cam.cy)
    labels = rendered.instance_mask.astype(np.int32)
    plain = estimate_cut_points(BranchMasks(labels, 65535), rendered.disparity, geometry)
    ids = [b.mask_id for b in plain.branches]
    scored = estimate_cut_points(BranchMasks(labels, 65535, scores={i: 0.5 for i in ids}), rendered.disparity, geometry)
    assert ids
    for a, b in zip(plain.branches, scored.branches):
        assert b.confidence == pytest.approx(0.5 * a.confidence)
        np.testing.assert_array_equal(a.cut_point_m, b.cut_point_m)


def test_a_damaged_model_file_is_refused_naming_both_hashes(tmp_path):
    copy = tmp_path / "branchnet.onnx"
    shutil.copy(SHIPPED_MODEL, copy)
    shutil.copy(SHIPPED_MODEL.with_suffix(".json"), tmp_path / "branchnet.json")
    LearnedSegmenter(LearnedSegmenterConfig(model=str(copy)))  # intact: loads
    data = bytearray(copy.read_bytes())
    data[-10] ^= 0xFF
    copy.write_bytes(bytes(data))
    recorded = json.loads((tmp_path / "branchnet.json").read_text())["onnx_sha256"]
    with pytest.raises(OnnxSegmenterError, match=recorded):
        LearnedSegmenter(LearnedSegmenterConfig(model=str(copy)))
    with pytest.raises(OnnxSegmenterError, match="no model file"):
        LearnedSegmenter(LearnedSegmenterConfig(model=str(tmp_path / "absent.onnx")))
    rgb_only = tmp_path / "rgb_only.onnx"  # a per-pixel model of another kind: 3 input channels
    torch.onnx.export(torch.nn.Conv2d(3, 3, 1), torch.zeros(1, 3, 32, 32), str(rgb_only), dynamo=False)
    with pytest.raises(OnnxSegmenterError, match="is not a BranchNet"):
        LearnedSegmenter(LearnedSegmenterConfig(model=str(rgb_only)))


def test_shipped_metadata_records_a_reproducible_training_run():
    meta = json.loads(SHIPPED_MODEL.with_suffix(".json").read_text())
    config = training_config(SHIPPED_MODEL.with_suffix(".json"), [])
    assert config.seed == meta["config"]["seed"] and config.train_seeds[1] <= config.val_seeds[0]
    assert SHIPPED_MODEL.stat().st_size < 5 * 2**20
    assert meta["final"]["iou_branch"] > 0.3 and meta["final"]["iou_trunk"] > 0.6
    assert sum(p.numel() for p in BranchNet(meta["width"], meta.get("fine_width", 0)).parameters()) < 1_000_000
    # the recipe's stages chain: each starts from the weights the one before writes, the last is 'config'
    stages = [training_config(SHIPPED_MODEL.with_suffix(".json"), [], k) for k in range(1, len(meta["stages"]) + 1)]
    assert stages[0].init_weights == "" and stages[-1] == config
    for before, after in zip(stages, stages[1:]):
        assert after.init_weights.startswith("runs/") and after.init_weights.endswith("/branchnet.pt")
        assert after.width == before.width and after.train_seeds == before.train_seeds
    assert sum(stage.steps for stage in stages) <= 30_000  # ≈ 0.2 s a step on 2 cores: within the 2 hours


def test_training_config_errors_name_the_key(tmp_path):
    with pytest.raises(ValueError, match="KEY one of"):
        training_config(None, ["stepz=3"])
    with pytest.raises(ValueError, match="overlap"):
        training_config(None, ["train_seeds=[1, 100]", "val_seeds=[50, 60]"])
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(ValueError, match="'config'"):
        training_config(tmp_path / "bad.json", [])
    staged = tmp_path / "staged.json"
    staged.write_text(json.dumps({"config": {"steps": 3}, "stages": [{"steps": 1}, {"steps": 2, "lr": 0.001}]}))
    assert training_config(staged, []).steps == 3
    assert training_config(staged, [], stage=2).steps == 2 and training_config(staged, [], stage=2).lr == 0.001
    with pytest.raises(ValueError, match="has 2 stages"):
        training_config(staged, [], stage=3)
    with pytest.raises(ValueError, match="--stage needs --config"):
        training_config(None, [], stage=1)


def test_training_runs_and_its_export_loads_as_a_segmenter(tmp_path):
    from branchrange.learning.training import train_branchnet

    config = training_config(
        None,
        [
            "train_seeds=[1, 3]",
            "val_seeds=[3, 4]",
            "steps=2",
            "batch=2",
            "crop=64",
            "val_every=1",
            "width=4",
            "threads=1",
        ],
    )
    lines: list[str] = []
    meta = train_branchnet(config, tmp_path / "run", tmp_path / "data", log=lines.append)
    assert lines[0] == f"rendered 3 generator scenes into {tmp_path / 'data'} (1 process)"
    assert len(lines) == 3 and "iou_branch" in lines[1]  # then one line per validation
    assert sorted(p.name for p in (tmp_path / "data").iterdir()) == [f"sample_{s:06d}.npz" for s in (1, 2, 3)]
    for name in ("branchnet.onnx", "branchnet.json", "metrics.csv", "training_curve.png", "branchnet.pt"):
        assert (tmp_path / "run" / name).is_file()
    segmenter = LearnedSegmenter(LearnedSegmenterConfig(model=str(tmp_path / "run" / "branchnet.onnx")))
    left = np.zeros((50, 70, 3), np.uint8)
    masks = segmenter.segment(left, np.full((50, 70), 5.0, np.float32), StereoGeometry.centred(100.0, 0.1, 70, 50))
    assert masks.labels.shape == (50, 70)
    assert meta["config"]["steps"] == 2
    # the same config on the same cached scenes trains the same weights (what the shipped JSON promises)
    again = train_branchnet(config, tmp_path / "again", tmp_path / "data", log=lines.append)
    assert again["onnx_sha256"] == meta["onnx_sha256"]
    assert len(lines) == 5  # the scenes were cached: nothing rendered again
    first, second = (torch.load(tmp_path / d / "branchnet.pt") for d in ("run", "again"))
    assert all(torch.equal(first[k], second[k]) for k in first)


def test_training_scenes_rendered_in_two_processes_are_the_ones_one_process_renders(tmp_path):
    from branchrange.learning.samples import render_samples, sample_path

    seeds = [(11, False), (12, False), (13, True)]
    assert render_samples(tmp_path / "two", seeds, workers=2) == 3
    assert render_samples(tmp_path / "one", seeds[:2], workers=1) == 2
    assert render_samples(tmp_path / "one", seeds, workers=1) == 1  # only the one not cached yet
    assert render_samples(tmp_path / "two", seeds, workers=2) == 0
    for seed, hardware in seeds:
        with np.load(sample_path(tmp_path / "one", seed, hardware)) as one:
            with np.load(sample_path(tmp_path / "two", seed, hardware)) as two:
                assert sorted(one.files) == sorted(two.files) == ["classes", "disparity", "instances", "left"]
                assert all(np.array_equal(one[key], two[key]) for key in one.files)
    assert sorted(p.name for p in (tmp_path / "two").iterdir()) == [
        "sample_000011.npz",
        "sample_000012.npz",
        "sample_hw_000013.npz",
    ]  # no partial files left behind


def test_a_stage_trained_with_no_calibrate_writes_its_model_without_calibrating(tmp_path, monkeypatch, capsys):
    """`train-segmenter --no-calibrate`: an intermediate stage, whose model only starts the next, skips the
    confidence calibration (~5 min of the reproduction's 2 hours); it and --calibrate-only exclude each other."""
    from branchrange.cli import main
    from branchrange.learning import calibration as branchnet_calibration

    def refuse(*args, **kwargs):
        raise AssertionError("calibrate_model must not run with --no-calibrate")

    monkeypatch.setattr(branchnet_calibration, "calibrate_model", refuse)
    settings = ["train_seeds=[1, 3]", "val_seeds=[3, 4]", "steps=1", "batch=2", "crop=64", "width=4", "threads=1"]
    argv = ["train-segmenter", "--out", str(tmp_path / "run"), "--data", str(tmp_path / "data"), "--no-calibrate"]
    assert main([*argv, *(a for s in settings for a in ("--set", s))]) == 0
    meta = json.loads((tmp_path / "run" / "branchnet.json").read_text())
    assert "confidence_calibrations" not in meta and "wrote" in capsys.readouterr().out
    assert main([*argv, "--calibrate-only"]) == 2
    assert "exclude each other" in capsys.readouterr().err


def test_train_segmenter_calibrates_in_the_workers_it_is_given_and_refuses_none(tmp_path, monkeypatch, capsys):
    from branchrange.cli import main
    from branchrange.learning import calibration as branchnet_calibration

    calls: list[tuple[Path, int]] = []
    monkeypatch.setattr(
        branchnet_calibration, "calibrate_model", lambda model, **kwargs: calls.append((model, kwargs["workers"]))
    )
    (tmp_path / "branchnet.onnx").write_bytes(b"a model")
    argv = ["train-segmenter", "--out", str(tmp_path), "--calibrate-only"]
    assert main([*argv, "--workers", "3"]) == 0 and calls == [(tmp_path / "branchnet.onnx", 3)]
    assert main([*argv, "--workers", "0"]) == 2 and len(calls) == 1
    assert "--workers 0: at least 1" in capsys.readouterr().err
    # the default: one process per core this process may run on (a container's cpuset), else per core
    from branchrange.commands import train_segmenter

    assert train_segmenter.usable_cores() == len(os.sched_getaffinity(0))
    monkeypatch.delattr(os, "sched_getaffinity")
    monkeypatch.setattr(os, "cpu_count", lambda: 6)
    assert train_segmenter.usable_cores() == 6


def test_calibrating_a_damaged_model_in_two_processes_is_an_error_message_not_a_traceback(tmp_path, capsys):
    from branchrange.cli import main

    (tmp_path / "branchnet.onnx").write_bytes(b"not an onnx file")
    argv = ["train-segmenter", "--out", str(tmp_path), "--data", str(tmp_path / "data"), "--calibrate-only"]
    assert main([*argv, "--workers", "2"]) == 2
    err = capsys.readouterr().err
    assert "train-segmenter: error: onnx:" in err and "not a model onnxruntime can load" in err
    assert "Traceback" not in err


def test_a_hardware_stage_also_trains_on_scenes_with_orchard_hardware(tmp_path):
    from branchrange.learning.training import train_branchnet

    settings = ["train_seeds=[1, 2]", "val_seeds=[2, 3]", "batch=3", "crop=64", "width=4", "threads=1", "steps=2"]
    train_branchnet(training_config(None, [*settings, "hardware_seeds=[5, 7]"]), tmp_path / "run", tmp_path / "data")
    drawn = {p.name for p in (tmp_path / "data").iterdir()}
    assert drawn & {"sample_hw_000005.npz", "sample_hw_000006.npz"} and "sample_000001.npz" in drawn
    hardware = np.load(tmp_path / "data" / sorted(drawn & {"sample_hw_000005.npz", "sample_hw_000006.npz"})[0])
    assert hardware["classes"].shape == (360, 640) and (hardware["classes"] == BRANCH).any()
    with pytest.raises(ValueError, match="hardware_seeds and val_seeds overlap"):
        training_config(None, ["hardware_seeds=[2, 5]", "val_seeds=[3, 4]", "train_seeds=[10, 20]"])
    with pytest.raises(ValueError, match="hardware_seeds must be"):
        training_config(None, ["hardware_seeds=[5, 5]"])
    with pytest.raises(ValueError, match="hardware_seeds overlap the calibration scenes 2861–3100"):
        training_config(None, ["hardware_seeds=[3001, 3601]"])  # the calibration scenes' second half
    with pytest.raises(ValueError, match="train_seeds overlap the calibration scenes"):
        training_config(None, ["train_seeds=[2840, 2900]"])


def test_isotonic_calibration_is_monotone_and_honest():
    rng = np.random.default_rng(0)
    raw = rng.uniform(0, 1, 2000)
    correct = rng.uniform(0, 1, 2000) < raw**2  # a raw confidence that overstates the share correct
    calibration = fit_calibration(raw, correct)
    assert list(calibration.raw) == sorted(calibration.raw) and list(calibration.calibrated) == sorted(
        calibration.calibrated
    )
    for value in (0.3, 0.6, 0.9):
        assert calibration(value) == pytest.approx(value**2, abs=0.08)
    assert ConfidenceCalibration.from_json_dict(calibration.to_json_dict())(0.5) == pytest.approx(
        calibration(0.5), abs=1e-3
    )
    # the calibration error: large for the raw confidence, small once calibrated, 0 for a perfect one
    outcomes = list(zip(raw, correct))
    assert expected_calibration_error(outcomes) > 0.1
    assert expected_calibration_error([(calibration(c), ok) for c, ok in outcomes]) < 0.03
    assert expected_calibration_error([(0.25, True), (0.25, False), (0.25, False), (0.25, False)]) == 0.0
    assert expected_calibration_error([(1.0, False)]) == 1.0 and math.isnan(expected_calibration_error([]))
    few = fit_calibration([0.9] * 5, [True] * 5)  # five right answers are not a certainty
    assert few(0.9) == pytest.approx(6 / 7)
    with pytest.raises(ValueError, match="ascending"):
        ConfidenceCalibration((0.2, 0.1), (0.1, 0.2))


def test_default_thresholds_come_in_hundredths_from_the_outcomes():
    """A block of cut points at exactly 0.80 of which only 60 % are right sits just under the confident ones
    above it: the target threshold is the lowest hundredth above the block (0.81), not the next 0.05 step
    (0.85), which would also drop the 19 right ones at 0.82; the obstacle threshold is the highest that
    keeps ≥ 98 % of the right ones (the block's 30 included)."""
    outcomes = [(0.8, i < 30) for i in range(50)]
    outcomes += [(0.82, i < 19) for i in range(20)] + [(0.9, i < 95) for i in range(100)]
    outcomes += [(0.3, i < 2) for i in range(10)] + [(0.05, False)] * 10
    assert lowest_reliable_threshold(outcomes, 0.9) == 0.81  # ≥ 0.81: 114 of 120 right; ≥ 0.80: 144 of 170
    assert lowest_reliable_threshold([(0.5, False)] * 3) is None
    assert highest_inclusive_threshold(outcomes, 0.98) == 0.8  # keeps 144 of the 146 right; 0.81 only 114


def test_the_network_sees_the_frame_at_network_width_and_answers_at_the_frame_size(scene):
    rendered, stereo = scene
    seen: list[tuple[int, ...]] = []

    def recording(run):  # onnxruntime's run, noting the input's shape
        def run_and_note(names, feeds):
            seen.append(next(iter(feeds.values())).shape)
            return run(names, feeds)

        return run_and_note

    branch = classes_from_instances(rendered.instance_mask) == BRANCH
    for width in (0, 320, 1280):
        segmenter = LearnedSegmenter(LearnedSegmenterConfig(network_width=width, trunk_band_px=0))
        segmenter.session.run = recording(segmenter.session.run)  # type: ignore[method-assign]
        logits = segmenter.logits(rendered.left, stereo.disparity)
        assert logits.shape == (3, 360, 640) and np.isfinite(logits).all()
        assert np.mean(logits.argmax(0)[branch] == CLASSES.index("branch")) > 0.4, width
    assert [shape[2:] for shape in seen] == [(368, 640), (192, 320), (720, 1280)]  # padded to ×16
    with pytest.raises(OnnxSegmenterError, match="network_width"):
        LearnedSegmenterConfig(network_width=100)


def test_trunk_and_branch_probabilities_are_the_softmax_resampled_and_classes_still_sum_to_one():
    """What the instance step reads at full resolution: the same arg-max and branch share as the log-probabilities
    `resampled_logits` gives, at the frame's own size and enlarged or shrunk."""
    logits = np.random.default_rng(3).normal(0.0, 3.0, (3, 36, 64)).astype(np.float32)
    for size in ((64, 36), (128, 72), (32, 18)):
        trunk, branch = trunk_and_branch_probabilities(logits, size)
        assert trunk.shape == branch.shape == (size[1], size[0]) and trunk.dtype == np.float32
        assert (trunk >= 0).all() and (branch >= 0).all() and (trunk + branch <= 1 + 1e-5).all()
        expected = softmax(resampled_logits(logits, size))
        np.testing.assert_allclose(branch, expected[CLASSES.index("branch")], atol=1e-5)
        background = 1.0 - trunk - branch
        is_trunk = (trunk > background) & (trunk > branch)
        assert np.mean(is_trunk == (expected.argmax(0) == CLASSES.index("trunk"))) > 0.999


def softmax(logits: np.ndarray) -> np.ndarray:
    """Class probabilities `(C, H, W)` of logits `(C, H, W)`."""
    exp = np.exp(logits - logits.max(axis=0))
    return np.asarray(exp / exp.sum(axis=0))


def test_the_trunk_band_is_seen_again_twice_as_large_and_averaged_with_the_first_look_there(scene):
    """The columns around the trunk are looked at a second time at twice the size; outside them the first look
    stands. Inside, the class probabilities are the mean of the first look's and of the network's answer for
    that crop alone, and they find more of the thin stems."""
    rendered, stereo = scene
    seen: list[tuple[int, ...]] = []
    once = LearnedSegmenter(LearnedSegmenterConfig(trunk_band_px=0))
    twice = LearnedSegmenter(LearnedSegmenterConfig(trunk_band_px=40))
    run = twice.session.run

    def run_and_note(names, feeds):  # onnxruntime's run, noting the input's shape
        seen.append(next(iter(feeds.values())).shape)
        return run(names, feeds)

    twice.session.run = run_and_note  # type: ignore[method-assign]
    first = once.logits(rendered.left, stereo.disparity)
    both = twice.logits(rendered.left, stereo.disparity)
    band = twice.trunk_band(first)
    assert band is not None and once.trunk_band(first) is None
    start, stop = band
    trunk = (first.argmax(0) == CLASSES.index("trunk")).sum(axis=0) >= 5
    columns = np.flatnonzero(trunk)
    assert start % 16 == 0 and start <= max(0, columns[0] - 40) and stop >= min(640, columns[-1] + 41)
    assert [shape[2:] for shape in seen] == [(368, 640), (720, 2 * (stop - start))]
    assert np.array_equal(both[:, :, :start], first[:, :, :start]) and np.array_equal(
        both[:, :, stop:], first[:, :, stop:]
    )
    alone = LearnedSegmenter(LearnedSegmenterConfig(network_width=2 * (stop - start), trunk_band_px=0))
    crop = (slice(None), slice(start, stop))
    second = alone.logits(rendered.left[crop], stereo.disparity[crop])
    mean = 0.5 * (softmax(first[:, :, start:stop]) + softmax(second))
    assert np.allclose(np.exp(both[:, :, start:stop]), mean, atol=1e-4)
    branch = classes_from_instances(rendered.instance_mask) == BRANCH
    branch[:, :start], branch[:, stop:] = False, False
    found = [np.mean(logits.argmax(0)[branch] == CLASSES.index("branch")) for logits in (first, both)]
    assert found[1] > found[0]
    assert band_seen_width(stop - start, 1.0) == 2 * (stop - start)
    assert band_seen_width(160, 2.0) == 640  # after a first look at twice the frame's width, four times
    assert band_seen_width(2208, 1.0) == MAX_NETWORK_WIDTH  # a whole 2208 px frame: capped, not 4416 px
    no_trunk = first.copy()
    no_trunk[CLASSES.index("trunk")] = -50.0
    assert twice.trunk_band(no_trunk) is None
    with pytest.raises(OnnxSegmenterError, match="trunk_band_px"):
        LearnedSegmenterConfig(trunk_band_px=-1)


def test_calibration_in_the_model_json_maps_the_reported_confidence_at_its_network_width(scene, tmp_path):
    rendered, stereo = scene
    cam = rendered.camera
    geometry = StereoGeometry(cam.focal_px, cam.baseline_m, cam.cx, cam.cy)
    for name in ("branchnet.onnx", "branchnet.json"):
        shutil.copy(SHIPPED_MODEL.with_name(name), tmp_path / name)
    meta = json.loads((tmp_path / "branchnet.json").read_text())
    meta.pop("confidence_calibrations")
    halving = {"raw": [0.0, 1.0], "calibrated": [0.0, 0.5]}  # halves every confidence
    model = str(tmp_path / "branchnet.onnx")

    def confidences(table_key: str, table: object, **settings: object) -> list[float]:
        (tmp_path / "branchnet.json").write_text(json.dumps({**meta, table_key: table}))
        config = LearnedSegmenterConfig(model=model, **{"trunk_band_px": 0, **settings})  # type: ignore[arg-type]
        masks = LearnedSegmenter(config).segment(rendered.left, stereo.disparity, geometry)
        return [b.confidence for b in estimate_cut_points(masks, stereo.disparity, geometry).branches]

    raw = {
        width: confidences("confidence_calibrations", [], calibrated=False, network_width=width) for width in (0, 1280)
    }
    assert raw[0] and raw[0] != raw[1280]  # the frame's own width (640) and twice it: other scores
    identity = {"raw": [0.0, 1.0], "calibrated": [0.0, 1.0]}
    tables = [{**halving, "network_width": 640}, {**identity, "network_width": 1280}]
    assert confidences("confidence_calibrations", tables) == pytest.approx([0.5 * c for c in raw[0]], abs=1e-9)
    assert confidences("confidence_calibrations", tables, network_width=1280) == pytest.approx(raw[1280])
    nearest = LearnedSegmenter(LearnedSegmenterConfig(model=model))  # its JSON holds `tables` now
    assert nearest.calibration_at(1100).calibration(0.8) == pytest.approx(0.8)
    assert nearest.calibration_at(850).calibration(0.8) == 0.4
    # a JSON from before widths were recorded: its one table was measured on the 640-wide scenes as they are,
    # and it is the nearest there is at any width
    assert confidences("confidence_calibration", halving) == pytest.approx([0.5 * c for c in raw[0]])
    assert confidences("confidence_calibration", halving, network_width=1280) == pytest.approx(
        [0.5 * c for c in raw[1280]]
    )
    with pytest.raises(OnnxSegmenterError, match="network_width"):
        confidences("confidence_calibrations", [halving])
    # tables measured at one width with and without the trunk band: each setting takes its own
    banded = confidences("confidence_calibrations", [], calibrated=False, trunk_band_px=40)
    by_band = [{**halving, "network_width": 640, "trunk_band_px": 40}, {**identity, "network_width": 640}]
    assert confidences("confidence_calibrations", by_band, trunk_band_px=40) == pytest.approx([0.5 * c for c in banded])
    assert confidences("confidence_calibrations", by_band) == pytest.approx(raw[0])
    with pytest.raises(OnnxSegmenterError, match="trunk_band_px"):
        confidences("confidence_calibrations", [{**halving, "network_width": 640, "trunk_band_px": "40"}])


def test_calibrating_a_model_stores_a_fit_per_setting_and_light_and_the_segmenter_applies_it(tmp_path):
    from branchrange.learning.calibration import CALIBRATION_SETTINGS, calibrate_model

    for name in ("branchnet.onnx", "branchnet.json"):
        shutil.copy(SHIPPED_MODEL.with_name(name), tmp_path / name)
    lines: list[str] = []
    model = tmp_path / "branchnet.onnx"
    calibrations = calibrate_model(
        model, seeds=(2861, 2864), cache=tmp_path / "cal", log=lines.append, light_changes=("dusk",), min_cut_points=1
    )
    # each scene also at dusk, which measures as dark light: a table per setting and light (one of the scenes,
    # leaves to its edges, measures as noisy in its own light)
    assert set(calibrations) == {(*s, light) for s in CALIBRATION_SETTINGS for light in ("normal", "dark", "noisy")}
    assert set(CALIBRATION_SETTINGS) == {(640, 40), (640, 0), (1280, 0)}
    assert "network width 640, trunk band 40 px, normal light" in lines[0] and "scenes 2861–2863" in lines[0]
    assert sorted(p.name for p in (tmp_path / "cal").glob("light_*.npz")) == [
        f"light_dusk_{s}.npz" for s in range(2861, 2864)
    ]
    meta = json.loads((tmp_path / "branchnet.json").read_text())
    assert "confidence_calibration" not in meta  # the single table of before is replaced
    stored = {(t["network_width"], t["trunk_band_px"], t["light"]): t for t in meta["confidence_calibrations"]}
    for setting, calibration in calibrations.items():
        assert stored[setting]["seeds"] == [2861, 2864] and stored[setting]["cut_points"] > 0
        assert stored[setting]["light_changes"] == ["dusk"]
        assert ConfidenceCalibration.from_json_dict(stored[setting]) == ConfidenceCalibration.from_json_dict(
            calibration.to_json_dict()  # as written: rounded
        )
    # measured in two processes (scenes 2861 and 2862–2863): the same tables
    parallel = tmp_path / "parallel"
    parallel.mkdir()
    for name in ("branchnet.onnx", "branchnet.json"):
        shutil.copy(SHIPPED_MODEL.with_name(name), parallel / name)
    calibrate_model(
        parallel / "branchnet.onnx",
        seeds=(2861, 2864),
        cache=tmp_path / "cal",
        log=lambda line: None,
        light_changes=("dusk",),
        min_cut_points=1,
        workers=2,
    )
    assert (
        json.loads((parallel / "branchnet.json").read_text())["confidence_calibrations"]
        == (meta["confidence_calibrations"])
    )
    segmenter = LearnedSegmenter(LearnedSegmenterConfig(model=str(model)))
    assert {k: c.calibration for k, c in segmenter.calibrations.items()} == {
        k: ConfidenceCalibration.from_json_dict(t) for k, t in stored.items()
    }
    one_look = LearnedSegmenter(LearnedSegmenterConfig(model=str(model), trunk_band_px=0))
    assert segmenter.calibration_at(640) == segmenter.calibrations[(640, 40, "normal")]
    assert segmenter.calibration_at(640, "dark") == segmenter.calibrations[(640, 40, "dark")]
    assert segmenter.calibration_at(640, "bright") == segmenter.calibrations[(640, 40, "normal")]  # none measured
    assert one_look.calibration_at(640) == segmenter.calibrations[(640, 0, "normal")]
    assert segmenter.calibration_at(1280) == segmenter.calibrations[(1280, 0, "normal")]  # the width decides first
    # too few cut points in a light: no table of its own
    lines.clear()
    calibrate_model(
        model,
        seeds=(2861, 2862),
        cache=tmp_path / "cal",
        log=lines.append,
        settings=((640, 0),),
        light_changes=("dusk",),
    )
    assert any("dark light at width 640, trunk band 0 px: only" in line and "no table" in line for line in lines)
    assert {t["light"] for t in json.loads((tmp_path / "branchnet.json").read_text())["confidence_calibrations"]} == {
        "normal"
    }


@pytest.mark.parametrize(
    ("seeds", "parts", "ranges"),
    [
        ((2861, 3101), 2, [(2861, 2981), (2981, 3101)]),
        ((2861, 2864), 2, [(2861, 2862), (2862, 2864)]),
        ((2861, 2863), 4, [(2861, 2862), (2862, 2863)]),  # never an empty range
        ((2861, 2871), 1, [(2861, 2871)]),
    ],
)
def test_the_calibration_scenes_split_into_contiguous_ranges_in_order(seeds, parts, ranges):
    from branchrange.learning.calibration import seed_ranges

    assert seed_ranges(seeds, parts) == ranges


def test_a_frame_is_read_through_the_calibration_of_its_light_and_dark_light_gives_no_target(scene, tmp_path):
    rendered, stereo = scene
    cam = rendered.camera
    for name in ("branchnet.onnx", "branchnet.json"):
        shutil.copy(SHIPPED_MODEL.with_name(name), tmp_path / name)
    meta = json.loads((tmp_path / "branchnet.json").read_text())
    identity = {"raw": [0.0, 1.0], "calibrated": [0.0, 1.0], "network_width": 640, "trunk_band_px": 0}
    tables = [
        {**identity, "target_min_confidence": 0.5},
        {**identity, "light": "dark", "calibrated": [0.0, 0.5], "target_min_confidence": None},
        {**identity, "light": "bright", "target_min_confidence": 1.0},
    ]
    (tmp_path / "branchnet.json").write_text(json.dumps({**meta, "confidence_calibrations": tables}))

    def run(left, light_calibration=True):
        config = LearnedSegmenterConfig(model=str(tmp_path / "branchnet.onnx"), trunk_band_px=0)
        segmenter = LearnedSegmenter(replace(config, light_calibration=light_calibration))
        settings = untracked_whole_frame()  # a low target minimum of its own: what the light asks decides
        settings = replace(settings, cutpoints=replace(settings.cutpoints, target_min_confidence=0.1))
        pipeline = Pipeline(settings, focal_px=cam.focal_px, baseline_m=cam.baseline_m, segmenter=segmenter)
        return pipeline.process_disparity(left, stereo.disparity, stereo.confidence), pipeline.last.masks

    normal, normal_masks = run(rendered.left)
    assert normal_masks.light.light == "normal" and normal_masks.target_min_confidence == 0.0
    assert normal.masks.light.light == "normal" and normal.target is not None  # the settings' 0.1 stands
    assert all(b.light_refuses_target is None for b in normal.branches)
    dusk_left = (rendered.left * 0.3).astype(np.uint8)  # same disparity: only the reading of confidences changes
    dusk, dusk_masks = run(dusk_left)
    assert dusk.masks.light.light == "dark" and dusk.masks.light.median_grey < 55
    assert dusk_masks.calibration == ConfidenceCalibration((0.0, 1.0), (0.0, 0.5))
    assert dusk_masks.target_min_confidence == math.inf and dusk.branches and dusk.target is None
    assert dusk.reason.startswith("no target in dark light (median grey") and "≥ 90 % right" in dusk.reason
    assert max(b.confidence for b in dusk.branches) <= 0.5
    assert all(b.light_refuses_target for b in dusk.branches)  # so the MAVLink relay's tracks hold to it too
    bright, _ = run(np.clip(rendered.left.astype(int) * 2 + 40, 0, 255).astype(np.uint8))
    assert bright.masks.light.light == "bright"
    assert bright.branches and bright.target is None  # 1.0 asked: no cut point is that sure
    assert "no branch reaches the target confidence 1.0 that bright light needs (median grey" in bright.reason
    # switched off: every frame through the normal table, no light measured, the settings' minimum alone
    off, off_masks = run(dusk_left, light_calibration=False)
    assert off.masks.light is None and off_masks.target_min_confidence == 0.0
    assert [b.confidence for b in off.branches] != [b.confidence for b in dusk.branches]


def test_target_and_obstacle_defaults_come_from_the_shipped_calibration_table():
    from branchrange.config.sections import MavlinkConfig
    from branchrange.core.cutpoints import CutPointConfig

    tables = json.loads(SHIPPED_MODEL.with_suffix(".json").read_text())["confidence_calibrations"]
    defaults = LearnedSegmenterConfig()
    setting = (640, defaults.trunk_band_px, "normal")
    table = next(t for t in tables if (t["network_width"], t["trunk_band_px"], t.get("light")) == setting)
    assert CutPointConfig().target_min_confidence == table["target_min_confidence"]
    assert MavlinkConfig().obstacle_min_confidence == table["obstacle_min_confidence"]


def test_instance_balance_weighs_a_small_branch_up_and_plain_weights_match_cross_entropy():
    from branchrange.learning.training import instance_weights, weighted_cross_entropy

    instances = np.zeros((40, 60), np.uint16)
    instances[5:35, 5:25] = 1  # a thick limb, 600 px
    instances[10:12, 30:55] = 2  # a thin stem, 50 px
    instances[20:30, 30:50] = 3  # a middling branch, 200 px (the median)
    instances[0:5, 0:60] = 65535  # trunk
    classes = classes_from_instances(instances)
    weights = instance_weights(classes, instances, 0.5)
    assert weights[instances == 65535].tolist() == [1.0] * 300 and weights[0, 0] == 1.0
    assert np.isclose(weights[10, 40], (200 / 50) ** 0.5) and np.isclose(weights[20, 40], 1.0)
    assert np.isclose(weights[10, 10], (200 / 600) ** 0.5)
    assert np.isclose(instance_weights(classes, instances, 2.0)[10, 40], 4.0)  # clipped
    assert (instance_weights(classes, instances, 0.0) == 1).all()
    logits = torch.randn(2, 3, 8, 8)
    targets = torch.randint(0, 3, (2, 8, 8))
    targets[0, 0, :4] = IGNORE
    class_weights = torch.tensor([1.0, 1.0, 5.0])
    plain = F.cross_entropy(logits, targets, weight=class_weights, ignore_index=IGNORE)
    assert torch.allclose(weighted_cross_entropy(logits, targets, class_weights, torch.ones(2, 8, 8)), plain)
    doubled = torch.where(targets == BRANCH, 2.0, 1.0)
    assert not torch.allclose(weighted_cross_entropy(logits, targets, class_weights, doubled), plain)


def test_a_second_stage_starts_from_the_given_weights_and_records_their_hash(tmp_path):
    from branchrange.learning.training import train_branchnet

    settings = ["train_seeds=[1, 2]", "val_seeds=[2, 3]", "batch=1", "crop=64", "width=4", "threads=1"]
    first = tmp_path / "first"
    train_branchnet(training_config(None, [*settings, "steps=1"]), first, tmp_path / "data", log=lambda _: None)
    start = torch.load(first / "branchnet.pt")
    config = training_config(
        None, [*settings, "steps=1", "lr=1e-12", "instance_balance=0.5", f'init_weights="{first / "branchnet.pt"}"']
    )
    meta = train_branchnet(config, tmp_path / "second", tmp_path / "data", log=lambda _: None)
    second = torch.load(tmp_path / "second" / "branchnet.pt")
    learned = [k for k in start if "running" not in k and "num_batches" not in k]  # batch-norm statistics move
    assert all(torch.allclose(start[k], second[k], atol=1e-6) for k in learned)  # lr ≈ 0: the weights it started from
    assert meta["init_sha256"] == hashlib.sha256((first / "branchnet.pt").read_bytes()).hexdigest()
    with pytest.raises(ValueError, match="train the stage before"):
        train_branchnet(training_config(None, ['init_weights="no/such.pt"']), tmp_path / "x", tmp_path / "data")
    with pytest.raises(ValueError, match="instance_balance"):
        training_config(None, ["instance_balance=-1"])
    # a stage that adds the full-resolution branch keeps every other tensor, and the new ones start fresh
    lines: list[str] = []
    finer = training_config(
        None, [*settings, "steps=1", "lr=1e-12", "fine_width=3", f'init_weights="{first / "branchnet.pt"}"']
    )
    meta = train_branchnet(finer, tmp_path / "finer", tmp_path / "data", log=lines.append)
    grown = torch.load(tmp_path / "finer" / "branchnet.pt")
    assert meta["fine_width"] == 3 and any(k.startswith("fine.") for k in grown)
    assert all(torch.allclose(start[k], grown[k], atol=1e-6) for k in learned if not k.startswith("head.0.0"))
    assert grown["head.0.0.weight"].shape[1] == 4 + 3  # width + fine_width channels into the head
    assert any("start fresh" in line and "fine.0.0.weight" in line for line in lines)
    with pytest.raises(ValueError, match="not a BranchNet of width 8"):
        wider = [*settings[:4], "width=8", "threads=1", "steps=1", f'init_weights="{first / "branchnet.pt"}"']
        train_branchnet(training_config(None, wider), tmp_path / "wider", tmp_path / "data", log=lambda _: None)


def test_the_shipped_int8_model_is_the_fp32_one_quantized_and_labels_alike(scene):
    from branchrange.core.segmentation.learned import SHIPPED_MODELS

    rendered, stereo = scene
    meta = json.loads(SHIPPED_MODELS["int8"].with_suffix(".json").read_text())
    # the int8 file was made from the fp32 file shipped beside it (re-quantize after retraining)
    assert meta["quantized_from"]["onnx_sha256"] == hashlib.sha256(SHIPPED_MODEL.read_bytes()).hexdigest()
    assert SHIPPED_MODELS["int8"].stat().st_size < SHIPPED_MODEL.stat().st_size
    fp32, int8 = LearnedSegmenter(), LearnedSegmenter(LearnedSegmenterConfig(precision="int8"))
    # its own calibration: each setting in each light
    assert int8.model_path == SHIPPED_MODELS["int8"] and set(int8.calibrations) == {
        (*setting, light) for setting in ((640, 40), (640, 0), (1280, 0)) for light in LIGHTS
    }
    classes = [s.logits(rendered.left, stereo.disparity).argmax(0) for s in (fp32, int8)]
    assert np.mean(classes[0] == classes[1]) > 0.98
    branch = classes[0] == CLASSES.index("branch")
    assert np.mean(classes[1][branch] == CLASSES.index("branch")) > 0.8  # the thin class survives int8 too


def test_the_fp32_model_runs_without_the_blocked_layout_and_gives_the_same_logits(scene):
    import onnxruntime as ort

    from branchrange.core.segmentation.onnx_model import onnx_session

    rendered, stereo = scene
    fp32, int8 = LearnedSegmenter(), LearnedSegmenter(LearnedSegmenterConfig(precision="int8"))
    level = ort.GraphOptimizationLevel
    assert fp32.session.get_session_options().graph_optimization_level == level.ORT_ENABLE_EXTENDED
    assert int8.session.get_session_options().graph_optimization_level == level.ORT_ENABLE_ALL
    first = fp32.logits(rendered.left, stereo.disparity)
    fp32.session = onnx_session(fp32.model_path, 1, blocked_layout=True)
    np.testing.assert_allclose(fp32.logits(rendered.left, stereo.disparity), first, atol=1e-4)


def test_precision_names_a_shipped_model_or_a_bundle_copy_only():
    with pytest.raises(OnnxSegmenterError, match="precision"):
        LearnedSegmenterConfig(precision="int4")
    with pytest.raises(OnnxSegmenterError, match="precision"):
        LearnedSegmenterConfig(model="mine.onnx", precision="int8")


def test_a_trained_model_quantizes_to_an_int8_copy_that_segments(tmp_path):
    from branchrange.learning.quantize import int8_path, quantize_branchnet
    from branchrange.learning.training import train_branchnet

    settings = ["train_seeds=[1, 2]", "val_seeds=[2, 3]", "steps=2", "batch=1", "crop=64", "width=4", "threads=1"]
    train_branchnet(training_config(None, settings), tmp_path / "run", tmp_path / "data", log=lambda _: None)
    model = tmp_path / "run" / "branchnet.onnx"
    meta = quantize_branchnet(model, tmp_path / "data", seeds=(1, 3))
    quantized = int8_path(model)
    assert quantized.name == "branchnet_int8.onnx" and not list(tmp_path.glob("run/*prepared*"))
    assert meta["quantized_from"]["onnx_sha256"] == hashlib.sha256(model.read_bytes()).hexdigest()
    assert meta["onnx_sha256"] == hashlib.sha256(quantized.read_bytes()).hexdigest()
    assert "QuantizeLinear" in quantized.read_bytes().decode("latin-1")  # an int8 graph, not a copy
    segmenter = LearnedSegmenter(LearnedSegmenterConfig(model=str(quantized)))
    masks = segmenter.segment(
        np.zeros((50, 70, 3), np.uint8), np.full((50, 70), 5.0, np.float32), StereoGeometry.centred(100.0, 0.1, 70, 50)
    )
    assert masks.labels.shape == (50, 70)
