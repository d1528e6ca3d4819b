"""The cropped, vectorised cut-point geometry gives the cut points the per-frame code gave.

`tests/data/cutpoints_reference.json` holds every estimate of `CASES` as computed by the
per-frame implementation at commit 930314a (before the geometry worked on each instance's
bounding box), pinned with this module's own `--pin`:

    git worktree add /tmp/old 930314a
    PYTHONPATH=/tmp/old:tests python tests/test_cutpoints_speed_parity.py --pin tests/data/cutpoints_reference.json

Tolerances: 1e-6 m on every position (cut point, base) and on the diameter and residual, 1e-6 on
unit vectors, confidence and valid fraction, 1e-4 px on the pixel; the point count, the kept
branch ids and every drop reason must match exactly. The crops keep the pixel order, the
arithmetic of every discrete decision (RANSAC counts, erosion, edge tensor) and all float
inputs of the fits bit for bit; what differs is the last bit of a few vectorised ray
normalisations, ~1e-16 relative.

The reference predates the depth's precision in the confidence, so the cases run without it
(`cut_disparity_noise_px` 0: `REFERENCE_CONFIG`; at 930314a, pin with `CutPointConfig()`).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from branch_geometry_fixtures import GEOMETRY, TRUNK_LABEL, Cylinder, branch_with_trunk, ray_cast, unit

from branchrange.core.cutpoints import CutPointConfig, estimate_cut_points
from branchrange.core.geometry import StereoGeometry
from branchrange.core.masks import masks_from_array

REFERENCE = Path(__file__).parent / "data" / "cutpoints_reference.json"
#: The synthetic generator's rig at 640×360.
WIDE = StereoGeometry(focal_px=320.0, baseline_m=0.063, cx=319.5, cy=179.5)

#: the reference's settings: it predates the depth's precision in the confidence (`cut_disparity_noise_px`)
REFERENCE_CONFIG = CutPointConfig(cut_disparity_noise_px=0.0)

Case = tuple[np.ndarray, np.ndarray, StereoGeometry, dict]  # labels, disparity, geometry, estimate kwargs


def _with_trunk(direction, radius) -> Case:
    scene, _, _ = branch_with_trunk(direction=direction, radius=radius)
    return scene.labels, scene.disparity, GEOMETRY, {"trunk_id": TRUNK_LABEL}


def _noisy(seed: int, sigma: float, outlier_share: float) -> Case:
    """The default branch with Gaussian disparity noise and background disparity on a share of it."""
    scene, _, _ = branch_with_trunk(radius=0.015)
    rng = np.random.default_rng(seed)
    disparity = scene.disparity + rng.normal(0, sigma, scene.disparity.shape).astype(np.float32) * (scene.disparity > 0)
    rows, cols = np.nonzero(scene.labels == 1)
    pick = rng.random(rows.size) < outlier_share
    disparity[rows[pick], cols[pick]] = GEOMETRY.fb / rng.uniform(3.0, 6.0, pick.sum())
    confidence = rng.uniform(0.5, 1.0, disparity.shape).astype(np.float32)
    return scene.labels, disparity.astype(np.float32), GEOMETRY, {"trunk_id": TRUNK_LABEL, "confidence": confidence}


def _trunk_without_depth(direction) -> Case:
    """The trunk's mask but no depth on it: the base is the end nearer the trunk in the image."""
    scene, _, _ = branch_with_trunk(direction=direction)
    disparity = np.where(scene.labels == TRUNK_LABEL, 0.0, scene.disparity).astype(np.float32)
    return scene.labels, disparity, GEOMETRY, {"trunk_id": TRUNK_LABEL}


def _thick_and_thin_without_trunk() -> Case:
    start, direction = np.array([-0.3, 0.0, 1.4]), unit([1.0, 0.2, 0.0])
    scene = ray_cast(
        320,
        240,
        GEOMETRY,
        {7: [Cylinder(start, direction, 0.2, 0.025), Cylinder(start + 0.2 * direction, direction, 0.25, 0.01)]},
    )
    return scene.labels, scene.disparity, GEOMETRY, {"trunk_id": None}


