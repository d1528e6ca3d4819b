"""`branchrange estimate`, `demo` and `evaluate-cuts` run end to end on synthetic files."""

from __future__ import annotations

import json

import cv2
import jsonschema
import numpy as np
import pytest
from result_factory import branch

from branchrange.cli import main
from branchrange.core.frame_result import SCHEMA_PATH
from branchrange.offline.evaluate_cuts import CutScores, evaluate_cuts, recall_difference_interval
from camera.calibration import from_rectified
from camera.opencv_file import write_opencv_file
from stereo.io import write_rgb
from stereo.synth import SynthCamera, render_scene
from stereo.synth.writer import write_dataset, write_mask

SCHEMA = json.loads(SCHEMA_PATH.read_text(encoding="utf-8"))


@pytest.fixture(scope="module")
def pair_files(tmp_path_factory):
    scene = render_scene(6, SynthCamera.zed_mini(640, 360))
    folder = tmp_path_factory.mktemp("pair")
    write_rgb(folder / "left.png", scene.left)
    write_rgb(folder / "right.png", scene.right)
    write_mask(folder / "mask.png", scene.instance_mask)
    return folder, scene


def test_estimate_with_focal_and_baseline_writes_json_and_overlay(pair_files, tmp_path, capsys):
    folder, scene = pair_files
    out_json, out_png = tmp_path / "r.json", tmp_path / "o.png"
    rc = main(
        [
            "estimate",
            "--left",
            str(folder / "left.png"),
            "--right",
            str(folder / "right.png"),
            "--focal-px",
            str(scene.camera.focal_px),
            "--baseline-m",
            str(scene.camera.baseline_m),
            "--mask",
            str(folder / "mask.png"),
            "--max-disp",
            "128",
            "--json",
            str(out_json),
            "--overlay",
            str(out_png),
        ]
    )
    assert rc == 0
    result = json.loads(out_json.read_text())
    jsonschema.validate(result, SCHEMA)
    assert result["stereo"]["backend"] == "sgbm" and result["masks"]["instances"] >= 5
    near = [
        b
        for b in scene.branches
        if b.cut_visible
        and any(np.linalg.norm(np.array(e["cut_point_m"]) - b.cut_point_m) < 0.05 for e in result["branches"])
    ]
    assert len(near) >= 5
    overlay = cv2.imread(str(out_png))
    assert overlay.shape == (360, 640, 3)
    assert not np.array_equal(overlay[..., ::-1], scene.left)  # something was drawn
    target = next(b for b in result["branches"] if b["id"] == result["target_id"])
    u, v = (int(round(c)) for c in target["pixel"])
    ring = overlay[max(v - 12, 0) : v + 13, max(u - 12, 0) : u + 13].reshape(-1, 3).astype(int)  # BGR
    assert np.any((ring[:, 2] > 200) & (ring[:, 1] < 80) & (ring[:, 0] < 80))  # the target's red ring
    assert "target" in capsys.readouterr().out


def test_estimate_with_a_calibration_file_prints_schema_json(pair_files, tmp_path, capsys):
    folder, scene = pair_files
    cam = scene.camera
    calib = write_opencv_file(
        from_rectified(cam.focal_px, cam.cx, cam.cy, cam.baseline_m, (cam.width, cam.height)), tmp_path / "calib.yaml"
    )
    rc = main(
        [
            "estimate",
            "--left",
            str(folder / "left.png"),
            "--right",
            str(folder / "right.png"),
            "--calib",
            str(calib),
            "--rectified",
            "--mask",
            str(folder / "mask.png"),
            "--max-disp",
            "128",
        ]
    )
    assert rc == 0
    result = json.loads(capsys.readouterr().out)
    jsonschema.validate(result, SCHEMA)
    assert result["camera"]["focal_px"] == pytest.approx(cam.focal_px)


