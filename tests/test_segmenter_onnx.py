"""`onnx:FILE` segmenters: tiny YOLOv8-seg and per-pixel-logit models exported here with torch."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from torch import nn

from branchrange.core.cutpoints import CutPointConfig
from branchrange.core.geometry import StereoGeometry
from branchrange.core.masks import DEFAULT_TRUNK_ID
from branchrange.core.pipeline import Pipeline, PipelineConfig, StereoConfig
from branchrange.core.segmentation.choose import SegmenterConfig, make_segmenter
from branchrange.core.segmentation.onnx_model import OnnxSegmenter, OnnxSegmenterConfig, OnnxSegmenterError

#: torch's TorchScript exporter is what builds these tiny graphs; its deprecation notice is not ours
pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
pytest.importorskip("onnxruntime", reason="onnxruntime (a dependency of branchrange) is not installed")

GEOMETRY = StereoGeometry.centred(100.0, 0.1, 128, 64)
BRIGHT, DARK = 230, 20
#: image boxes (x0, x1, y0, y1), inclusive pixels of the 128×64 test image
BRANCH_BAR, TRUNK_BAR, LEAF_BAR, STRAY_BLOB = (12, 38, 12, 18), (84, 96, 0, 63), (54, 66, 20, 40), (110, 120, 40, 50)


def _box_mask(box: tuple[int, int, int, int], shape=(64, 128)) -> np.ndarray:
    x0, x1, y0, y1 = box
    mask = np.zeros(shape, dtype=bool)
    mask[y0 : y1 + 1, x0 : x1 + 1] = True
    return mask


def _scene() -> np.ndarray:
    """128×64 RGB: bright, with dark bars (branch, trunk, leaf) and a dark blob no detection covers."""
    image = np.full((64, 128, 3), BRIGHT, dtype=np.uint8)
    for box in (BRANCH_BAR, TRUNK_BAR, LEAF_BAR, STRAY_BLOB):
        image[_box_mask(box)] = DARK
    return image


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max(1, (a | b).sum()))


#: (box, class, score) of `TinyYoloSeg`'s detections: a branch, a weaker duplicate of it (NMS must drop
#: it), a trunk, a leaf (class 2, not wanted) and a branch below the score threshold
SCENE_DETECTIONS = (
    (BRANCH_BAR, 0, 0.9),
    (BRANCH_BAR, 0, 0.8),
    (TRUNK_BAR, 1, 0.7),
    (LEAF_BAR, 2, 0.95),
    (STRAY_BLOB, 0, 0.1),
)


class TinyYoloSeg(nn.Module):
    """YOLOv8-seg outputs on a fixed 128×128 input (the 128×64 image is letterboxed 32 px down).

    Prototypes `(1, 2, 32, 32)`: darkness of the input at stride 4, and a constant plane, so the
    coefficients (20, −10) give a mask that is exactly the dark pixels of a box. Detections are
    fixed (a buffer): `detections` ((x0, x1, y0, y1) image box, class, score), each box grown by 2 px;
    the end-to-end form leaves out what NMS would drop (the second of two equal boxes).
    """

    def __init__(self, detections=SCENE_DETECTIONS, end_to_end: bool = False) -> None:
        super().__init__()
        pad = 32  # letterbox offset of the image in the input
        rows = [(x0 - 2, y0 - 2 + pad, x1 + 2, y1 + 2 + pad, c, s) for (x0, x1, y0, y1), c, s in detections]
        if end_to_end:
            kept = [row for i, row in enumerate(rows) if row[:5] not in [r[:5] for r in rows[:i]]]
            table = [[x1, y1, x2, y2, s, c, 20.0, -10.0] for x1, y1, x2, y2, c, s in kept]
            self.register_buffer("detections", torch.tensor([table], dtype=torch.float32))
        else:
            columns = []
            for x1, y1, x2, y2, c, s in rows:
                scores = [0.01, 0.01, 0.01]
                scores[c] = s
                columns.append([(x1 + x2) / 2, (y1 + y2) / 2, x2 - x1, y2 - y1, *scores, 20.0, -10.0])
            self.register_buffer("detections", torch.tensor(columns, dtype=torch.float32).T[None])

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.detections + 0.0 * image.mean(), _dark_prototypes(image)


def _dark_prototypes(image: torch.Tensor) -> torch.Tensor:
    """`(1, 2, H/4, W/4)`: the input's darkness at stride 4 and a constant plane (see `TinyYoloSeg`)."""
    darkness = 1.0 - nn.functional.avg_pool2d(image.mean(dim=1, keepdim=True), 4)
    return torch.cat([darkness, torch.ones_like(darkness)], dim=1)


