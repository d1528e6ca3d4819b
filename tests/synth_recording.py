"""A short recording of a synthetic tree scene (stereo.synth, exact ground truth) for the replay and daemon tests.

The scene is rendered once per test process at 480×270 (ZED Mini rig scaled: f = 240 px,
B = 0.063 m). A camera holding still in front of the tree gives the frames: the same view with
fresh sensor noise each time (stereo.synth has no camera motion), so every frame is computed anew.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from camera.calibration import from_rectified
from camera.sources import Recorder, StereoFrame
from stereo.synth import BranchTruth, SynthCamera, SyntheticScene, render_scene

WIDTH, HEIGHT = 480, 270
#: A scene whose target branch (nearest confident cut point) is seen whole: the pipeline's
#: ground-truth-mask accuracy applies to it (see test_daemon's tolerance).
SEED = 9
FIRST_TIMESTAMP_NS = 1_000_000_000
#: Extra sensor noise per frame, grey levels (the render already has 1.0).
FRAME_NOISE_STD = 1.0


@functools.cache
def tree_scene(seed: int = SEED) -> SyntheticScene:
    """The rendered scene (cached: rendering takes about a second)."""
    return render_scene(seed, SynthCamera.zed_mini(WIDTH, HEIGHT))


def still_camera_frames(scene: SyntheticScene, count: int, period_ns: int, with_masks: bool) -> list[StereoFrame]:
    """`count` frames of `scene`, `period_ns` apart, each with its own sensor noise; with the
    ground-truth instance mask (uint16, stereo.synth ids) when `with_masks`."""
    rng = np.random.default_rng(1234)
    frames = []
    for i in range(count):
        left, right = (
            np.clip(view + rng.normal(0.0, FRAME_NOISE_STD, view.shape), 0, 255).round().astype(np.uint8)
            for view in (scene.left, scene.right)
        )
        mask = scene.instance_mask if with_masks else None
        frames.append(StereoFrame(left, right, FIRST_TIMESTAMP_NS + i * period_ns, i, mask))
    return frames


def write_tree_recording(out_dir: Path, count: int, period_ns: int, with_masks: bool = True) -> Path:
    """Record `count` still-camera frames of the scene in the replay format, with its rectified calibration."""
    scene = tree_scene()
    cam = scene.camera
    calibration = from_rectified(cam.focal_px, cam.cx, cam.cy, cam.baseline_m, (cam.width, cam.height))
    with Recorder(out_dir, calibration=calibration, source_spec=f"stereo.synth seed {scene.seed}") as recorder:
        for frame in still_camera_frames(scene, count, period_ns, with_masks):
            recorder.write(frame)
    return out_dir


def truth_of(scene: SyntheticScene, mask_id: int) -> BranchTruth:
    """The ground truth of the branch with instance id `mask_id`."""
    return next(b for b in scene.branches if b.id == mask_id)
