"""Input sanity: row misalignment of a pair (warn / refuse) and Middlebury `doffs` in depth."""

from __future__ import annotations

import json
import logging

import cv2
import numpy as np
import pytest
from api_scene import BAR_DEPTH_M, BAR_DISPARITY, BASELINE_M, FOCAL_PX, bar_scene

from branchrange.cli import main
from branchrange.core.pair_check import REFUSE_DY_PX, PairRefusedError, check_rectification
from camera import load_calibration
from camera.calibration import CalibrationError
from camera.load import detect_format

DOFFS_PX = 8  # the bar's measured disparity becomes 32 − 8 = 24 px


@pytest.fixture(scope="module")
def scene():
    return bar_scene()


def _write_pair(folder, left, right, mask=None):
    for name, image in (("l.png", left), ("r.png", right)):
        cv2.imwrite(str(folder / name), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    if mask is not None:
        cv2.imwrite(str(folder / "m.png"), mask)
    return [str(folder / "l.png"), str(folder / "r.png")]


@pytest.mark.parametrize("shift, status", [(0, "ok"), (3, "warning"), (20, "refused")])
def test_vertical_shift_is_measured_and_judged(scene, shift, status, caplog):
    check = check_rectification(scene.left, np.roll(scene.right, shift, axis=0))
    assert check.status == status and check.matches >= 20
    assert check.median_dy_px == pytest.approx(shift, abs=0.5)
    with caplog.at_level(logging.DEBUG, logger="pair"):
        check.log(logging.getLogger("pair"))
    assert caplog.records[-1].levelno == (logging.DEBUG if status == "ok" else logging.WARNING)
    if status == "refused":
        with pytest.raises(PairRefusedError, match=f"{REFUSE_DY_PX:g} px limit.*rectify the pair"):
            check.raise_if_refused()


def test_textureless_pair_gives_no_verdict():
    flat = np.full((120, 160, 3), 128, np.uint8)
    check = check_rectification(flat, flat)
    assert check.status == "unknown" and check.median_dy_px is None


def test_estimate_warns_on_a_shifted_pair_and_refuses_a_20_px_one(scene, tmp_path, capsys):
    camera = ["--focal-px", str(FOCAL_PX), "--baseline-m", str(BASELINE_M), "--max-disp", "64"]
    left, right = _write_pair(tmp_path, scene.left, np.roll(scene.right, 3, axis=0))
    assert main(["estimate", "--left", left, "--right", right, *camera, "--json", str(tmp_path / "r.json")]) == 0
    assert "warning: rows of the pair are 3.0 px apart" in capsys.readouterr().err
    assert json.loads((tmp_path / "r.json").read_text())["pair_check"]["status"] == "warning"
    left, right = _write_pair(tmp_path, scene.left, np.roll(scene.right, 20, axis=0))
    assert main(["estimate", "--left", left, "--right", right, *camera]) == 2
    assert "20.0 px apart" in capsys.readouterr().err


def test_api_reports_the_check_and_refuses_with_422(scene):
    from fastapi.testclient import TestClient

    from api import create_app
    from api.estimator import PipelineEstimator
    from branchrange.config.sections import ApiConfig

    data = {"focal_px": str(FOCAL_PX), "baseline_m": str(BASELINE_M), "max_disp": "64"}
    with TestClient(create_app(ApiConfig(), PipelineEstimator())) as client:
        replies = {}
        for shift in (3, 20):
            right = cv2.imencode(".png", np.roll(scene.right, shift, axis=0))[1].tobytes()
            files = {
                "left": ("l.png", scene.png("left"), "image/png"),
                "right": ("r.png", right, "image/png"),
                "mask": ("m.png", scene.png("mask"), "image/png"),
            }
            replies[shift] = client.post("/estimate", files=files, data=data)
    assert replies[3].status_code == 200 and replies[3].json()["pair_check"]["status"] == "warning"
    assert replies[20].status_code == 422 and "8 px limit" in replies[20].text


def _middlebury_calib(path, doffs: float, width=320, height=256) -> str:
    cx, cy = (width - 1) / 2, (height - 1) / 2
    path.write_text(
        f"cam0=[{FOCAL_PX} 0 {cx}; 0 {FOCAL_PX} {cy}; 0 0 1]\n"
        f"cam1=[{FOCAL_PX} 0 {cx + doffs}; 0 {FOCAL_PX} {cy}; 0 0 1]\n"
        f"doffs={doffs}\nbaseline={BASELINE_M * 1000}\nwidth={width}\nheight={height}\n"
        "ndisp=64\nisint=0\nvmin=10\nvmax=40\ndyavg=0\ndymax=0\n"
    )
    return str(path)


def test_middlebury_calib_with_doffs_gives_the_true_depth(scene, tmp_path):
    """The right view moved DOFFS_PX right (its principal point sits doffs px right): Z = f·B/(d + doffs)."""
    calib = _middlebury_calib(tmp_path / "calib.txt", DOFFS_PX)
    assert detect_format(calib) == "middlebury"
    calibration = load_calibration(calib)
    assert calibration.baseline_m == pytest.approx(BASELINE_M) and calibration.is_rectified
    right = np.roll(scene.right, DOFFS_PX, axis=1)
    pair = _write_pair(tmp_path, scene.left, right, scene.mask)
    common = ["estimate", "--left", pair[0], "--right", pair[1], "--mask", str(tmp_path / "m.png"), "--max-disp", "64"]
    depths = {}
    for name, camera in (
        ("calib", ["--calib", calib]),
        ("doffs", ["--focal-px", str(FOCAL_PX), "--baseline-m", str(BASELINE_M), "--doffs", str(DOFFS_PX)]),
        ("ignored", ["--focal-px", str(FOCAL_PX), "--baseline-m", str(BASELINE_M)]),
    ):
        out = tmp_path / f"{name}.json"
        assert main(common + camera + ["--json", str(out)]) == 0
        (branch,) = json.loads(out.read_text())["branches"]
        depths[name] = branch["cut_point_m"][2]
    assert depths["calib"] == pytest.approx(BAR_DEPTH_M, abs=0.03)
    assert depths["doffs"] == pytest.approx(BAR_DEPTH_M, abs=0.03)
    no_offset = FOCAL_PX * BASELINE_M / (BAR_DISPARITY - DOFFS_PX)  # what ignoring doffs gives: 1.67 m
    assert depths["ignored"] == pytest.approx(no_offset, abs=0.05)


def test_middlebury_calib_errors_name_the_key(scene, tmp_path, capsys):
    path = tmp_path / "calib.txt"
    _middlebury_calib(path, 10.0)
    pair = _write_pair(tmp_path, scene.left, scene.right)
    assert main(["estimate", "--left", pair[0], "--right", pair[1], "--calib", str(path), "--doffs", "3"]) == 2
    assert "--doffs goes with --focal-px" in capsys.readouterr().err
    path.write_text(path.read_text().replace("doffs=10.0", "doffs=12.5"))
    with pytest.raises(CalibrationError, match="doffs.*cam1 cx − cam0 cx is 10.0"):
        load_calibration(path)
    path.write_text("cam0=[1 0 0; 0 1 0]\ncam1=[1 0 0; 0 1 0; 0 0 1]\nbaseline=1\nwidth=2\nheight=2\n")
    with pytest.raises(CalibrationError, match="cam0.*3×3 matrix"):
        load_calibration(path)