#: two branch boxes of one class overlapping with IoU 0.6 once grown by 2 px (40 px wide, 10 px apart)
OVERLAP_A, OVERLAP_B = (10, 46, 20, 40), (20, 56, 20, 40)


def _overlap_scene() -> np.ndarray:
    """128×64 RGB: bright, dark where either overlapping box lies."""
    image = np.full((64, 128, 3), BRIGHT, dtype=np.uint8)
    image[_box_mask(OVERLAP_A) | _box_mask(OVERLAP_B)] = DARK
    return image


#: 1920×1080 frame of the dynamic-shape test: the dark bar a detection covers and one no detection covers
FRAME_BAR, DECOY_BAR = (600, 1199, 300, 359), (100, 699, 800, 859)


class DynamicYoloSeg(nn.Module):
    """YOLOv8-seg outputs for any input size (dynamic axes), one class, prototypes as `TinyYoloSeg`'s.

    Its one detection is `FRAME_BAR` where a 1920×1080 frame lands in a 640×384 input (scale 1/3,
    12 px of padding above): x 200..400, y 112..132, grown by 4 px — so its mask is that bar only
    when the frame is letterboxed as Ultralytics' predictor does for a dynamic-shape model.
    """

    def __init__(self) -> None:
        super().__init__()
        x1, y1, x2, y2 = 196.0, 108.0, 404.0, 136.0
        column = [(x1 + x2) / 2, (y1 + y2) / 2, x2 - x1, y2 - y1, 0.9, 20.0, -10.0]
        self.register_buffer("detections", torch.tensor([column], dtype=torch.float32).T[None])

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.detections + 0.0 * image.mean(), _dark_prototypes(image)


def _frame_1080p() -> np.ndarray:
    frame = np.full((1080, 1920, 3), BRIGHT, dtype=np.uint8)
    for box in (FRAME_BAR, DECOY_BAR):
        frame[_box_mask(box, (1080, 1920))] = DARK
    return frame


class RecordingSession:
    """An onnxruntime session that records the shape of every input it is run on."""

    def __init__(self, session) -> None:
        self.session, self.shapes = session, []

    def run(self, names, feeds):
        self.shapes += [tuple(feed.shape) for feed in feeds.values()]
        return self.session.run(names, feeds)


def _with_metadata(source: str, path, **entries: str) -> str:
    """A copy of the model `source` at `path` with `entries` in its metadata_props (as Ultralytics writes)."""
    import onnx

    model = onnx.load(source)
    for key, value in entries.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.save(model, str(path))
    return str(path)


class TinyLogits(nn.Module):
    """Per-pixel logits `(1, 3, H/2, W/2)` for any input size: 0 background, 1 dark = branch, 2 red = trunk."""

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        small = nn.functional.avg_pool2d(image, 2)
        r, g, b = small[:, 0:1], small[:, 1:2], small[:, 2:3]
        dark = 1.0 - small.mean(dim=1, keepdim=True)
        red = r - (g + b) / 2
        return torch.cat([torch.zeros_like(dark), 20 * (dark - 0.5) - 20 * red, 20 * (red - 0.3)], dim=1)


def _export(model: nn.Module, path, height: int, width: int, dynamic: bool) -> str:
    axes = {"image": {2: "h", 3: "w"}} if dynamic else None
    torch.onnx.export(
        model.eval(),
        torch.zeros(1, 3, height, width),
        str(path),
        input_names=["image"],
        dynamic_axes=axes,
        dynamo=False,
        opset_version=17,
    )
    return str(path)


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> dict[str, str]:
    folder = tmp_path_factory.mktemp("onnx_seg")
    return {
        "yolo": _export(TinyYoloSeg(), folder / "yolo.onnx", 128, 128, False),
        "e2e": _export(TinyYoloSeg(end_to_end=True), folder / "e2e.onnx", 128, 128, False),
        "logits": _export(TinyLogits(), folder / "logits.onnx", 64, 64, True),
        "overlap": _export(
            TinyYoloSeg(((OVERLAP_A, 0, 0.9), (OVERLAP_B, 0, 0.8))), folder / "overlap.onnx", 128, 128, False
        ),
        "dynamic": _export(DynamicYoloSeg(), folder / "dynamic.onnx", 384, 640, True),
    }


