"""`branchrange export-frames`: frames picked for labelling, written as COCO that pycocotools reads back exactly."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from synth_recording import FIRST_TIMESTAMP_NS, HEIGHT, WIDTH, tree_scene, write_tree_recording

from branchrange.cli import main
from branchrange.commands.exit_codes import BAD_INPUT, DONE
from branchrange.config.loader import Config
from branchrange.core.frame_results import run_header_line
from branchrange.learning.coco_labels import read_labelled_frames
from branchrange.learning.samples import BRANCH
from branchrange.offline.frame_export import frames_source
from branchrange.offline.frame_selection import FrameStats, mask_agreement, select_frames, with_flicker
from camera.sources.image_files import read_mask, read_rgb
from camera.sources.recording_format import mask_name
from stereo.synth.truth import TRUNK_ID, is_branch_id

#: pycocotools' decoder under numpy 2 warns about its own `__array__`; not ours to fix
pytestmark = pytest.mark.filterwarnings("ignore:__array__ implementation doesn't accept a copy keyword")
coco = pytest.importorskip("pycocotools.coco", reason="pycocotools (the 'coco' extra) writes and reads the masks")

SECOND = 1_000_000_000


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """Four frames of the synthetic tree, 1 s apart, with their instance masks."""
    return write_tree_recording(tmp_path_factory.mktemp("rec") / "rec", count=4, period_ns=SECOND)


def _decoded(dataset, image_id: int) -> dict[str, list[np.ndarray]]:
    """Category name → the boolean masks pycocotools decodes from the image's annotations."""
    names = {c["id"]: c["name"] for c in dataset.loadCats(dataset.getCatIds())}
    found: dict[str, list[np.ndarray]] = {"branch": [], "trunk": []}
    for annotation in dataset.loadAnns(dataset.getAnnIds(imgIds=[image_id])):
        found[names[annotation["category_id"]]].append(dataset.annToMask(annotation).astype(bool))
    return found


def test_export_round_trips_the_recordings_masks_exactly_through_pycocotools(recording, tmp_path, capsys):
    out = tmp_path / "coco"
    assert main(["export-frames", str(recording), "--out", str(out), "--count", "3", "--min-spacing-s", "1.5"]) == DONE
    assert "picked 2" in capsys.readouterr().out  # 4 frames 1 s apart, 1.5 s spacing: two fit
    dataset = coco.COCO(str(out / "annotations.json"))
    assert [(c["id"], c["name"]) for c in dataset.loadCats(dataset.getCatIds())] == [(1, "branch"), (2, "trunk")]
    images = dataset.loadImgs(dataset.getImgIds())
    assert len(images) == 2 and abs(images[0]["timestamp_ns"] - images[1]["timestamp_ns"]) >= 1.5 * SECOND
    raw = json.loads((out / "annotations.json").read_text())
    assert raw["info"]["contributor"] == "branchrange export-frames" and raw["licenses"][0]["id"] == 1
    for image in images:
        position = (image["timestamp_ns"] - FIRST_TIMESTAMP_NS) // SECOND
        truth = read_mask(recording / mask_name(position))
        exported = read_rgb(out / "images" / image["file_name"])
        assert np.array_equal(exported, read_rgb(recording / "left" / f"{position:06d}.png"))  # rectified already
        assert (image["width"], image["height"]) == (truth.shape[1], truth.shape[0])
        found = _decoded(dataset, image["id"])
        expected = [truth == i for i in np.unique(truth) if is_branch_id(i)]
        assert len(found["branch"]) == len(expected) >= 5
        for mask in expected:  # each branch instance comes back pixel for pixel
            assert sum(np.array_equal(mask, f) for f in found["branch"]) == 1
        assert len(found["trunk"]) == 1 and np.array_equal(found["trunk"][0], truth == TRUNK_ID)
    polygons = coco.COCO(str(out / "annotations_polygons.json"))  # what Label Studio imports: the outlines
    first = polygons.loadAnns(polygons.getAnnIds(imgIds=[images[0]["id"]]))
    assert first and all(isinstance(a["segmentation"], list) and len(a["segmentation"][0]) >= 6 for a in first)
    iou = [mask_agreement(polygons.annToMask(a).astype(bool), dataset.annToMask(a).astype(bool)) for a in first]
    assert min(iou) > 0.95  # holes aside, the outlines give the masks back
    trainable = read_labelled_frames(out / "annotations.json", out / "images")  # what a fine-tune reads back
    camera = tree_scene().camera
    assert [f.name for f in trainable] == [image["file_name"] for image in images]
    for frame in trainable:
        assert (
            frame.geometry.focal_px == pytest.approx(camera.focal_px) and frame.geometry.baseline_m == camera.baseline_m
        )
        assert frame.sample["disparity"].shape == (HEIGHT, WIDTH) and (frame.sample["disparity"] > 0).mean() > 0.5
        assert frame.confidence.shape == (HEIGHT, WIDTH) and (frame.sample["classes"] == BRANCH).any()


