"""Synthetic flight sequences: a stereo camera flying toward one static synthetic tree, with exact truth per frame.

The tree (with its ground, background and sky) is drawn once by `build_scene` for the seed, as
`render_scene` draws it; each frame then carries that geometry into the frame's camera pose
(`viewpoint.scene_in_camera`) and ray-casts both views. The path (`flight_path`) approaches
one *target* branch's cut point from `start_m` to `end_m`; the target is the thickest branch
whose cut point a quarter-size check render shows at both ends of the nominal path (else the
thickest branch seen at the end, else the thickest).

Frames (`FlightFrame`): rectified left/right RGB uint8 (ZED Mini rig scaled to the size), the
left instance mask (uint16, `render_scene`'s ids: branches 1..N, `TRUNK_ID`, `TWIG_ID`,
`LEAF_ID`, background 0), left depth, the pose and every branch's truth in that frame's camera
frame, with `cut_visible` by `render.with_visibility`'s rule: the cut point lies in front of the
camera and the mask at its rounded pixel is its branch. World frame = the rectified left camera
frame of frame 0 (OpenCV axes, metres); poses give `X_world = R_world_cam · X_cam + t_world_cam`.

Photometry: one exposure gain for the whole flight, the auto-exposure of frame 0 (from a
quarter-size render), times the path's exposure wobble; per view gain jitter and sensor noise
are drawn per frame from the seed and the frame index, so any frame renders alone, identically.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from stereo.synth.camera import RayGrid, SynthCamera
from stereo.synth.flight_path import ApproachPath, FlightOptions
from stereo.synth.motion_blur import blur_along_motion, image_motion
from stereo.synth.render import (
    RenderedViews,
    auto_gain,
    develop,
    rasterise,
    render_views,
    scene_batches,
    with_visibility,
)
from stereo.synth.scene import SceneDescription, build_scene
from stereo.synth.truth import BranchTruth
from stereo.synth.viewpoint import scene_in_camera

#: Width (px) of the renders that choose the target and set the exposure.
CHECK_WIDTH = 320
#: Pose: (rotation `(3, 3)`, translation `(3,)` m).
Pose = tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True)
class FlightCut:
    """A branch's cut point in the world frame: mask id, position `(3,)` m, branch radius there (m)."""

    id: int
    world_m: np.ndarray
    radius_m: float


@dataclass(frozen=True)
class FlightView:
    """One viewpoint's render with every branch's truth in its camera frame (`cut_visible` filled in)."""

    views: RenderedViews
    branches: tuple[BranchTruth, ...]


@dataclass(frozen=True, eq=False)
class FlightFrame:
    """One frame of a flight: images, truth and pose.

    `left`, `right` RGB uint8 `H×W×3`; `mask` uint16 `H×W` (left view); `depth_m` float32 `H×W`
    (left Z, inf on sky); `R_world_cam` `(3, 3)`, `t_world_cam` `(3,)` m; `distance_m` to the
    target cut point along the approach; `branches` in this frame's left camera frame.
    """

    index: int
    timestamp_ns: int
    left: np.ndarray
    right: np.ndarray
    mask: np.ndarray
    depth_m: np.ndarray
    R_world_cam: np.ndarray
    t_world_cam: np.ndarray
    distance_m: float
    branches: tuple[BranchTruth, ...]

    @property
    def visible_cut_ids(self) -> list[int]:
        """Ids of the branches whose cut point this frame shows."""
        return [branch.id for branch in self.branches if branch.cut_visible]