@pytest.mark.parametrize("layout", ["yolo", "e2e"])
def test_yolo_seg_outputs_give_the_branch_and_trunk_masks_only(models, layout):
    segmenter = OnnxSegmenter(models[layout], OnnxSegmenterConfig(branch_classes=(0,), trunk_classes=(1,)))
    masks = segmenter.segment(_scene(), np.zeros((64, 128), np.float32), GEOMETRY)
    assert segmenter.layout == "yolo" and masks.source == f"onnx:{layout}.onnx"
    assert masks.branch_ids() == [1]  # the duplicate is suppressed, leaf and low score dropped
    assert _iou(masks.branch(1), _box_mask(BRANCH_BAR)) > 0.8
    assert _iou(masks.trunk(), _box_mask(TRUNK_BAR)) > 0.8
    assert not masks.labels[_box_mask(LEAF_BAR) | _box_mask(STRAY_BLOB)].any()


def test_class_ids_are_configurable(models):
    """Leaves as the branch class, no trunk class: only the leaf bar is an instance."""
    segmenter = OnnxSegmenter(models["yolo"], OnnxSegmenterConfig(branch_classes=(2,)))
    masks = segmenter.segment(_scene(), np.zeros((64, 128), np.float32), GEOMETRY)
    assert masks.branch_ids() == [1] and masks.trunk() is None
    assert _iou(masks.branch(1), _box_mask(LEAF_BAR)) > 0.8


def test_logits_model_splits_branch_pixels_into_instances_and_finds_the_trunk(models):
    image = np.full((64, 128, 3), BRIGHT, dtype=np.uint8)
    image[_box_mask(BRANCH_BAR)] = DARK
    image[_box_mask(LEAF_BAR)] = DARK  # a second, separate dark bar
    image[_box_mask(TRUNK_BAR)] = (220, 30, 30)
    segmenter = make_segmenter(
        f"onnx:{models['logits']}", onnx=OnnxSegmenterConfig(branch_classes=(1,), trunk_classes=(2,))
    )
    masks = segmenter.segment(image, np.zeros((64, 128), np.float32), GEOMETRY)
    assert segmenter.layout == "logits" and len(masks.branch_ids()) == 2
    found = sorted(max(_iou(masks.branch(i), _box_mask(b)) for i in masks.branch_ids()) for b in (BRANCH_BAR, LEAF_BAR))
    assert found[0] > 0.7
    assert _iou(masks.trunk(), _box_mask(TRUNK_BAR)) > 0.7 and masks.trunk_id == DEFAULT_TRUNK_ID


def test_pipeline_uses_the_named_onnx_segmenter(models):
    config = PipelineConfig(
        cutpoints=CutPointConfig(tracking=False),
        segmenter=SegmenterConfig(model=f"onnx:{models['yolo']}", branch_classes=(0,), trunk_classes=(1,)),
    )
    pipeline = Pipeline(config, focal_px=100.0, baseline_m=0.1)
    disparity = np.full((64, 128), 10.0, np.float32)
    result = pipeline.process_disparity(_scene(), disparity)
    assert result.masks.to_json_dict() == {"source": "onnx:yolo.onnx", "instances": 1, "trunk": True}


def test_bad_names_models_and_settings_are_clear_errors(models, tmp_path):
    with pytest.raises(
        OnnxSegmenterError, match="'onnx:': expected 'learned', 'geometric', 'structure' or 'onnx:FILE'"
    ):
        make_segmenter("onnx:")
    with pytest.raises(OnnxSegmenterError, match="no such model file"):
        make_segmenter(f"onnx:{tmp_path / 'missing.onnx'}")
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    with pytest.raises(OnnxSegmenterError, match="not a model onnxruntime can load"):
        make_segmenter(f"onnx:{junk}")
    flat = _export(nn.Flatten(), tmp_path / "flat.onnx", 8, 8, False)  # one (1, 192) output
    with pytest.raises(OnnxSegmenterError, match="neither YOLOv8-seg"):
        make_segmenter(f"onnx:{flat}")
    with pytest.raises(OnnxSegmenterError, match="trunk_classes .*not also branch classes"):
        OnnxSegmenterConfig(branch_classes=(0, 1), trunk_classes=(1,))


