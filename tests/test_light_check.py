"""Measuring a frame's light: brightness and sensor noise, and the class a frame's confidences are read in."""

from __future__ import annotations

import numpy as np
import pytest

from branchrange.core.light_check import NOISY_ABOVE, light_class, measure_light, noise_sigma


def lit(level: float, noise: float, seed: int = 0, size: tuple[int, int] = (180, 320)) -> np.ndarray:
    """An RGB frame: a smooth ramp around `level` grey with Gaussian noise σ `noise` (grey levels)."""
    rng = np.random.default_rng(seed)
    ramp = level + np.linspace(-15, 15, size[1])[None, :] + np.linspace(-10, 10, size[0])[:, None]
    grey = ramp + rng.normal(0.0, noise, size)
    return np.repeat(np.clip(np.rint(grey), 0, 255).astype(np.uint8)[..., None], 3, axis=2)


@pytest.mark.parametrize("sigma", [1.0, 2.5, 4.0, 6.0])
def test_the_noise_estimate_reads_the_sensor_noise_and_not_a_smooth_gradient(sigma):
    grey = lit(110, sigma)[..., 0]
    # the flattest blocks' low percentile reads a little under σ; a plane or ramp adds nothing
    assert noise_sigma(grey) == pytest.approx(sigma, rel=0.2)
    assert noise_sigma(lit(110, 0.0)[..., 0]) < 0.35  # rounding to whole grey levels only


def test_texture_does_not_read_as_noise_where_flat_blocks_remain():
    frame = lit(110, 1.0)
    rng = np.random.default_rng(1)
    frame[:, :160] = rng.integers(40, 200, size=(180, 160, 1))  # half the frame wholly textured (leaves)
    assert measure_light(frame).noise_grey < 1.3 and measure_light(frame).light == "normal"


def test_each_light_is_classed_by_its_median_grey_and_noise():
    assert measure_light(lit(105, 1.0)).light == "normal"
    dusk = measure_light(lit(32, 1.5))
    assert dusk.light == "dark" and dusk.median_grey == pytest.approx(32, abs=1)
    assert measure_light(lit(190, 1.0)).light == "bright"
    high_gain = measure_light(lit(105, 6.0))
    assert high_gain.light == "noisy" and high_gain.noise_grey > NOISY_ABOVE
    assert light_class(30, 8.0) == "dark"  # dark first: at dusk the noise is what is left of the signal


def test_clipped_and_black_blocks_are_not_taken_for_flat_ones():
    frame = lit(105, 5.0)
    frame[:90] = 255  # an overexposed sky: flat, but its noise is clipped away
    frame[90:110] = 0
    assert measure_light(frame).noise_grey == pytest.approx(5.0, rel=0.2)
    assert measure_light(np.full((64, 64, 3), 255, np.uint8)).noise_grey == 0.0
    assert noise_sigma(np.zeros((8, 8), np.uint8)) == 0.0  # smaller than a block


def test_the_message_says_what_was_measured_and_what_it_means():
    assert measure_light(lit(105, 1.0)).message.startswith("light normal (median grey 105, noise σ")
    dark = measure_light(lit(30, 1.0)).message
    assert "light dark (median grey 30" in dark and "calibration measured in dark light" in dark


def test_a_frame_that_is_not_an_8_bit_image_is_refused():
    with pytest.raises(ValueError, match="uint8 H×W or H×W×3 image, got float32"):
        measure_light(np.zeros((10, 10, 3), np.float32))


def test_estimate_and_the_api_report_the_light_and_warn_out_of_normal_light(tmp_path, capsys):
    import json

    import cv2
    from api_scene import BASELINE_M, FOCAL_PX, bar_scene
    from fastapi.testclient import TestClient

    from api import create_app
    from api.estimator import PipelineEstimator
    from branchrange.cli import main
    from branchrange.config.sections import ApiConfig

    scene = bar_scene()
    dusk = {side: (getattr(scene, side) * 0.3).astype(np.uint8) for side in ("left", "right")}
    paths = []
    for side in ("left", "right"):
        paths.append(tmp_path / f"{side}.png")
        cv2.imwrite(str(paths[-1]), cv2.cvtColor(dusk[side], cv2.COLOR_RGB2BGR))
    camera = ["--focal-px", str(FOCAL_PX), "--baseline-m", str(BASELINE_M), "--max-disp", "64"]
    args = ["estimate", "--left", str(paths[0]), "--right", str(paths[1]), *camera, "--json", str(tmp_path / "r.json")]
    assert main(args) == 0
    assert "branchrange estimate: warning: light dark (median grey" in capsys.readouterr().err
    light = json.loads((tmp_path / "r.json").read_text())["masks"]["light"]
    assert light["light"] == "dark" and light["median_grey"] < 55 and light["noise_grey"] >= 0
    data = {"focal_px": str(FOCAL_PX), "baseline_m": str(BASELINE_M), "max_disp": "64"}
    with TestClient(create_app(ApiConfig(), PipelineEstimator())) as client:
        for image, expected in ((scene, "normal"), (None, "dark")):
            files = {
                side: (f"{side}.png", cv2.imencode(".png", cv2.cvtColor(dusk[side], cv2.COLOR_RGB2BGR))[1].tobytes())
                if image is None
                else (f"{side}.png", scene.png(side))
                for side in ("left", "right")
            }
            reply = client.post("/estimate", files=files, data=data)
            assert reply.status_code == 200 and reply.json()["masks"]["light"]["light"] == expected