def test_without_masks_the_configured_segmenter_pre_annotates(tmp_path):
    from branchrange.core.pipeline import Pipeline, PipelineConfig, StereoConfig
    from branchrange.core.segmentation.choose import SegmenterConfig
    from camera.sources import open_source

    recording = write_tree_recording(tmp_path / "plain", count=1, period_ns=SECOND, with_masks=False)
    out = tmp_path / "coco"
    assert main(["export-frames", str(recording), "--out", str(out), "--segmenter", "structure"]) == DONE
    with open_source(f"replay:{recording}", pace="fast") as source:
        frame = next(source)
        config = PipelineConfig(stereo=StereoConfig(mode="full"), segmenter=SegmenterConfig(model="structure"))
        pipeline = Pipeline(config, calibration=source.calibration)
    pipeline.process(frame.left, frame.right)
    masks = pipeline.last.masks
    dataset = coco.COCO(str(out / "annotations.json"))
    found = _decoded(dataset, dataset.getImgIds()[0])
    assert masks.source == "structure" and len(found["branch"]) == len(masks.branch_ids()) >= 1
    for branch_id in masks.branch_ids():
        assert sum(np.array_equal(masks.branch(branch_id), f) for f in found["branch"]) == 1


def _stats(index: int, colour: int, confidence: float, near: float = 0.5) -> FrameStats:
    """A frame at `index` s whose histogram is all in bin `colour`, the segmenters agreeing."""
    histogram = np.zeros(64)
    histogram[colour] = 1.0
    return FrameStats(index, index * SECOND, histogram, near, confidence=confidence, agreement=1.0)


def test_selection_starts_uncertain_then_picks_unlike_frames_never_closer_than_the_spacing():
    """Ten frames 1 s apart: 0–4 red, 5–9 green; frame 2 the most uncertain. With 2 s spacing: 2 first
    (most uncertain), then the first green frame far enough from it (5), then the earliest frame left
    (0: every other candidate is as unlike what was picked and as certain)."""
    stats = [_stats(i, 0 if i < 5 else 63, 0.1 if i == 2 else 0.5) for i in range(10)]
    picked = [s.index for s in select_frames(stats, 3, 2 * SECOND)]
    assert picked == [2, 5, 0]
    everything = [s.index for s in select_frames(stats, 10, 2 * SECOND)]
    assert all(abs(a - b) >= 2 for i, a in enumerate(everything) for b in everything[i + 1 :])
    assert len(everything) == 5  # ten seconds hold five frames two seconds apart


def test_selection_prefers_an_unlike_scene_over_a_more_uncertain_copy():
    """After the first pick, a frame of another colour and nearness beats a slightly more uncertain
    frame that looks like the first."""
    stats = [_stats(0, 0, 0.0), _stats(5, 0, 0.2), _stats(10, 63, 0.7, near=0.9)]
    assert [s.index for s in select_frames(stats, 2, SECOND)] == [0, 10]


def test_flicker_counts_branches_seen_in_one_frame_alone_and_branches_one_frame_missed():
    """A branch at 1 m seen in every frame but 3; frame 2 also sees one 0.5 m aside that no neighbour sees."""
    steady, stray = [0.0, 0.0, 1.0], [0.5, 0.0, 1.0]
    points = {0: [steady], 1: [steady], 2: [steady, stray], 3: [], 4: [[0.05, 0.0, 1.02]]}  # 5 cm off: the same
    stats = [replace(_stats(i, 0, 0.5), cut_points=np.array(p).reshape(-1, 3)) for i, p in points.items()]
    flicker = [s.flicker for s in with_flicker(stats)]
    assert flicker == [0.0, 0.0, 0.5, 1.0, 0.0]
    first, _, third, fourth, _ = with_flicker(stats)
    assert fourth.uncertainty > third.uncertainty > first.uncertainty  # (0.5 + 0 + f) / 3