def _off_axis_trunk(direction) -> Case:
    """A trunk 36 cm thick 33° off the optical axis (as in test_cutpoints_perspective) and a branch."""
    axis_point, radius, axis = np.array([-0.77, 0.0, 1.18]), 0.18, unit([0.045, 1.0, 0.02])
    direction = unit(direction)
    across = direction - (direction @ axis) * axis
    base = axis_point + direction * radius / np.linalg.norm(across)
    scene = ray_cast(
        640,
        360,
        WIDE,
        {
            TRUNK_LABEL: [Cylinder(axis_point - 1.5 * axis, axis, 3.0, radius)],
            1: [Cylinder(base, direction, 0.5, 0.012)],
        },
    )
    return scene.labels, scene.disparity, WIDE, {"trunk_id": TRUNK_LABEL}


def _border_cut_and_end_on() -> Case:
    """Branch 1 runs out of the image's right border (edge-direction axis); branch 2 points almost
    at the camera (a short silhouette: the 3D line fit); branch 3 is tiny (dropped)."""
    trunk = Cylinder(np.array([0.1, -1.0, 1.2]), unit([0.03, 1.0, 0.0]), 2.0, 0.07)
    out = Cylinder(np.array([0.17, 0.02, 1.2]), unit([1.0, 0.35, -0.1]), 0.6, 0.02)
    end_on = Cylinder(np.array([-0.2, 0.1, 1.3]), unit([0.1, 0.05, -1.0]), 0.3, 0.03)
    scene = ray_cast(320, 240, GEOMETRY, {TRUNK_LABEL: [trunk], 1: [out], 2: [end_on]})
    labels = scene.labels.copy()
    labels[10:12, 10:13] = 3
    return labels, scene.disparity, GEOMETRY, {"trunk_id": TRUNK_LABEL}


def _synthetic(seed: int, noise_px: float) -> Case:
    """A rendered tree at 640×360 (trunk, branches, twigs, leaves): truth disparity, optionally noisy."""
    from stereo.synth import SynthCamera, render_scene

    camera = SynthCamera.zed_mini(640, 360)
    scene = render_scene(seed, camera, supersample=1)
    disparity = scene.disparity.astype(np.float32)
    if noise_px:
        rng = np.random.default_rng(seed)
        disparity = disparity + rng.normal(0, noise_px, disparity.shape).astype(np.float32) * (disparity > 0)
    geometry = StereoGeometry(camera.focal_px, camera.baseline_m, camera.cx, camera.cy)
    return scene.instance_mask, disparity, geometry, {"max_disparity": 128.0}


def _binary() -> Case:
    """Two branches given as one binary mask (split into components, no trunk)."""
    scene, _, _ = branch_with_trunk(direction=(1, 0.2, 0.1))
    second, _, _ = branch_with_trunk(direction=(1, -0.9, 0.2), trunk=False)
    labels = ((scene.labels == 1) | (second.labels == 1)).astype(np.uint8) * 255
    disparity = np.maximum(scene.disparity * (scene.labels == 1), second.disparity)
    return labels, disparity, GEOMETRY, {"kind": "binary"}


