"""Fine-tuning BranchNet on a user's COCO labels: reading them (polygons, RLE), a few steps that change the weights,
the model bundle it writes, and loading it (CLI name, config, API) — or refusing it when it is not what it says."""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import replace

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from api import create_app
from api.estimator import PipelineEstimator
from branchrange.cli import main
from branchrange.config.loader import load_config, pipeline_config
from branchrange.config.sections import ApiConfig
from branchrange.core.confidence import ConfidenceCalibration
from branchrange.core.geometry import StereoGeometry
from branchrange.core.pipeline import no_target_reason
from branchrange.core.segmentation.bundle import MANIFEST_NAME, bundle_model
from branchrange.core.segmentation.choose import make_segmenter
from branchrange.core.segmentation.learned import (
    SHIPPED_MODEL,
    LearnedSegmenter,
    LearnedSegmenterConfig,
    calibrations_by_setting,
)
from branchrange.core.segmentation.onnx_model import OnnxSegmenterError
from branchrange.core.segmentation.ood import reference_in
from branchrange.learning.coco_labels import (
    LabelsError,
    read_labelled_frames,
    split_by_image,
    write_frame_stereo,
)
from branchrange.learning.from_onnx import branchnet_from_onnx
from branchrange.learning.heldout import calibration_table, judged_cut_points, labelled_branches
from branchrange.learning.samples import BRANCH, IGNORE, TRUNK
from stereo.weights import sha256_of

pytestmark = pytest.mark.filterwarnings("ignore:__array__ implementation doesn't accept a copy keyword")
mask_api = pytest.importorskip("pycocotools.mask", reason="pycocotools (the 'coco' extra) reads the labels")

WIDTH, HEIGHT = 160, 96
GEOMETRY = StereoGeometry(100.0, 0.06, 79.5, 47.5)
#: the fine-tune of the tests: a few tiny steps, one synthetic scene to mix in, one to validate on
TINY = ["--steps", "3", "--set", "batch=2", "--set", "crop=64", "--set", "synthetic_scenes=1"]
TINY += [
    "--set",
    "validation_scenes=1",
    "--set",
    "val_every=3",
    "--set",
    "depth_scenes=2",
    "--synthetic-share",
    "0.5",
    "--holdout-share",
    "0.34",
]