def test_bad_sources_and_options_are_clear_errors_with_the_bad_input_exit_code(recording, tmp_path, capsys):
    out = str(tmp_path / "coco")
    assert main(["export-frames", str(tmp_path / "missing"), "--out", out]) == BAD_INPUT
    err = capsys.readouterr().err
    assert "branchrange export-frames:" in err and "missing" in err and "Traceback" not in err
    assert main(["export-frames", str(recording), "--out", out, "--count", "0"]) == BAD_INPUT
    assert "expected a count ≥ 1" in capsys.readouterr().err
    live = tmp_path / "daemon.jsonl"
    live.write_text(run_header_line("daemon", Config(), "zed:0"))
    assert main(["export-frames", str(live), "--out", out]) == BAD_INPUT
    assert "its run read 'zed:0', not a recording" in capsys.readouterr().err
    junk = tmp_path / "junk.jsonl"
    junk.write_text("not json\n")
    assert main(["export-frames", str(junk), "--out", out]) == BAD_INPUT
    assert "not a readable results file" in capsys.readouterr().err
    assert not (tmp_path / "coco").exists()


def test_a_replays_results_file_names_the_recording_to_export_from(recording, tmp_path):
    results = tmp_path / "results.jsonl"
    results.write_text(run_header_line("replay", Config(), f"replay:{recording}") + '{"schema": "branchrange/v1"}\n')
    assert frames_source(results) == f"replay:{recording}"
    assert frames_source(recording) == f"replay:{recording}"


def test_a_ros2_bag_is_exported_with_the_segmenters_masks(recording, tmp_path, capsys):
    pytest.importorskip("rosbags", reason="ROS 2 bags need the 'ros' extra")
    from camera.sources import open_source
    from camera.sources.rosbag_writer import write_bag

    with open_source(f"replay:{recording}", pace="fast") as source:
        write_bag(list(source), source.calibration, tmp_path / "bag")
    out = tmp_path / "coco"
    argv = ["export-frames", str(tmp_path / "bag"), "--out", str(out), "--count", "2", "--segmenter", "structure"]
    assert main(argv) == DONE
    assert "scored 4 frames of rosbag:" in capsys.readouterr().out
    dataset = coco.COCO(str(out / "annotations.json"))
    images = dataset.loadImgs(dataset.getImgIds())
    assert len(images) == 2 and all(dataset.getAnnIds(imgIds=[image["id"]]) for image in images)
    for image in images:  # the bag's frames, in time order, as they were recorded
        assert np.array_equal(
            read_rgb(out / "images" / image["file_name"]),
            read_rgb(recording / "left" / f"{image['frame_index']:06d}.png"),
        )


def _shrink(recording, position: int) -> None:
    """Make the recording's pair at `position` half its size: a frame its calibration does not fit."""
    import cv2

    for side in ("left", "right"):
        path = recording / side / f"{position:06d}.png"
        cv2.imwrite(str(path), cv2.resize(cv2.imread(str(path)), (240, 136)))


def test_frames_the_pipeline_rejects_are_skipped_and_counted_and_none_scored_is_bad_input(tmp_path, capsys):
    recording = write_tree_recording(tmp_path / "rec", count=2, period_ns=SECOND, with_masks=True)
    _shrink(recording, 1)
    assert main(["export-frames", str(recording), "--out", str(tmp_path / "coco"), "--count", "2"]) == DONE
    assert "scored 1 frames of replay:" in (out := capsys.readouterr().out) and "1 rejected by the pipeline" in out
    lonely = write_tree_recording(tmp_path / "lonely", count=1, period_ns=SECOND, with_masks=True)
    _shrink(lonely, 0)
    assert main(["export-frames", str(lonely), "--out", str(tmp_path / "none")]) == BAD_INPUT
    err = capsys.readouterr().err
    assert "no frame could be scored (0 unreadable, 1 rejected; frame 0: the calibration is for 480×270" in err
    assert not (tmp_path / "none").exists()
