"""A cap on branch instances: a mask of thousands of ids is refused with its count and the cap —
by `estimate_cut_points`, through the configuration, and as an HTTP 422 from POST /estimate."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from api_scene import BASELINE_M, FOCAL_PX, bar_scene
from branch_geometry_fixtures import GEOMETRY
from fastapi.testclient import TestClient

from api import create_app
from api.estimator import PipelineEstimator
from branchrange.config.loader import config_from_dict, pipeline_config
from branchrange.config.sections import ApiConfig
from branchrange.core.cutpoints import CutPointConfig, CutPointConfigError, estimate_cut_points
from branchrange.core.masks import MaskError, masks_from_array
from branchrange.core.settings_check import ConfigError


def runs_of_ids(height: int, width: int, count: int, run_px: int = 5) -> np.ndarray:
    """An `H×W` label image whose first `count·run_px` pixels hold ids 1..count in runs of `run_px`."""
    ids = np.arange(height * width) // run_px + 1
    return np.where(ids <= count, ids, 0).reshape(height, width).astype(np.int32)


def test_65000_ids_are_refused_naming_the_count_and_the_cap():
    masks = masks_from_array(runs_of_ids(512, 640, 65000), kind="instance", source="many.png")
    with pytest.raises(
        MaskError,
        match=r"many\.png: the mask holds 65000 branch instances, more than "
        r"cutpoints\.max_instances = 256",
    ):
        estimate_cut_points(masks, np.full((512, 640), 20.0, np.float32), GEOMETRY)


def test_up_to_the_cap_every_instance_is_estimated_or_dropped_with_a_reason():
    masks = masks_from_array(runs_of_ids(240, 320, 300, run_px=4), kind="instance")
    disparity = np.full((240, 320), 20.0, np.float32)
    with pytest.raises(MaskError, match="300 branch instances"):
        estimate_cut_points(masks, disparity, GEOMETRY)
    result = estimate_cut_points(masks, disparity, GEOMETRY, CutPointConfig(max_instances=300))
    assert len(result.dropped) == 300 and all("fewer than" in d.reason for d in result.dropped)


def test_the_cap_is_a_setting_checked_like_the_others():
    with pytest.raises(CutPointConfigError, match=r"cutpoints\.max_instances = 0"):
        CutPointConfig(max_instances=0)
    with pytest.raises(ConfigError, match=r"cutpoints\.max_instances = 0: expected ≥ 1 instance"):
        config_from_dict({"cutpoints": {"max_instances": 0}})
    cfg = config_from_dict({"cutpoints": {"max_instances": 32}})
    assert pipeline_config(cfg).cutpoints.max_instances == 32


def test_http_estimate_answers_422_with_the_count_and_the_cap():
    scene = bar_scene()
    many = runs_of_ids(*scene.mask.shape, 1000).astype(np.uint16)
    files = {
        "left": ("l.png", scene.png("left"), "image/png"),
        "right": ("r.png", scene.png("right"), "image/png"),
        "mask": ("m.png", cv2.imencode(".png", many)[1].tobytes(), "image/png"),
    }
    data = {"focal_px": str(FOCAL_PX), "baseline_m": str(BASELINE_M), "max_disp": "64"}
    with TestClient(create_app(ApiConfig(max_pixels=400 * 300, max_upload_mb=1.0), PipelineEstimator())) as client:
        r = client.post("/estimate", files=files, data=data)
    assert r.status_code == 422, r.text
    assert "1000 branch instances, more than cutpoints.max_instances = 256" in r.text
