"""`onnx:FILE` segmenters: tiny YOLOv8-seg and per-pixel-logit models exported here with torch."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from torch import nn

from branchrange.core.config import SegmenterConfig, StereoConfig
from branchrange.core.cutpoints import CutPointConfig
from branchrange.core.geometry import StereoGeometry
from branchrange.core.masks import DEFAULT_TRUNK_ID
from branchrange.core.pipeline import Pipeline, PipelineConfig
from branchrange.core.segmentation.choose import make_segmenter
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


class TinyYoloSeg(nn.Module):
    """YOLOv8-seg outputs on a fixed 128×128 input (the 128×64 image is letterboxed 32 px down).

    Prototypes `(1, 2, 32, 32)`: darkness of the input at stride 4, and a constant plane, so the
    coefficients (20, −10) give a mask that is exactly the dark pixels of a box. Detections are
    fixed (a buffer): a branch, a weaker duplicate of it (NMS must drop it), a trunk, a leaf
    (class 2, not wanted) and a branch below the score threshold.
    """

    def __init__(self, end_to_end: bool = False) -> None:
        super().__init__()
        pad = 32  # letterbox offset of the image in the input
        rows = []  # x1, y1, x2, y2, class, score
        for (x0, x1, y0, y1), cls, score in (
            (BRANCH_BAR, 0, 0.9),
            (BRANCH_BAR, 0, 0.8),
            (TRUNK_BAR, 1, 0.7),
            (LEAF_BAR, 2, 0.95),
            (STRAY_BLOB, 0, 0.1),
        ):
            rows.append((x0 - 2, y0 - 2 + pad, x1 + 2, y1 + 2 + pad, cls, score))
        if end_to_end:
            table = [[x1, y1, x2, y2, s, c, 20.0, -10.0] for x1, y1, x2, y2, c, s in rows if c != 0 or s != 0.8]
            self.register_buffer("detections", torch.tensor([table], dtype=torch.float32))
        else:
            columns = []
            for x1, y1, x2, y2, c, s in rows:
                scores = [0.01, 0.01, 0.01]
                scores[c] = s
                columns.append([(x1 + x2) / 2, (y1 + y2) / 2, x2 - x1, y2 - y1, *scores, 20.0, -10.0])
            self.register_buffer("detections", torch.tensor(columns, dtype=torch.float32).T[None])

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        darkness = 1.0 - nn.functional.avg_pool2d(image.mean(dim=1, keepdim=True), 4)
        prototypes = torch.cat([darkness, torch.ones_like(darkness)], dim=1)
        return self.detections + 0.0 * image.mean(), prototypes


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
    from branchrange.core.config import ConfigError, load_config, pipeline_config

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
    from branchrange.core.config import ApiConfig

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