def test_config_section_reaches_the_pipeline(models, tmp_path):
    from branchrange.config.loader import load_config, pipeline_config
    from branchrange.core.settings_check import ConfigError

    path = tmp_path / "c.toml"
    path.write_text(f'[segmenter]\nmodel = "onnx:{models["yolo"]}"\nbranch_classes = [0]\ntrunk_classes = [1]\n')
    config = pipeline_config(load_config(path))
    assert config.segmenter.model.endswith("yolo.onnx") and config.segmenter.trunk_classes == (1,)
    path.write_text('[segmenter]\nmodel = "maskrcnn"\n')
    with pytest.raises(ConfigError, match="'maskrcnn': expected 'learned', 'geometric', 'structure' or 'onnx:FILE'"):
        load_config(path)
    path.write_text("[segmenter]\nbranch_classes = 3\n")
    with pytest.raises(ConfigError, match="segmenter.branch_classes"):
        load_config(path)


def test_api_segmenter_field_picks_the_configured_model_or_the_geometric_one(models):
    import cv2
    from fastapi.testclient import TestClient

    from api import create_app
    from api.estimator import PipelineEstimator
    from branchrange.config.sections import ApiConfig

    config = PipelineConfig(
        stereo=StereoConfig(mode="full", max_disp=64),
        segmenter=SegmenterConfig(model=f"onnx:{models['yolo']}", branch_classes=(0,), trunk_classes=(1,)),
    )
    left = _scene()
    right = np.roll(left, -8, axis=1)  # a rectified pair 8 px of disparity apart
    png = [cv2.imencode(".png", image)[1].tobytes() for image in (left, right)]
    files = {"left": ("l.png", png[0], "image/png"), "right": ("r.png", png[1], "image/png")}
    with TestClient(create_app(ApiConfig(), PipelineEstimator(config))) as client:
        sources = {}
        for choice in ("configured", "geometric"):
            r = client.post(
                "/estimate", files=files, data={"focal_px": "100", "baseline_m": "0.1", "segmenter": choice}
            )
            assert r.status_code == 200, r.text
            sources[choice] = r.json()["masks"]["source"]
        bad = client.post("/estimate", files=files, data={"focal_px": "100", "baseline_m": "0.1", "segmenter": "yolo"})
    assert sources == {"configured": "onnx:yolo.onnx", "geometric": "geometric"}
    assert bad.status_code == 422 and "configured" in bad.text


def test_estimate_command_takes_an_onnx_segmenter_and_its_class_ids(models, tmp_path, capsys):
    import cv2

    from branchrange.cli import main

    left = _scene()
    for name, image in (("l.png", left), ("r.png", np.roll(left, -8, axis=1))):
        cv2.imwrite(str(tmp_path / name), image)
    common = [
        "estimate",
        "--left",
        str(tmp_path / "l.png"),
        "--right",
        str(tmp_path / "r.png"),
        "--focal-px",
        "100",
        "--baseline-m",
        "0.1",
        "--max-disp",
        "64",
        "--json",
        str(tmp_path / "r.json"),
    ]
    assert main(common + ["--segmenter", f"onnx:{models['yolo']}", "--trunk-classes", "1"]) == 0
    assert json.loads((tmp_path / "r.json").read_text())["masks"]["source"] == "onnx:yolo.onnx"
    assert main(common + ["--segmenter", f"onnx:{models['yolo']}", "--trunk-classes", "0"]) == 2
    assert "trunk_classes" in capsys.readouterr().err


def test_thresholds_default_to_ultralytics_predict_conf_and_iou():
    assert (OnnxSegmenterConfig().score_threshold, OnnxSegmenterConfig().nms_iou) == (0.25, 0.7)


@pytest.mark.parametrize(
    "settings, instances",
    [({}, 2), ({"nms_iou": 0.7}, 2), ({"nms_iou": 0.5}, 1), ({"score_threshold": 0.85}, 1)],
    ids=["defaults", "iou-0.7", "iou-0.5", "score-0.85"],
)
def test_nms_keeps_boxes_overlapping_less_than_nms_iou_and_scores_from_the_threshold(models, settings, instances):
    """Boxes of IoU 0.6: both kept at 0.7 (the default), the weaker dropped at 0.5 or below its score."""
    segmenter = OnnxSegmenter(models["overlap"], OnnxSegmenterConfig(**settings))
    masks = segmenter.segment(_overlap_scene(), np.zeros((64, 128), np.float32), GEOMETRY)
    assert len(masks.branch_ids()) == instances
    assert _iou(masks.branch(1), _box_mask(OVERLAP_A)) > 0.8  # the stronger box is always the first
    if instances == 2:
        assert (masks.labels == 2).sum() >= 100  # the other's pixels beyond the first's box