def _frame(i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(left RGB, disparity px, trunk mask, branch mask) of drawn frame `i`: a bark-brown trunk, a stem leaving it."""
    rng = np.random.default_rng(i)
    left = rng.integers(40, 110, (HEIGHT, WIDTH, 3)).astype(np.uint8)
    left[..., 1] += 40  # greenish background
    trunk = np.zeros((HEIGHT, WIDTH), np.uint8)
    trunk[:, 66 + i : 82 + i] = 1
    branch = np.zeros_like(trunk)
    cv2.line(branch, (82 + i, 60 - 2 * i), (150, 18 + 3 * i), 1, 4)
    branch &= 1 - trunk
    left[trunk > 0] = (95, 70, 45)
    left[branch > 0] = (125, 95, 60)
    disparity = np.where(branch > 0, 22.0, np.where(trunk > 0, 20.0, 6.0)).astype(np.float32)
    return left, disparity, trunk.astype(bool), branch.astype(bool)


def _rle(mask: np.ndarray, compressed: bool) -> dict:
    """COCO RLE of a boolean mask: pycocotools' compressed string, or the plain column-major run lengths."""
    if compressed:
        rle = mask_api.encode(np.asfortranarray(mask.astype(np.uint8)))
        return {"size": list(rle["size"]), "counts": rle["counts"].decode("ascii")}
    flat = mask.T.reshape(-1).astype(np.int8)  # column-major, runs start with zeros
    edges = np.flatnonzero(np.diff(np.concatenate([[0], flat, [1 - flat[-1]]])))
    return {"size": list(mask.shape), "counts": np.diff(np.concatenate([[0], edges])).tolist()}


def write_dataset(folder, count: int = 12) -> dict:
    """`count` drawn frames as export-frames lays them out: images/, stereo/, annotations.json with the trunk as
    RLE (compressed in even frames, plain in odd ones), the stem as a polygon, and a 'leaf' left to ignore."""
    (folder / "images").mkdir(parents=True)
    (folder / "stereo").mkdir()
    images, annotations = [], []
    for i in range(count):
        left, disparity, trunk, branch = _frame(i)
        name = f"frame_{i:06d}.png"
        cv2.imwrite(str(folder / "images" / name), cv2.cvtColor(left, cv2.COLOR_RGB2BGR))
        write_frame_stereo(folder / "stereo" / f"frame_{i:06d}.npz", disparity, np.ones_like(disparity), GEOMETRY)
        images.append({"id": i + 1, "file_name": name, "width": WIDTH, "height": HEIGHT})
        doubled = cv2.resize(branch.astype(np.uint8), None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST)
        contour = cv2.findContours(doubled, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)[0][0]
        polygon = [(float(v) + 0.5) / 2 for v in contour.reshape(-1)]  # around the pixels, not through their centres
        base = {"image_id": i + 1, "iscrowd": 0, "area": 1.0, "bbox": [0, 0, 1, 1]}
        annotations += [
            {**base, "id": 3 * i + 1, "category_id": 2, "segmentation": _rle(trunk, compressed=i % 2 == 0)},
            {**base, "id": 3 * i + 2, "category_id": 1, "segmentation": [polygon]},
            {**base, "id": 3 * i + 3, "category_id": 7, "segmentation": [[2, 2, 12, 2, 12, 10, 2, 10]]},
        ]
    categories = [{"id": 1, "name": "branch"}, {"id": 2, "name": "Trunk"}, {"id": 7, "name": "leaf"}]
    coco = {"images": images, "annotations": annotations, "categories": categories}
    (folder / "annotations.json").write_text(json.dumps(coco))
    return coco


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    folder = tmp_path_factory.mktemp("labels")
    write_dataset(folder)
    return folder


@pytest.fixture(scope="module")
def bundle(dataset, tmp_path_factory):
    """A bundle fine-tuned through the command line on the drawn frames, with its int8 copy."""
    out = tmp_path_factory.mktemp("tuned") / "bundle"
    data = tmp_path_factory.mktemp("segdata")
    args = ["train-segmenter", "--coco", str(dataset / "annotations.json"), "--out", str(out), "--data", str(data)]
    assert main([*args, *TINY, "--workers", "1", "--int8"]) == 0
    return out


def test_coco_polygons_and_rle_are_read_by_category_name_and_others_left_out(dataset):
    said = []
    frames = read_labelled_frames(dataset / "annotations.json", dataset / "images", log=said.append)
    assert len(frames) == 12 and "['leaf'] left out" in said[0]
    for i, frame in enumerate(frames):
        _, disparity, trunk, branch = _frame(i)
        classes = frame.sample["classes"]
        assert np.array_equal(classes == TRUNK, trunk & ~(classes == BRANCH))  # RLE, plain or compressed: exact
        drawn = classes == BRANCH
        assert (drawn & branch).sum() / (drawn | branch).sum() > 0.8  # the polygon rasterised back
        assert set(np.unique(frame.sample["instances"])) == {0, 1}
        assert np.array_equal(frame.sample["disparity"], disparity) and frame.geometry == GEOMETRY
        assert not (classes == IGNORE).any() and frame.sample["left"][0, 0, 1] >= 80  # the leaf: background


def test_labels_without_branch_or_trunk_or_without_stereo_are_refused_clearly(dataset, tmp_path):
    coco = json.loads((dataset / "annotations.json").read_text())
    coco["categories"] = [{"id": c["id"], "name": f"thing{c['id']}"} for c in coco["categories"]]
    (tmp_path / "other.json").write_text(json.dumps(coco))
    with pytest.raises(LabelsError, match="no 'branch' or 'trunk' category"):
        read_labelled_frames(tmp_path / "other.json", dataset / "images")
    with pytest.raises(LabelsError, match="no stereo for this frame.*export-frames writes it"):
        read_labelled_frames(dataset / "annotations.json", dataset / "images", tmp_path)


def test_the_split_is_by_image_seeded_and_keeps_a_frame_on_each_side():
    train, held = split_by_image(6, 0.34, seed=0)
    assert len(held) == 2 and sorted(train + held) == list(range(6)) and split_by_image(6, 0.34, 0) == (train, held)
    assert split_by_image(2, 0.05, 0)[1] and split_by_image(2, 0.95, 0)[0]


def test_the_shipped_onnx_reads_back_into_torch_with_the_same_logits():
    meta = json.loads(SHIPPED_MODEL.with_suffix(".json").read_text())
    branchnet_from_onnx(SHIPPED_MODEL, meta["width"], meta["fine_width"])  # it compares the two itself
    with pytest.raises(OnnxSegmenterError, match="BranchNet of width 16"):
        branchnet_from_onnx(SHIPPED_MODEL, 16, meta["fine_width"])


def test_a_fine_tune_changes_the_weights_and_writes_a_bundle_that_segments_a_frame(bundle, dataset):
    manifest = json.loads((bundle / MANIFEST_NAME).read_text())
    assert set(manifest["files"]) >= {"branchnet.onnx", "branchnet.json", "branchnet.pt", "metrics.json"}
    assert manifest["classes"] == ["background", "trunk", "branch"] and manifest["input"]["channels"] == 5
    assert manifest["input"]["frame_sizes"] == [[WIDTH, HEIGHT]]
    meta = json.loads(SHIPPED_MODEL.with_suffix(".json").read_text())
    shipped = branchnet_from_onnx(SHIPPED_MODEL, meta["width"], meta["fine_width"]).state_dict()
    tuned = branchnet_from_onnx(bundle / "branchnet.onnx", meta["width"], meta["fine_width"]).state_dict()
    assert any(not np.allclose(shipped[k].numpy(), tuned[k].numpy()) for k in shipped if k.endswith("weight"))
    metrics = json.loads((bundle / "metrics.json").read_text())
    assert metrics["heldout"]["frames"] == 4 and metrics["training"]["steps"] == 3
    assert set(metrics["heldout"]["before"]) == {"trunk_band_40", "trunk_band_0"}
    tuned_meta = json.loads((bundle / "branchnet.json").read_text())
    assert tuned_meta["init_sha256"] == meta["onnx_sha256"] and len(tuned_meta["finetune"]["heldout_frames"]) == 4
    left, disparity, _, _ = _frame(0)
    masks = make_segmenter(f"learned:{bundle}").segment(left, disparity, GEOMETRY)
    assert masks.labels.shape == (HEIGHT, WIDTH) and masks.source == "learned"
    # the bundle's own out-of-distribution reference, measured on the labelled frames: they read as known
    assert reference_in(tuned_meta) is not None and "12 labelled frames" in reference_in(tuned_meta).domain
    assert masks.ood is not None and not masks.ood.flagged


def test_a_bundle_made_with_int8_runs_its_quantized_copy_and_one_without_says_so(bundle, tmp_path):
    manifest = json.loads((bundle / MANIFEST_NAME).read_text())
    assert {"branchnet_int8.onnx", "branchnet_int8.json"} <= set(manifest["files"])
    int8_meta = json.loads((bundle / "branchnet_int8.json").read_text())
    assert "labelled frames" in int8_meta["quantization"]["frames"] and "confidence_calibrations" in int8_meta
    config = LearnedSegmenterConfig(model=str(bundle), precision="int8")  # a bundle folder may ask for int8
    assert LearnedSegmenter(config).model_path == bundle / "branchnet_int8.onnx"
    left, disparity, _, _ = _frame(0)
    masks = LearnedSegmenter(config).segment(left, disparity, GEOMETRY)
    assert masks.labels.shape == (HEIGHT, WIDTH)
    # the shipped onboard file asks for int8: a bundle without the copy is refused with what to do
    plain = _copy(bundle, tmp_path, "fp32-only")
    for name in ("branchnet_int8.onnx", "branchnet_int8.json"):
        (plain / name).unlink()
    files = {k: v for k, v in manifest["files"].items() if "int8" not in k}
    _edit_manifest(plain, files=files)
    with pytest.raises(OnnxSegmenterError, match="has no int8 copy.*--int8"):
        LearnedSegmenter(LearnedSegmenterConfig(model=str(plain), precision="int8"))
    assert LearnedSegmenter(LearnedSegmenterConfig(model=str(plain))).model_path == plain / "branchnet.onnx"


def _copy(bundle, tmp_path, name="copy"):
    copy = tmp_path / name
    shutil.copytree(bundle, copy)
    return copy


def _edit_manifest(folder, **changes):
    manifest = json.loads((folder / MANIFEST_NAME).read_text())
    for key, value in changes.items():
        manifest[key] = value
    (folder / MANIFEST_NAME).write_text(json.dumps(manifest))


def test_a_bundle_for_another_class_set_or_input_or_with_a_changed_file_is_refused(bundle, tmp_path):
    other_classes = _copy(bundle, tmp_path, "classes")
    _edit_manifest(other_classes, classes=["background", "branch"])
    with pytest.raises(OnnxSegmenterError, match=r"made for the classes \['background', 'branch'\]"):
        bundle_model(other_classes)
    other_input = _copy(bundle, tmp_path, "input")
    _edit_manifest(other_input, input={"channels": 4, "stride": 16})
    with pytest.raises(OnnxSegmenterError, match="made for input.*'channels': 4"):
        make_segmenter(f"learned:{other_input}")
    edited = _copy(bundle, tmp_path, "edited")
    meta = json.loads((edited / "branchnet.json").read_text())
    meta["confidence_calibrations"] = []
    (edited / "branchnet.json").write_text(json.dumps(meta))
    with pytest.raises(OnnxSegmenterError, match="branchnet.json has SHA-256.*truncated or changed"):
        make_segmenter(f"learned:{edited}")
    truncated = _copy(bundle, tmp_path, "truncated")
    data = (truncated / "branchnet.onnx").read_bytes()
    (truncated / "branchnet.onnx").write_bytes(data[: len(data) // 2])
    with pytest.raises(OnnxSegmenterError, match="branchnet.onnx has SHA-256"):
        make_segmenter(f"learned:{truncated}")
    with pytest.raises(OnnxSegmenterError, match="not a model bundle"):
        make_segmenter(f"learned:{tmp_path}")


def test_the_cli_refuses_a_bad_bundle_with_a_message_not_a_traceback(bundle, tmp_path, capsys):
    truncated = _copy(bundle, tmp_path)
    (truncated / "branchnet.onnx").write_bytes((truncated / "branchnet.onnx").read_bytes()[:1000])
    left, disparity, _, _ = _frame(1)
    cv2.imwrite(str(tmp_path / "l.png"), left)
    cv2.imwrite(str(tmp_path / "r.png"), left)
    pair = ["--left", str(tmp_path / "l.png"), "--right", str(tmp_path / "r.png")]
    camera = ["--focal-px", "100", "--baseline-m", "0.06", "--backend", "sgbm"]
    code = main(["estimate", *pair, *camera, "--segmenter", f"learned:{truncated}"])
    err = capsys.readouterr().err
    assert code == 2 and "truncated or changed" in err and "Traceback" not in err


def test_a_bundle_configured_in_the_toml_serves_the_http_api(bundle, tmp_path):
    toml = tmp_path / "serve.toml"
    toml.write_text(f'[segmenter.learned]\nmodel = "{bundle}"\ntrunk_band_px = 0\n')
    config = pipeline_config(load_config(toml))
    estimator = PipelineEstimator(config)
    assert estimator.segmenter().model_path == bundle / "branchnet.onnx"
    left, disparity, _, _ = _frame(2)
    right = np.zeros_like(left)  # the right view shifted by each pixel's disparity
    cols = np.arange(WIDTH)
    for row in range(HEIGHT):
        shifted = np.clip(cols - disparity[row].astype(int), 0, WIDTH - 1)
        right[row, shifted] = left[row]
    files = {
        name: (f"{name}.png", cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))[1].tobytes(), "image/png")
        for name, image in (("left", left), ("right", right))
    }
    with TestClient(create_app(ApiConfig(), estimator)) as client:
        answer = client.post("/estimate", files=files, data={"focal_px": "100", "baseline_m": "0.06", "max_disp": "32"})
    assert answer.status_code == 200, answer.text
    assert answer.json()["schema"] == "branchrange/v1"
    broken = _copy(bundle, tmp_path, "broken")
    _edit_manifest(broken, classes=["sky"])
    bad = replace(
        config, segmenter=replace(config.segmenter, learned=replace(config.segmenter.learned, model=str(broken)))
    )
    with pytest.raises(OnnxSegmenterError, match="made for the classes"):
        PipelineEstimator(bad).segmenter()


def test_held_out_cut_points_are_judged_against_the_labels_and_calibrate_a_readable_table(dataset):
    frame = read_labelled_frames(dataset / "annotations.json", dataset / "images", log=lambda _: None)[0]
    frame.sample["classes"][90:, :10] = IGNORE
    branch_v, branch_u = np.nonzero(frame.sample["classes"] == BRANCH)
    on_branch = (branch_u[0] + 2.0, branch_v[0])  # 2 px off its first pixel: still on it
    judged, found = judged_cut_points(frame, [on_branch, (74.0, 5.0), (3.0, 93.0), (3.0, 40.0)])
    assert judged == [True, False, None, False] and found == {1}  # branch, trunk, ignored, background
    assert labelled_branches(frame) == {1}
    outcomes = [(c, c > 0.5) for c in np.linspace(0.05, 0.95, 40)]
    sure = ConfidenceCalibration((0.0, 1.0), (1.0, 1.0))  # every cut point on a branch within 5 cm
    assert calibration_table(outcomes[:19], 160, 0, sure) is None
    assert calibration_table(outcomes, 160, 0, None) is None  # "on a branch" alone is no confidence to fly on
    table = calibration_table(outcomes, 160, 40, sure)
    (setting,) = calibrations_by_setting({"confidence_calibrations": [table]})
    assert setting == (160, 40, "normal") and table["target_min_confidence"] is not None
    assert "labelled branch" in table["measure"] and "within 5 cm" in table["measure"]
    # on a branch, only 70 % within 5 cm: every confidence falls to 0.7 of "on a branch", and no threshold is
    # ≥ 90 % right any more, so the bundle's cut points need more than any confidence reaches to be targets
    depth = ConfidenceCalibration((0.0, 1.0), (0.7, 0.7))
    shaky = calibration_table(outcomes, 160, 40, depth)
    on_branch = ConfidenceCalibration.from_json_dict(shaky["on_branch"])
    product = ConfidenceCalibration.from_json_dict(shaky)
    for c in (0.1, 0.5, 0.9):
        assert product(c) == pytest.approx(0.7 * on_branch(c), abs=1e-3)
    assert shaky["target_min_confidence"] is None and shaky["share_within_5cm_expected"] == pytest.approx(0.35, 0.01)


def test_the_depth_factor_is_measured_on_cut_points_that_lie_on_a_true_branch(tmp_path):
    from branchrange.learning.calibration import raw_outcomes
    from branchrange.learning.depth_factor import depth_factor

    seeds, setting = (2861, 2864), (640, 0)
    every = [o for group in raw_outcomes(SHIPPED_MODEL, seeds, tmp_path, [setting])[setting].values() for o in group]
    on_branch = raw_outcomes(SHIPPED_MODEL, seeds, tmp_path, [setting], on_branch_only=True)[setting]
    kept = [o for group in on_branch.values() for o in group]
    assert 0 < len(kept) < len(every)  # some cut points of these scenes lie off every branch (trunk, leaves)
    assert np.mean([ok for _, ok in kept]) >= np.mean([ok for _, ok in every])
    lines: list[str] = []
    factor = depth_factor(SHIPPED_MODEL, 3, 0, tmp_path, lines.append, min_cut_points=1)
    assert factor is not None and all(0 < y < 1 for y in factor.calibrated)
    assert "cut points on a branch in synthetic scenes 2861–2863" in lines[0]
    assert depth_factor(SHIPPED_MODEL, 3, 0, tmp_path, lines.append, min_cut_points=len(kept) + 1) is None
    assert "at least" in lines[-1]


def test_a_model_without_a_confidence_calibration_reports_cut_points_but_never_a_target(bundle, tmp_path, caplog):
    uncalibrated = _copy(bundle, tmp_path, "uncalibrated")
    meta_path = uncalibrated / "branchnet.json"
    meta = json.loads(meta_path.read_text())
    meta["confidence_calibrations"] = []
    meta_path.write_text(json.dumps(meta))
    _edit_manifest(uncalibrated, files={**json.loads((uncalibrated / MANIFEST_NAME).read_text())["files"],
                                        "branchnet.json": sha256_of(meta_path)})  # fmt: skip
    segmenter = make_segmenter(f"learned:{uncalibrated}")
    assert "carries no confidence calibration" in caplog.text
    left, disparity, _, _ = _frame(1)
    masks = segmenter.segment(left, disparity, GEOMETRY)
    assert masks.calibration is None and math.isinf(masks.target_min_confidence)
    assert "no confidence calibration" in no_target_reason(0.5, masks)