CASES: dict[str, Callable[[], Case]] = {
    **{
        f"trunk_{i}_{radius}": (lambda d=d, r=radius: _with_trunk(d, r))
        for i, d in enumerate([(1, -0.3, -0.4), (1, 0, 0), (1, 0.5, 0.3), (1, -1, 0), (0.5, -0.2, -1)])
        for radius in (0.008, 0.02)
    },
    "toward_camera": lambda: _with_trunk((1.0, 0.0, -0.9), 0.02),
    "noisy": lambda: _noisy(1, 0.3, 0.0),
    "outliers": lambda: _noisy(0, 0.0, 0.25),
    "no_trunk_thicker_end": _thick_and_thin_without_trunk,
    "trunk_without_depth": lambda: _trunk_without_depth((1, -0.3, -0.4)),
    "trunk_without_depth_mirrored": lambda: _trunk_without_depth((-1, 0.4, 0.2)),
    **{
        f"off_axis_trunk_{i}": (lambda d=d: _off_axis_trunk(d))
        for i, d in enumerate([(1.0, -0.3, -0.5), (1.0, 0.2, 0.4), (0.6, -0.8, -0.3)])
    },
    "border_cut_and_end_on": _border_cut_and_end_on,
    "binary": _binary,
    "synthetic_3_truth": lambda: _synthetic(3, 0.0),
    "synthetic_7_noisy": lambda: _synthetic(7, 0.4),
}


def run_case(name: str) -> dict:
    """Every estimate and drop of one case as plain numbers (full precision)."""
    labels, disparity, geometry, options = CASES[name]()
    options = dict(options)
    mask_args = {key: options.pop(key) for key in ("trunk_id", "kind") if key in options}
    masks = masks_from_array(labels, **mask_args)
    result = estimate_cut_points(masks, disparity, geometry, REFERENCE_CONFIG, **options)
    return {
        "branches": [
            {
                "mask_id": b.mask_id,
                "cut_point_m": b.cut_point_m.tolist(),
                "base_m": b.base_m.tolist(),
                "axis": b.axis.tolist(),
                "distance_m": b.distance_m,
                "pixel": list(b.pixel),
                "diameter_m": b.diameter_m,
                "confidence": b.confidence,
                "valid_fraction": b.valid_fraction,
                "residual_m": b.residual_m,
                "n_points": b.n_points,
            }
            for b in result.branches
        ],
        "dropped": [{"mask_id": d.mask_id, "reason": d.reason} for d in result.dropped],
    }


TOLERANCE = {
    "cut_point_m": 1e-6,
    "base_m": 1e-6,
    "axis": 1e-6,
    "distance_m": 1e-6,
    "pixel": 1e-4,
    "diameter_m": 1e-6,
    "confidence": 1e-6,
    "valid_fraction": 1e-6,
    "residual_m": 1e-6,
}


@pytest.fixture(scope="module")
def reference() -> dict:
    return json.loads(REFERENCE.read_text(encoding="utf-8"))


@pytest.mark.parametrize("name", list(CASES))
def test_same_cut_points_as_the_per_frame_reference(name, reference):
    pinned, now = reference[name], run_case(name)
    assert now["dropped"] == pinned["dropped"]
    assert [b["mask_id"] for b in now["branches"]] == [b["mask_id"] for b in pinned["branches"]]
    for got, want in zip(now["branches"], pinned["branches"]):
        assert got["n_points"] == want["n_points"], got["mask_id"]
        for key, tol in TOLERANCE.items():
            np.testing.assert_allclose(got[key], want[key], rtol=0, atol=tol, err_msg=f"{name} {got['mask_id']} {key}")


def test_the_reference_covers_every_path():
    """The pinned cases exercise trunks, border-cut and end-on silhouettes, drops and many instances."""
    pinned = json.loads(REFERENCE.read_text(encoding="utf-8"))
    assert set(pinned) == set(CASES)
    reasons = " ".join(d["reason"] for case in pinned.values() for d in case["dropped"])
    assert "fewer than" in reasons
    assert sum(len(case["branches"]) for case in pinned.values()) >= 30


if __name__ == "__main__":  # pin the reference with the implementation on the path
    if len(sys.argv) != 3 or sys.argv[1] != "--pin":
        sys.exit("usage: python tests/test_cutpoints_speed_parity.py --pin FILE.json")
    out = Path(sys.argv[2])
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({name: run_case(name) for name in CASES}, indent=1), encoding="utf-8")
    print(f"wrote {out}")