def test_dynamic_shape_model_runs_a_1080p_frame_at_640_and_maps_its_masks_to_the_frame(models):
    segmenter = OnnxSegmenter(models["dynamic"])
    segmenter.session = recorder = RecordingSession(segmenter.session)
    masks = segmenter.segment(_frame_1080p(), np.zeros((1080, 1920), np.float32), GEOMETRY)
    assert recorder.shapes == [(1, 3, 384, 640)]  # 640×360 and 12 px above and below, not 1920×1088
    assert masks.labels.shape == (1080, 1920) and masks.branch_ids() == [1]
    branch, truth = masks.branch(1), _box_mask(FRAME_BAR, (1080, 1920))
    assert _iou(branch, truth) > 0.98
    rows, cols = np.flatnonzero(branch.any(axis=1)), np.flatnonzero(branch.any(axis=0))
    assert (
        abs(rows[0] - 300) <= 2 and abs(rows[-1] - 359) <= 2 and abs(cols[0] - 600) <= 2 and abs(cols[-1] - 1199) <= 2
    )
    assert not branch[_box_mask(DECOY_BAR, (1080, 1920))].any()


@pytest.mark.parametrize(
    "imgsz, input_size, shape",
    [
        (None, 0, (384, 640)),
        ("640", 0, (384, 640)),
        ("[320, 320]", 0, (192, 320)),
        ("[320, 320]", 960, (544, 960)),
        (None, 650, (384, 672)),
    ],
    ids=["default-640", "metadata-640", "metadata-320", "setting-wins", "rounded-to-stride"],
)
def test_dynamic_input_size_is_the_setting_else_the_export_size_in_the_metadata(
    models, tmp_path, imgsz, input_size, shape
):
    path = models["dynamic"] if imgsz is None else _with_metadata(models["dynamic"], tmp_path / "m.onnx", imgsz=imgsz)
    segmenter = OnnxSegmenter(path, OnnxSegmenterConfig(input_size=input_size))
    segmenter.session = recorder = RecordingSession(segmenter.session)
    segmenter.segment(_frame_1080p(), np.zeros((1080, 1920), np.float32), GEOMETRY)
    assert recorder.shapes == [(1, 3, *shape)]


def test_bad_export_size_and_input_size_are_clear_errors(models, tmp_path):
    for imgsz in ("[0, 640]", "big", "[1, 2, 3]"):
        path = _with_metadata(models["dynamic"], tmp_path / "m.onnx", imgsz=imgsz)
        with pytest.raises(OnnxSegmenterError, match=r"metadata imgsz = .* set segmenter.input_size"):
            OnnxSegmenter(path)
    with pytest.raises(OnnxSegmenterError, match=r"segmenter.input_size = 16: expected 0 .* or 32..8192 px"):
        OnnxSegmenterConfig(input_size=16)
    with pytest.raises(OnnxSegmenterError, match=r"segmenter.nms_iou = 0: expected an IoU in \(0, 1\]"):
        OnnxSegmenterConfig(nms_iou=0)


def test_estimate_command_passes_the_thresholds_to_the_onnx_segmenter(models, tmp_path, capsys):
    import cv2

    from branchrange.cli import main

    left = _overlap_scene()
    for name, image in (("l.png", left), ("r.png", np.roll(left, -8, axis=1))):
        cv2.imwrite(str(tmp_path / name), image)
    common = ["estimate", "--left", str(tmp_path / "l.png"), "--right", str(tmp_path / "r.png")]
    common += ["--focal-px", "100", "--baseline-m", "0.1", "--max-disp", "64", "--json", str(tmp_path / "r.json")]
    common += ["--segmenter", f"onnx:{models['overlap']}"]
    found = {}
    for flags in ([], ["--nms-iou", "0.5"], ["--score-threshold", "0.85"]):
        assert main(common + flags) == 0
        found[" ".join(flags)] = json.loads((tmp_path / "r.json").read_text())["masks"]["instances"]
    assert found == {"": 2, "--nms-iou 0.5": 1, "--score-threshold 0.85": 1}
    capsys.readouterr()
    assert main(common + ["--nms-iou", "1.5"]) == 2
    assert "segmenter.nms_iou = 1.5: expected an IoU in (0, 1]" in capsys.readouterr().err