class FlightRenderer:
    """Renders the frames of the flight `options` describe; the tree is drawn once, in `__init__`."""

    def __init__(self, options: FlightOptions) -> None:
        self.options = options
        self.synth_options = options.synth_options()
        self.camera = SynthCamera.zed_mini(options.width, options.height)
        width = min(CHECK_WIDTH, options.width)
        self.check_camera = SynthCamera.zed_mini(width, max(8, round(options.height * width / options.width)))
        self.scene: SceneDescription = build_scene(np.random.default_rng(options.seed), self.camera, self.synth_options)
        self.down = self.scene.sky.world_from_camera[1]  # gravity (world y) in the scene frame
        self.target_id = self._choose_target()
        target = next(b for b in self.scene.branches if b.id == self.target_id)
        self.path = ApproachPath(
            np.asarray(target.cut_point_m), self.down, options, np.random.default_rng([options.seed, 1])
        )
        self.origin: Pose = self.path.pose(0.0)
        preview = self.view(*self.origin, camera=self.check_camera)
        self.base_gain = auto_gain(preview.views.left, self.scene.exposure_target)

    def __len__(self) -> int:
        return self.options.frame_count

    @property
    def cut_points(self) -> list[FlightCut]:
        """Every branch's cut point in the world frame (frame 0's left camera)."""
        rotation, position = self.origin
        return [
            FlightCut(b.id, (np.asarray(b.cut_point_m) - position) @ rotation, b.radius_at(b.cut_offset_m))
            for b in self.scene.branches
        ]

    def world_pose(self, time_s: float) -> Pose:
        """(R_world_cam, t_world_cam) of the left camera at `time_s` (s after frame 0; frame 0 is the world)."""
        if time_s == 0.0:
            return np.eye(3), np.zeros(3)
        rotation, position = self.path.pose(time_s)
        origin_rotation, origin_position = self.origin
        return origin_rotation.T @ rotation, origin_rotation.T @ (position - origin_position)

    def view(self, rotation: np.ndarray, position: np.ndarray, camera: SynthCamera | None = None) -> FlightView:
        """Render the tree from a left camera at `position` `(3,)` m, `rotation` `(3, 3)`, in the scene frame."""
        camera = camera or self.camera
        scene = scene_in_camera(self.scene, rotation, position, camera)
        views = render_views(scene, camera, self.options.supersample, self.options.threads)
        return FlightView(views, tuple(with_visibility(scene.branches, views.ids)))

    def render(self, index: int) -> FlightFrame:
        """Frame `index` (0 ≤ index < len(self)): images, mask, depth, pose and truth."""
        if not 0 <= index < len(self):
            raise IndexError(f"frame index {index} is outside the flight's 0..{len(self) - 1}")
        opts = self.options
        time_s = opts.time_s(index)
        view = self.view(*self.path.pose(time_s))
        left, right = view.views.left, view.views.right
        now = self.world_pose(time_s)
        if opts.motion_blur:
            before = self.world_pose(time_s - 1.0 / opts.fps)
            with ThreadPoolExecutor(max_workers=opts.threads) as pool:
                left, right = pool.map(
                    lambda image, depth, side: blur_along_motion(
                        image, image_motion(depth, self.camera, side, now, before), opts.shutter
                    ),
                    (left, right),
                    (view.views.depth, view.views.right_depth),
                    ("left", "right"),
                )
        gain = self.base_gain * self.path.gain_factor(time_s)
        left, right = develop([left, right], gain, self.synth_options, np.random.default_rng([opts.seed, 2, index]))
        return FlightFrame(
            index,
            opts.timestamp_ns(index),
            left,
            right,
            view.views.ids,
            view.views.depth.astype(np.float32),
            now[0],
            now[1],
            opts.distance_m(time_s),
            view.branches,
        )

    def __iter__(self) -> Iterator[FlightFrame]:
        return (self.render(index) for index in range(len(self)))

    def _choose_target(self) -> int:
        """Id of the branch to approach (see the module docstring): its cut point seen from both path ends."""
        by_thickness = sorted(self.scene.branches, key=lambda b: (-b.base_radius_m, b.id))
        nominal = dataclasses.replace(self.options, sway_m=0.0, jitter_deg=0.0, yaw_rate_dps=0.0)
        last = nominal.time_s(nominal.frame_count - 1)
        seen_at_end = []
        for branch in by_thickness:
            path = ApproachPath(np.asarray(branch.cut_point_m), self.down, nominal, np.random.default_rng(0))
            seen = [self._cut_seen(branch.id, *path.pose(t)) for t in (last, 0.0)]
            if all(seen):
                return branch.id
            if seen[0]:
                seen_at_end.append(branch.id)
        return seen_at_end[0] if seen_at_end else by_thickness[0].id

    def _cut_seen(self, branch_id: int, rotation: np.ndarray, position: np.ndarray) -> bool:
        """Whether a check-size truth pass (ids only, no shading) from this pose shows `branch_id`'s cut point."""
        scene = scene_in_camera(self.scene, rotation, position, self.check_camera)
        _, ids, _ = rasterise(
            scene_batches(scene, self.check_camera), RayGrid.for_view(self.check_camera, "left", 1), None, None
        )
        return next(b.cut_visible for b in with_visibility(scene.branches, ids) if b.id == branch_id)