def test_estimate_reports_bad_input_with_exit_status_2(pair_files, tmp_path, capsys):
    folder, scene = pair_files
    small = tmp_path / "small.png"
    write_rgb(small, scene.right[:, :600])
    rc = main(
        [
            "estimate",
            "--left",
            str(folder / "left.png"),
            "--right",
            str(small),
            "--focal-px",
            "320",
            "--baseline-m",
            "0.063",
        ]
    )
    assert rc == 2
    assert "differ in size" in capsys.readouterr().err
    wrong = write_opencv_file(from_rectified(640.0, 639.5, 359.5, 0.063, (1280, 720)), tmp_path / "hd.yaml")
    rc = main(
        ["estimate", "--left", str(folder / "left.png"), "--right", str(folder / "right.png"), "--calib", str(wrong)]
    )
    assert rc == 2
    assert "1280×720" in capsys.readouterr().err
    rc = main(
        [
            "estimate",
            "--left",
            str(tmp_path / "missing.png"),
            "--right",
            str(folder / "right.png"),
            "--focal-px",
            "320",
            "--baseline-m",
            "0.063",
        ]
    )
    assert rc == 2 and "missing.png" in capsys.readouterr().err


@pytest.mark.parametrize(
    "case, message",
    [
        ("mask_of_wrong_size", "must match the left image"),
        ("empty_mask", "holds no branch instance"),
        ("emcstereo_without_weights", "--backend emcstereo needs --weights"),
        ("trunk_id_0", "trunk_id = 0"),
        ("json_in_a_file_not_a_folder", "not_a_folder"),
    ],
)
def test_estimate_names_each_bad_input_and_exits_2_without_a_traceback(case, message, pair_files, tmp_path, capsys):
    folder, scene = pair_files
    args = [
        "estimate",
        "--left",
        str(folder / "left.png"),
        "--right",
        str(folder / "right.png"),
        "--focal-px",
        "320",
        "--baseline-m",
        "0.063",
        "--max-disp",
        "64",
        "--mask",
        str(folder / "mask.png"),
    ]
    if case == "mask_of_wrong_size":
        write_mask(tmp_path / "small.png", scene.instance_mask[:100, :100])
        args[-1] = str(tmp_path / "small.png")
    elif case == "empty_mask":
        write_mask(tmp_path / "empty.png", np.zeros_like(scene.instance_mask))
        args[-1] = str(tmp_path / "empty.png")
    elif case == "emcstereo_without_weights":
        args += ["--backend", "emcstereo"]
    elif case == "trunk_id_0":
        args += ["--trunk-id", "0"]
    else:
        (tmp_path / "not_a_folder").write_text("a file")
        args += ["--json", str(tmp_path / "not_a_folder" / "out.json")]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("branchrange estimate: error: ") and message in err and "Traceback" not in err


def test_demo_says_sgbm_prints_truth_table_and_writes_overlay(tmp_path, capsys):
    rc = main(["demo", "--out", str(tmp_path / "demo")])
    out = capsys.readouterr().out
    assert rc == 0
    assert "using the classical sgbm stereo backend" in out
    assert "visible cut points within 5 cm" in out
    result = json.loads((tmp_path / "demo" / "result.json").read_text())
    jsonschema.validate(result, SCHEMA)
    assert cv2.imread(str(tmp_path / "demo" / "overlay.png")).shape == (360, 640, 3)


def test_demo_names_an_output_folder_it_cannot_create(tmp_path, capsys):
    (tmp_path / "a_file").write_text("not a folder")
    assert main(["demo", "--out", str(tmp_path / "a_file" / "demo"), "--size", "320x256"]) == 2
    err = capsys.readouterr().err
    assert "cannot write the outputs to" in err and "a_file" in err and "Traceback" not in err


def test_demo_refuses_emcstereo_without_weights(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--backend", "emcstereo"]) == 2
    assert "needs --weights" in capsys.readouterr().err


@pytest.fixture(scope="module")
def tiny_set(tmp_path_factory):
    root = tmp_path_factory.mktemp("set")
    write_dataset(root, 2, 0, 480, 270, progress=False)
    return root


def test_evaluate_cuts_scores_ground_truth_geometry(tiny_set):
    [gt_gt] = evaluate_cuts(tiny_set, ["gt"], ["gt"])
    assert gt_gt.frames == 2 and gt_gt.truth >= 3
    assert gt_gt.recall >= 0.75
    low, high = gt_gt.interval()["recall"]
    assert low <= gt_gt.recall <= high
    assert gt_gt.error_quantile(0.5) < 0.015
    assert gt_gt.false_per_frame <= 1.0
    assert gt_gt.targets == 2 and gt_gt.target_accuracy == 1.0


def test_evaluate_cuts_scores_a_target_far_from_every_truth_as_a_miss():
    scores = CutScores("gt", "gt")
    truth = [{"cut_point_m": [0.0, 0.0, 1.0], "cut_visible": True}]
    near, far = branch(0, [0.0, 0.0, 1.01]), branch(0, [0.0, 0.0, 1.2])
    scores.add_frame(truth, [near], target=near)
    scores.add_frame(truth, [far], target=far)
    scores.add_frame(truth, [], target=None)
    assert (scores.targets, scores.targets_within, scores.target_accuracy) == (2, 1, 0.5)


def test_scores_carry_a_bootstrap_interval_over_frames():
    truth = [{"cut_point_m": [0.0, 0.0, 1.0], "cut_visible": True}, {"cut_point_m": [0.3, 0.0, 1.0]}]
    hit, miss = branch(0, [0.0, 0.0, 1.01]), branch(1, [0.3, 0.0, 1.2])
    steady = CutScores("gt", "gt")
    for _ in range(6):
        steady.add_frame(truth, [hit, miss])  # every frame alike: 1 of 2 found, 1 false
    assert steady.frame_counts == [(1, 2, 1)] * 6
    assert steady.interval() == {"recall": (0.5, 0.5), "false_per_frame": (1.0, 1.0)}
    mixed = CutScores("gt", "gt")
    for k in range(20):  # half the frames find both branches, half find none and report two false ones
        mixed.add_frame(truth, [hit, branch(1, [0.3, 0.0, 1.0])] if k % 2 else [miss, branch(2, [1.0, 1.0, 3.0])])
    (low, high), (f_low, f_high) = mixed.interval()["recall"], mixed.interval()["false_per_frame"]
    assert low < mixed.recall == 0.5 < high and f_low < mixed.false_per_frame == 1.0 < f_high
    assert 0.2 < low and high < 0.8  # 20 frames: about ± 0.22
    assert mixed.interval() == mixed.interval()  # seeded: a run repeats
    assert mixed.interval(level=0.5)["recall"][1] < high
    lone = CutScores("gt", "gt")
    lone.add_frame(truth, [hit])
    assert all(np.isnan(v) for bounds in lone.interval().values() for v in bounds)


def test_a_paired_difference_tells_apart_what_the_single_intervals_cannot():
    truth = [{"cut_point_m": [x, 0.0, 1.0]} for x in (0.0, 0.3, 0.6, 0.9)]
    found = [branch(k, t["cut_point_m"]) for k, t in enumerate(truth)]
    better, worse = CutScores("gt", "a"), CutScores("gt", "b")
    for k in range(30):  # scenes from easy to hard; the better one finds one branch more in every fourth
        easy = found[: 1 + k % 4]
        better.add_frame(truth, easy + found[len(easy) : len(easy) + (k % 4 == 0)])
        worse.add_frame(truth, easy)
    assert better.interval()["recall"][0] < worse.interval()["recall"][1]  # the single intervals overlap
    low, high = recall_difference_interval(better, worse)
    assert 0 < low <= better.recall - worse.recall <= high
    other = CutScores("gt", "c")
    other.add_frame(truth[:1], [])
    with pytest.raises(ValueError, match="same frames"):
        recall_difference_interval(better, other)


def test_evaluate_cuts_command_prints_the_table(tiny_set, tmp_path, capsys):
    rc = main(
        ["evaluate-cuts", str(tiny_set), "--stereo", "gt", "sgbm", "--limit", "1", "--json", str(tmp_path / "s.json")]
    )
    out = capsys.readouterr().out
    assert rc == 0
    for row in ("gt         gt", "gt         segmenter", "sgbm       gt", "sgbm       segmenter"):
        assert row in out
    scores = json.loads((tmp_path / "s.json").read_text())
    assert len(scores) == 4 and all(s["frames"] == 1 for s in scores)


def test_evaluate_cuts_refuses_an_unknown_target_policy(tiny_set, capsys):
    assert main(["evaluate-cuts", str(tiny_set), "--stereo", "gt", "--target-policy", "farthest"]) == 2
    assert "target_policy = 'farthest'" in capsys.readouterr().err


def test_evaluate_cuts_names_a_folder_that_is_not_a_set(tmp_path, capsys):
    assert main(["evaluate-cuts", str(tmp_path)]) == 2
    assert "not a set written by `emcstereo synth`" in capsys.readouterr().err
