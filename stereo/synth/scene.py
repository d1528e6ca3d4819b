"""Procedural tree scenes: a trunk with branches, twigs and leaves in front of far foliage, ground and sky.

The scene is drawn in a world frame with y pointing down (gravity) and the camera at the origin,
then carried into the left camera frame (x right, y down, z forward) through the camera's pitch
and roll. Pose classes follow VirtualTree's views: upward into the crown against the sky,
near-parallel toward a tree row, downward onto branches with the ground behind them. Every
pruning-target branch is a straight tapered cylinder 0.2–1.5 m long, 5–60 mm thick at the
base, kept 0.3–4 m from the camera and at least half inside the left image, with its cut point
in view.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from stereo.synth.camera import SynthCamera
from stereo.synth.cones import BarkMaterial, Cone
from stereo.synth.hardware import orchard_hardware
from stereo.synth.leaves import Leaf
from stereo.synth.options import SynthOptions
from stereo.synth.orchard import (
    ESPALIER_AZIMUTH_DEG,
    ESPALIER_ELEVATION_DEG,
    ORCHARD_BARKS,
    ORCHARD_LEAF_COLOURS,
    TRUNK_LEAN,
    orchard_bark_tile,
    orchard_light,
)
from stereo.synth.planes import PlaneLayer
from stereo.synth.primitives import Lighting, cross3, norm3, rowdot, unit, unit_rows
from stereo.synth.sky import Sky
from stereo.synth.textures import (
    BARK_KINDS,
    MipTile,
    bark_tile,
    cloud_tile,
    detail_tile,
    foliage_tile,
    ground_tile,
    periodic_noise,
)
from stereo.synth.truth import LEAF_ID, TRUNK_ID, TWIG_ID, BranchTruth

UP = np.array([0.0, -1.0, 0.0])
#: Radius (m) of a cone at a distance (m) from its base along the axis.
RadiusProfile = Callable[[float], float]
BRANCH_RANGE_M = (0.3, 4.0)
BRANCH_LENGTH_M = (0.2, 1.5)
BRANCH_BASE_RADIUS_M = (0.0025, 0.030)
_PITCH_DEG = {"upward": (15.0, 45.0), "parallel": (-10.0, 10.0), "downward": (-40.0, -15.0)}
_TRUNK_DISTANCE_M = {"upward": (0.8, 3.0), "parallel": (0.5, 2.5), "downward": (0.8, 3.0)}
_GROUND_BELOW_M = {"upward": (0.5, 1.8), "parallel": (1.0, 2.2), "downward": (1.0, 2.5)}
_LEAF_COLOURS = {
    "spring": (0.36, 0.56, 0.17),
    "summer": (0.17, 0.34, 0.10),
    "yellow": (0.70, 0.58, 0.14),
    "orange": (0.72, 0.36, 0.09),
}


@dataclass(frozen=True)
class SceneDescription:
    """Everything the renderer draws, in the left camera frame, plus the branch truth."""

    pose: str
    foliage: str
    leaf_shape: str
    cones: tuple[Cone, ...]
    leaves: tuple[Leaf, ...]
    layers: tuple[PlaneLayer, ...]
    sky: Sky
    lighting: Lighting
    branches: tuple[BranchTruth, ...]
    exposure_target: float
    leaf_detail: MipTile


class _DrawnBranch(NamedTuple):
    """A pruning-target branch that fits the view, in world coordinates (m).

    `base` is where its axis leaves the trunk's tapered surface, exactly: the truth is measured
    from it. The drawn cone, its twigs and the fit checks are measured from `drawn_from`, the point
    of the same axis `trunk radius at the attachment height / max(sin(angle to the trunk), 0.3)`
    from the trunk axis, 1.5 mm inside to 12 mm outside the bark; it stays what scenes are drawn
    from so they render as before. `length`, `r0` and `r1` are the drawn cone's, from `drawn_from`
    to the tip.
    """

    base: np.ndarray
    drawn_from: np.ndarray
    axis: np.ndarray
    length: float
    r0: float
    r1: float


class CameraFrame:
    """The camera's pose: carries world points and directions (y down) into the camera frame."""

    def __init__(self, pitch_rad: float, roll_rad: float) -> None:
        forward = np.array([0.0, -np.sin(pitch_rad), np.cos(pitch_rad)])
        right0 = np.array([1.0, 0.0, 0.0])
        down0 = np.array([0.0, np.cos(pitch_rad), np.sin(pitch_rad)])
        right = np.cos(roll_rad) * right0 + np.sin(roll_rad) * down0
        down = -np.sin(roll_rad) * right0 + np.cos(roll_rad) * down0
        self.world_from_camera = np.stack([right, down, forward], axis=1)
        self.forward, self.right = forward, right

    def point(self, p: np.ndarray) -> np.ndarray:
        """A world point (or `(N, 3)` points) in the camera frame."""
        return np.asarray(p) @ self.world_from_camera

    direction = point


class _SceneBuilder:
    """Draws one scene from a random generator; `build()` returns its description."""

    def __init__(self, rng: np.random.Generator, camera: SynthCamera, options: SynthOptions) -> None:
        self.rng, self.camera, self.options = rng, camera, options
        self.tan_half_h = (camera.width / 2) / camera.focal_px
        self.tan_half_v = (camera.height / 2) / camera.focal_px
        self.pose = (
            options.pose
            if options.pose != "auto"
            else str(rng.choice(["upward", "parallel", "downward"], p=[0.35, 0.35, 0.30]))
        )
        self.foliage = (
            options.foliage
            if options.foliage != "auto"
            else str(rng.choice(["bare", "sparse", "dense"], p=[0.4, 0.35, 0.25]))
        )
        self.leaf_shape = options.leaf_shape if options.leaf_shape != "auto" else str(rng.choice(["broad", "needles"]))
        pitch = np.radians(rng.uniform(*_PITCH_DEG[self.pose]))
        self.frame = CameraFrame(pitch, np.radians(rng.uniform(-6.0, 6.0)))
        self.cones: list[Cone] = []
        self.leaves: list[Leaf] = []
        self.leafy_twigs: list[tuple[np.ndarray, np.ndarray, float, int]] = []
        self.detail = MipTile(detail_tile(rng))
        self.orchard = options.domain == "orchard"
        if self.orchard:
            self.leaf_colour = np.array(ORCHARD_LEAF_COLOURS[str(rng.choice(list(ORCHARD_LEAF_COLOURS)))])
        else:
            self.leaf_colour = np.array(_LEAF_COLOURS[str(rng.choice(list(_LEAF_COLOURS), p=[0.3, 0.4, 0.15, 0.15]))])

    # -- checks in the camera frame ---------------------------------------------------------
    def _in_image_fraction(self, points_cam: np.ndarray, margin: float = 0.0) -> float:
        """Fraction of camera-frame points in front of the camera that project inside the image."""
        z = points_cam[:, 2]
        front = z > 0.05
        if not front.any():
            return 0.0
        pix = self.camera.project(points_cam[front])
        mx, my = margin * self.camera.width, margin * self.camera.height
        inside = (
            (pix[:, 0] >= mx)
            & (pix[:, 0] <= self.camera.width - 1 - mx)
            & (pix[:, 1] >= my)
            & (pix[:, 1] <= self.camera.height - 1 - my)
        )
        return float(inside.sum()) / len(z)

    def _axis_points(self, base: np.ndarray, axis: np.ndarray, length: float, n: int = 16) -> np.ndarray:
        """World points along an axis, in the camera frame `(n, 3)`."""
        return self.frame.point(base[None, :] + np.linspace(0.0, length, n)[:, None] * axis[None, :])

    def _bark(self, tile: MipTile, radius: float, tint: np.ndarray) -> BarkMaterial:
        """Bark wrapped so its features scale with the branch (about 12 cm of bark per tile on a trunk)."""
        around = int(np.clip(round(2 * np.pi * radius / 0.12), 1, 12))
        return BarkMaterial(tile, around, 2.5 * 2 * np.pi * radius / around, tint)

    def _cone(
        self,
        base_w: np.ndarray,
        axis_w: np.ndarray,
        length: float,
        r0: float,
        r1: float,
        material: BarkMaterial,
        instance_id: int,
    ) -> Cone:
        """A cone given in world coordinates, stored in the camera frame."""
        cone = Cone(self.frame.point(base_w), unit(self.frame.direction(axis_w)), length, r0, r1, material, instance_id)
        self.cones.append(cone)
        return cone

    # -- the main tree ----------------------------------------------------------------------
    def _trunk(self) -> tuple[np.ndarray, np.ndarray, float, float, float, float]:
        """Place the trunk; returns (foot on the ground, axis, length, radius at ground, at top, ground y).

        World y of the ground = how far below the camera it lies (m).
        """
        rng = self.rng
        distance = rng.uniform(*_TRUNK_DISTANCE_M[self.pose])
        frac = rng.uniform(-0.8, 0.8) if rng.random() < 0.85 else rng.choice([-1, 1]) * rng.uniform(1.0, 1.3)
        target = distance * self.frame.forward + frac * distance * self.tan_half_h * self.frame.right
        ground_y = max(target[1], 0.0) + rng.uniform(*_GROUND_BELOW_M[self.pose])
        lean = TRUNK_LEAN if self.orchard else 0.12
        axis = unit(np.array([rng.uniform(-lean, lean), -1.0, rng.uniform(-lean, lean)]))
        foot = np.array([target[0], ground_y, target[2]])
        top_above_camera = rng.uniform(6.0, 12.0)
        length = (ground_y + top_above_camera) / -axis[1]
        r_ground = min(rng.uniform(0.08, 0.22), 0.25 * distance)
        return foot, axis, length, r_ground, r_ground * rng.uniform(0.3, 0.5), ground_y

    def _visible_trunk_span(self, foot: np.ndarray, axis: np.ndarray, length: float) -> tuple[float, float]:
        """Axis range (m from the ground) whose points fall within the image rows, with margins."""
        s = np.linspace(0.0, length, 240)
        pts = self.frame.point(foot[None, :] + s[:, None] * axis[None, :])
        front = pts[:, 2] > 0.1
        rows = np.full(s.shape, -1.0)
        rows[front] = self.camera.project(pts[front])[:, 1]
        seen = s[front & (rows >= 0) & (rows <= self.camera.height - 1)]
        if seen.size == 0:
            return 0.5, min(length - 0.5, 3.0)
        return max(0.5, seen.min() - 0.3), min(length - 0.5, seen.max() + 0.3)

    def _hidden_by_trunk(self, points_cam: np.ndarray) -> np.ndarray:
        """Which camera-frame points `(N, 3)` the trunk hides from the left camera (sight line enters it first)."""
        foot, axis, length, r_ground, r_top = self.trunk
        to_foot = foot[None, :]
        pa = points_cam @ axis
        across = rowdot(points_cam, points_cam) - pa * pa
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = (points_cam @ foot - (foot @ axis) * pa) / across
        lam = np.clip(np.nan_to_num(lam, nan=1.0), 0.0, 1.0)
        closest = lam[:, None] * points_cam - to_foot
        s = closest @ axis
        dist = norm3(closest - s[:, None] * axis)
        radius = r_ground + (r_top - r_ground) * np.clip(s, 0.0, length) / length
        return (lam < 0.999) & (s >= 0.0) & (s <= length) & (dist < 1.05 * radius)

    def _branch_fits(self, base: np.ndarray, axis: np.ndarray, length: float, r0: float) -> bool:
        """The branch stays 0.3–4 m away, at least half in the image, unhidden by the trunk, its cut point in view."""
        pts = self._axis_points(base, axis, length)
        dist = norm3(pts)
        if dist.min() < BRANCH_RANGE_M[0] + r0 or dist.max() > BRANCH_RANGE_M[1] or pts[:, 2].min() < 0.25:
            return False
        cut = self.frame.point(base + self.options.cut_offset_m * axis)[None, :]
        if self._hidden_by_trunk(cut)[0] or self._hidden_by_trunk(pts).mean() > 0.4:
            return False
        return self._in_image_fraction(pts) >= 0.5 and self._in_image_fraction(cut, margin=0.02) == 1.0

    def _draw_branch(
        self, foot: np.ndarray, trunk_axis: np.ndarray, span: tuple[float, float], trunk: Cone
    ) -> _DrawnBranch | None:
        """A branch out of `trunk` (drawn from `foot` along world `trunk_axis`) that fits, or None after 40 tries."""
        rng = self.rng
        for _ in range(40):
            s_att = rng.uniform(*span)
            if self.orchard:  # espalier: nearly level, along the row (world x) either way
                along = rng.choice([0.0, np.pi]) + np.radians(rng.uniform(-ESPALIER_AZIMUTH_DEG, ESPALIER_AZIMUTH_DEG))
                azimuth, elevation = along, np.radians(rng.uniform(*ESPALIER_ELEVATION_DEG))
            else:
                azimuth = rng.uniform(0, 2 * np.pi)
                elevation = np.radians(rng.uniform(-20.0, 60.0))
            axis = np.array(
                [np.cos(elevation) * np.cos(azimuth), -np.sin(elevation), np.cos(elevation) * np.sin(azimuth)]
            )
            sin_trunk = float(np.sqrt(np.sum(cross3(axis, trunk_axis) ** 2)))
            radius_here = trunk.radius_at(s_att)
            on_trunk_axis = foot + s_att * trunk_axis
            drawn_from = on_trunk_axis + axis * radius_here / max(sin_trunk, 0.3)
            length = float(np.exp(rng.uniform(np.log(BRANCH_LENGTH_M[0]), np.log(BRANCH_LENGTH_M[1]))))
            r0 = float(
                np.exp(
                    rng.uniform(
                        np.log(BRANCH_BASE_RADIUS_M[0]), np.log(min(BRANCH_BASE_RADIUS_M[1], 0.6 * radius_here))
                    )
                )
            )
            r1 = max(0.0008, r0 * rng.uniform(0.15, 0.45))
            if self._branch_fits(drawn_from, axis, length, r0):
                # the frame is a rotation, so the distance is the same in world and camera coordinates
                to_bark = trunk.exit_distance(self.frame.point(on_trunk_axis), self.frame.direction(axis))
                return _DrawnBranch(on_trunk_axis + to_bark * axis, drawn_from, axis, length, r0, r1)
        return None

    def _twigs(
        self,
        base: np.ndarray,
        axis: np.ndarray,
        length: float,
        radius: RadiusProfile,
        tile: MipTile,
        ids: tuple[int, int] = (TWIG_ID, LEAF_ID),
        depth: int = 0,
    ) -> None:
        """Thin twigs (and their leaves) growing from an axis, one level of sub-twigs; `ids`: (twig, leaf) mask ids."""
        rng = self.rng
        count = rng.integers(3, 5 + int(14 * length)) if depth == 0 else rng.integers(0, 4)
        tint = np.array([1.05, 0.95, 0.85]) * rng.uniform(0.9, 1.2)
        for _ in range(count):
            s = rng.uniform(0.15, 0.98) * length
            side = unit(cross3(axis, rng.normal(size=3)))
            angle = np.radians(rng.uniform(25.0, 65.0))
            twig_axis = unit(np.cos(angle) * axis + np.sin(angle) * side + 0.25 * UP)
            twig_len = rng.uniform(0.04, 0.30) * (0.5 if depth else 1.0) * min(1.0, 0.5 + length)
            r0 = min(0.75 * radius(s), rng.uniform(0.0008, 0.003))
            r1 = max(0.00035, r0 * rng.uniform(0.3, 0.6))
            start = base + s * axis
            if self._axis_points(start, twig_axis, twig_len, 6)[:, 2].min() < 0.2:
                continue
            self._cone(start, twig_axis, twig_len, r0, r1, self._bark(tile, r0, tint), ids[0])
            self.leafy_twigs.append((start, twig_axis, twig_len, ids[1]))
            if depth == 0:
                self._twigs(
                    start,
                    twig_axis,
                    twig_len,
                    lambda q, r0=r0, r1=r1, n=twig_len: r0 + (r1 - r0) * q / n,
                    tile,
                    ids,
                    depth=1,
                )

    def _grow_leaves(self) -> None:
        """Leaves at random points of every recorded twig: blades, or needle clusters when `leaf_shape` says so."""
        if self.foliage == "bare" or not self.leafy_twigs:
            return
        rng = self.rng
        start, axis, length, leaf_id = (np.array(column) for column in zip(*self.leafy_twigs))
        low, high = (1, 4) if self.foliage == "sparse" else (3, 8)
        twig = np.repeat(np.arange(len(length)), rng.integers(low, high, size=len(length)))
        along = rng.uniform(0.2, 1.0, twig.size)
        attach = start[twig] + (along * length[twig])[:, None] * axis[twig]
        grow = self._needle_clusters if self.leaf_shape == "needles" else self._leaf_blades
        grow(attach, axis[twig], leaf_id[twig])
        self.leafy_twigs = []

    def _leaf_blades(self, attach: np.ndarray, axis: np.ndarray, leaf_id: np.ndarray) -> None:
        """Leaf blades at world points `attach` `(n, 3)` of twigs with unit `axis` `(n, 3)`, angled outward
        (about 50°) and roughly facing up."""
        rng = self.rng
        n = attach.shape[0]
        half_length = rng.uniform(0.025, 0.055, n)
        side = unit_rows(cross3(axis, rng.normal(size=(n, 3))))
        e1 = unit_rows(np.cos(np.radians(50)) * axis + np.sin(np.radians(50)) * side + rng.normal(0, 0.3, (n, 3)))
        centre = attach + (1.1 * half_length)[:, None] * e1
        up = unit_rows(UP - (e1 @ UP)[:, None] * e1)
        normal = unit_rows(cross3(e1, rng.normal(size=(n, 3))))
        normal = unit_rows(normal + 1.2 * up * np.sign(rowdot(normal, up) + 1e-9)[:, None])
        normal = unit_rows(normal - rowdot(normal, e1)[:, None] * e1)
        colour = np.clip(self.leaf_colour * rng.uniform(0.8, 1.2, (n, 1)) + rng.normal(0, 0.03, (n, 3)), 0.02, 1.0)
        widths = half_length * rng.uniform(0.3, 0.55, n)
        centre_cam, normal_cam, e1_cam = (self.frame.point(v) for v in (centre, normal, e1))
        for i in np.flatnonzero(centre_cam[:, 2] >= 0.2 + half_length):
            self.leaves.append(
                Leaf(
                    centre_cam[i],
                    normal_cam[i],
                    e1_cam[i],
                    float(half_length[i]),
                    float(widths[i]),
                    colour[i],
                    int(leaf_id[i]),
                )
            )

    def _needle_clusters(self, attach: np.ndarray, axis: np.ndarray, leaf_id: np.ndarray) -> None:
        """A tuft of 5–10 needles at each world point `attach` `(n, 3)`: thin cones 2–6 cm long, 1–1.6 mm
        thick at the base, fanning 15–60° out of the twig direction `axis` `(n, 3)`, with the leaves' mask id."""
        rng = self.rng
        n = attach.shape[0]
        cluster = np.repeat(np.arange(n), rng.integers(5, 11, size=n))
        m = cluster.size
        spread = np.radians(rng.uniform(15.0, 60.0, m))
        side = unit_rows(cross3(axis[cluster], rng.normal(size=(m, 3))))
        direction = unit_rows(np.cos(spread)[:, None] * axis[cluster] + np.sin(spread)[:, None] * side)
        length = rng.uniform(0.02, 0.06, n)[cluster] * rng.uniform(0.85, 1.15, m)
        radius = rng.uniform(0.0005, 0.0008, n)[cluster]
        tints = np.clip(self.leaf_colour * rng.uniform(0.7, 1.1, (n, 1)), 0.02, 1.0)
        materials = [BarkMaterial(self.detail, 1, 0.02, tint) for tint in tints]
        in_front = self.frame.point(attach)[cluster, 2] >= 0.2 + length
        for i in np.flatnonzero(in_front):
            c = cluster[i]
            self._cone(
                attach[c],
                direction[i],
                float(length[i]),
                float(radius[i]),
                0.3 * float(radius[i]),
                materials[c],
                int(leaf_id[c]),
            )

    def _main_tree(self) -> tuple[list[BranchTruth], float]:
        """Trunk, branches, twigs and leaves of the tree being pruned; returns the truth and ground depth."""
        rng = self.rng
        tile = self._bark_tile()
        for _ in range(10):
            self.cones, self.leaves, self.leafy_twigs = [], [], []
            foot, trunk_axis, trunk_len, r_ground, r_top, ground_y = self._trunk()

            trunk = self._cone(
                foot, trunk_axis, trunk_len, r_ground, r_top, self._bark(tile, r_ground, np.ones(3)), TRUNK_ID
            )
            self.trunk = (trunk.base, trunk.axis, trunk_len, r_ground, r_top)
            self.trunk_foot = foot
            span = self._visible_trunk_span(foot, trunk_axis, trunk_len)
            truths: list[BranchTruth] = []
            for _ in range(rng.integers(4, 11)):
                drawn = self._draw_branch(foot, trunk_axis, span, trunk)
                if drawn is None:
                    continue
                base, drawn_from, axis, length, r0, r1 = drawn
                tint = np.clip(rng.uniform(0.9, 1.15) + rng.normal(0, 0.04, 3), 0.7, 1.3)
                # the surface starts inside the trunk (same taper), so no open end shows at an oblique junction
                root = foot + (drawn_from - foot) @ trunk_axis * trunk_axis
                sunk = float(np.sqrt(np.sum((drawn_from - root) ** 2)))
                slope = (r1 - r0) / length
                cone = self._cone(
                    drawn_from - sunk * axis,
                    axis,
                    length + sunk,
                    r0 - slope * sunk,
                    r1,
                    self._bark(tile, r0, tint),
                    len(truths) + 1,
                )
                # the truth runs from where the axis leaves the bark to the drawn tip, on the drawn taper
                beyond_bark = float((drawn_from - base) @ axis)
                truths.append(
                    self._truth(
                        cone.instance_id,
                        self.frame.point(base),
                        cone.axis,
                        length + beyond_bark,
                        r0 - slope * beyond_bark,
                        r1,
                    )
                )
                self._twigs(drawn_from, axis, length, lambda s, r0=r0, r1=r1, n=length: r0 + (r1 - r0) * s / n, tile)
            if len(truths) >= 2:
                self._crown(foot, trunk_axis, trunk_len, trunk.radius_at, tile)
                self._grow_leaves()
                return truths, ground_y
        raise RuntimeError("could not place two branches in view after 10 tree layouts; the camera is too narrow")

    def _bark_tile(self) -> MipTile:
        """A bark of the scene's domain: one of `BARK_KINDS`, or of `ORCHARD_BARKS` in the orchard."""
        rng = self.rng
        if self.orchard:
            return MipTile(orchard_bark_tile(rng, str(rng.choice(list(ORCHARD_BARKS)))))
        return MipTile(bark_tile(rng, str(rng.choice(list(BARK_KINDS)))))

    def _crown(
        self, foot: np.ndarray, trunk_axis: np.ndarray, trunk_len: float, trunk_radius: RadiusProfile, tile: MipTile
    ) -> None:
        """Branches of the same tree beyond the 4 m working range (mask id 0, like all background)."""
        rng = self.rng
        far = BRANCH_RANGE_M[1] + 0.2
        for _ in range(rng.integers(4, 11)):
            s_att = rng.uniform(1.0, trunk_len - 0.5)
            azimuth, elevation = rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(10.0, 70.0))
            axis = np.array(
                [np.cos(elevation) * np.cos(azimuth), -np.sin(elevation), np.cos(elevation) * np.sin(azimuth)]
            )
            start = foot + s_att * trunk_axis
            length = rng.uniform(1.0, 3.0)
            r0 = min(rng.uniform(0.015, 0.04), 0.6 * trunk_radius(s_att))
            r1 = r0 * rng.uniform(0.2, 0.4)
            if norm3(self._axis_points(start, axis, length)).min() < far + r0:
                continue
            self._cone(start, axis, length, r0, r1, self._bark(tile, r0, np.ones(3)), 0)
            self._twigs(start, axis, length, lambda s, r0=r0, r1=r1, n=length: r0 + (r1 - r0) * s / n, tile, (0, 0))

    def _truth(
        self, branch_id: int, base: np.ndarray, axis: np.ndarray, length: float, r0: float, r1: float
    ) -> BranchTruth:
        """The truth of a branch given in the camera frame (base on the trunk surface)."""
        cut = base + self.options.cut_offset_m * axis
        pixel = self.camera.project(cut[None, :])[0]
        as_tuple = lambda v: (float(v[0]), float(v[1]), float(v[2]))  # noqa: E731
        return BranchTruth(
            branch_id, as_tuple(base), as_tuple(axis), length, r0, r1, as_tuple(cut), (float(pixel[0]), float(pixel[1]))
        )

    # -- mid-ground trees and background ------------------------------------------------------
    def _background_trees(self, tile: MipTile, ground_y: float) -> None:
        """0–3 leafless trees 4.5–9 m away (mask id 0): clutter a matcher must not confuse with targets."""
        rng = self.rng
        horizontal = unit(np.array([self.frame.forward[0], 0.0, self.frame.forward[2]]))
        side = np.array([horizontal[2], 0.0, -horizontal[0]])
        for _ in range(rng.integers(0, 4)):
            distance = rng.uniform(4.5, 9.0)
            foot = distance * horizontal + rng.uniform(-1.2, 1.2) * distance * self.tan_half_h * side
            foot[1] = ground_y
            axis = unit(np.array([rng.uniform(-0.1, 0.1), -1.0, rng.uniform(-0.1, 0.1)]))
            length = ground_y + rng.uniform(5.0, 10.0)
            r_ground = rng.uniform(0.08, 0.25)
            tint = np.full(3, rng.uniform(0.6, 0.9))
            self._cone(foot, axis, length, r_ground, 0.35 * r_ground, self._bark(tile, r_ground, tint), 0)
            for _ in range(rng.integers(3, 7)):
                s = rng.uniform(1.5, length - 1.0)
                az, el = rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(10, 60))
                b_axis = np.array([np.cos(el) * np.cos(az), -np.sin(el), np.cos(el) * np.sin(az)])
                b_len, b_r0 = rng.uniform(0.8, 2.5), rng.uniform(0.015, 0.05)
                start = foot + s * axis
                if norm3(self._axis_points(start, b_axis, b_len, 8)).min() < 4.0:
                    continue
                self._cone(start, b_axis, b_len, b_r0, 0.3 * b_r0, self._bark(tile, b_r0, tint), 0)

    def _ground(self, ground_y: float) -> PlaneLayer:
        """The ground plane `ground_y` m below the camera: grass and soil patches."""
        rng = self.rng
        if self.orchard:  # a mown, yellowing alley over dark soil
            grass = np.array([0.32, 0.35, 0.14]) * rng.uniform(0.8, 1.1)
            soil = np.array([0.20, 0.16, 0.12]) * rng.uniform(0.7, 1.2)
        else:
            grass = np.array([0.26, 0.36, 0.12]) * rng.uniform(0.7, 1.2)
            soil = np.array([0.36, 0.28, 0.19]) * rng.uniform(0.7, 1.2)
        return PlaneLayer(
            self.frame.point(np.array([0.0, ground_y, 0.0])),
            self.frame.direction(np.array([1.0, 0, 0])),
            self.frame.direction(np.array([0.0, 0, 1.0])),
            MipTile(ground_tile(rng, grass, soil)),
            rng.uniform(0.8, 2.0),
            0.8,
        )

    def _crown_line(self, period_m: float, samples: int = 512) -> tuple[np.ndarray, list[tuple[float, float]]]:
        """A row of rounded tree crowns, periodic over `period_m`.

        Returns the canopy heights (m above ground, `(samples,)`) and each crown's (u, centre
        height) in metres, where its trunk goes.
        """
        rng = self.rng
        u = np.arange(samples) * period_m / samples
        top = np.zeros(samples)
        crowns = []
        mean_height, position = rng.uniform(6.0, 14.0), 0.0
        while position < period_m:
            radius = rng.uniform(1.5, 5.0)
            centre_height = mean_height * rng.uniform(0.75, 1.2) - radius
            offset = np.mod(u - position - radius + period_m / 2, period_m) - period_m / 2
            dome = centre_height + np.sqrt(np.clip(radius**2 - offset**2, 0.0, None)) * rng.uniform(0.8, 1.3)
            top = np.where(np.abs(offset) < radius, np.maximum(top, dome), top)
            crowns.append(((position + radius) % period_m, centre_height))
            position += radius * rng.uniform(1.0, 1.8)
        return top + 0.25 * periodic_noise(rng, 40.0, 40.0, size=samples)[0], crowns

    def _tree_rows(self, ground_y: float, bark: MipTile) -> list[PlaneLayer]:
        """One or two far rows of trees (10–45 m): trunks under rounded crowns of leaf clumps, gaps to the sky.

        The last row's foliage reaches the ground (a wood behind), so the far horizon stays hidden.
        """
        rng = self.rng
        layers, distance, period = [], rng.uniform(10.0, 25.0), 80.0
        rows = int(rng.integers(1, 3))
        for row in range(rows):
            hue = np.array([0.16, 0.30, 0.10]) * rng.uniform(0.7, 1.3) + rng.normal(0, 0.02, 3)
            foliage = foliage_tile(rng, tuple(np.clip(hue, 0.02, 1)), rng.uniform(0.85, 0.97))
            profile, crowns = self._crown_line(period)
            floor = rng.uniform(1.5, 3.5) if row < rows - 1 else None
            reach = distance * (2 * self.tan_half_h + 0.5) + 10.0
            tint = np.full(3, rng.uniform(0.5, 0.8))
            for u, height in crowns:
                for x in np.arange(u - period * np.ceil(reach / period), reach, period):
                    if abs(x) < reach:
                        foot = np.array([x + rng.uniform(-0.3, 0.3), ground_y, distance + rng.uniform(0.2, 1.0)])
                        radius = rng.uniform(0.1, 0.3)
                        self._cone(
                            foot,
                            unit(UP + rng.normal(0, 0.04, 3)),
                            max(height, 2.0),
                            radius,
                            0.6 * radius,
                            self._bark(bark, radius, tint),
                            0,
                        )
            layers.append(
                PlaneLayer(
                    self.frame.point(np.array([0.0, ground_y, distance])),
                    self.frame.direction(np.array([1.0, 0, 0])),
                    self.frame.direction(UP),
                    MipTile(foliage[:, :, :3]),
                    rng.uniform(2.0, 4.0),
                    0.5,
                    np.ascontiguousarray(foliage[:, :, 3:]),
                    profile,
                    period,
                    floor,
                )
            )
            distance += rng.uniform(8.0, 20.0)
        return layers

    def _canopy(self) -> PlaneLayer | None:
        """A leaf canopy overhead with holes to the sky (mostly in upward views)."""
        rng = self.rng
        chance = {"upward": 0.6, "parallel": 0.25, "downward": 0.0}[self.pose]
        if rng.random() >= chance:
            return None
        hue = np.array([0.20, 0.36, 0.12]) * rng.uniform(0.7, 1.3)
        foliage = foliage_tile(rng, tuple(hue), rng.uniform(0.35, 0.7))
        return PlaneLayer(
            self.frame.point(np.array([0.0, -rng.uniform(4.0, 9.0), 0.0])),
            self.frame.direction(np.array([1.0, 0, 0])),
            self.frame.direction(np.array([0.0, 0, 1.0])),
            MipTile(foliage[:, :, :3]),
            rng.uniform(1.5, 3.0),
            0.6,
            np.ascontiguousarray(foliage[:, :, 3:]),
        )

    def _sky_and_light(self) -> tuple[Sky, Lighting]:
        """A sunny (65 %) or overcast sky with clouds, and the sun, ambient light and haze that go with it."""
        rng = self.rng
        if self.orchard:
            return self._orchard_sky_and_light()
        sunny = rng.random() < 0.65
        if sunny:
            zenith = np.array([0.25, 0.45, 0.85]) * rng.uniform(0.85, 1.1)
            horizon = np.array([0.76, 0.84, 0.93])
            cloud_rgb, cover = np.array([0.96, 0.96, 0.97]), rng.uniform(0.05, 0.5)
            sun_rgb = np.array([1.0, 0.95, 0.85]) * rng.uniform(0.75, 1.05)
            ambient = np.array([0.35, 0.40, 0.50]) * rng.uniform(0.8, 1.2)
        else:
            zenith = np.array([0.70, 0.72, 0.77]) * rng.uniform(0.9, 1.1)
            horizon = np.array([0.86, 0.87, 0.89])
            cloud_rgb, cover = np.array([0.62, 0.63, 0.66]), rng.uniform(0.3, 0.7)
            sun_rgb = np.array([1.0, 0.97, 0.92]) * rng.uniform(0.1, 0.25)
            ambient = np.array([0.75, 0.77, 0.80]) * rng.uniform(0.85, 1.1)
        elevation, azimuth = np.radians(rng.uniform(15.0, 70.0)), rng.uniform(0, 2 * np.pi)
        sun_world = np.array(
            [np.cos(elevation) * np.sin(azimuth), -np.sin(elevation), np.cos(elevation) * np.cos(azimuth)]
        )
        sky = Sky(
            self.frame.world_from_camera, zenith, horizon, cloud_rgb, cloud_tile(rng, cover), rng.uniform(0.05, 0.2)
        )
        light = Lighting(unit(self.frame.direction(sun_world)), sun_rgb, ambient, horizon, rng.uniform(60.0, 200.0))
        return sky, light

    def _orchard_sky_and_light(self) -> tuple[Sky, Lighting]:
        """The orchard's low warm sun or dim overcast (`orchard.orchard_light`), the sun from any azimuth."""
        rng = self.rng
        drawn = orchard_light(rng)
        elevation, azimuth = drawn.elevation_rad, rng.uniform(0, 2 * np.pi)
        sun_world = np.array(
            [np.cos(elevation) * np.sin(azimuth), -np.sin(elevation), np.cos(elevation) * np.cos(azimuth)]
        )
        sky = Sky(
            self.frame.world_from_camera,
            drawn.zenith,
            drawn.horizon,
            drawn.cloud_rgb,
            cloud_tile(rng, drawn.cover),
            rng.uniform(0.05, 0.2),
        )
        haze = rng.uniform(60.0, 200.0)
        return sky, Lighting(unit(self.frame.direction(sun_world)), drawn.sun_rgb, drawn.ambient, drawn.horizon, haze)

    def _row_behind(self, tile: MipTile, ground_y: float) -> None:
        """The next row of espalier trees, 4.5–8 m away along the camera's right (mask id 0, beyond the working
        range): upright trunks 1.2–2 m apart, each with level branches in tiers along the row."""
        rng = self.rng
        horizontal = unit(np.array([self.frame.forward[0], 0.0, self.frame.forward[2]]))
        side = np.array([horizontal[2], 0.0, -horizontal[0]])
        distance, spacing = rng.uniform(4.5, 8.0), rng.uniform(1.2, 2.0)
        reach = distance * self.tan_half_h + 2.0
        tint = np.full(3, rng.uniform(0.6, 0.9))
        for offset in np.arange(-reach + rng.uniform(0.0, spacing), reach, spacing):
            foot = distance * horizontal + offset * side
            foot[1] = ground_y
            r_ground = rng.uniform(0.06, 0.14)
            height = ground_y + rng.uniform(1.0, 2.5)
            self._cone(foot, UP, height, r_ground, 0.5 * r_ground, self._bark(tile, r_ground, tint), 0)
            for tier in np.arange(rng.uniform(0.4, 0.7), height - 0.3, rng.uniform(0.4, 0.6)):
                for direction in (side, -side):
                    length, r0 = rng.uniform(0.5, 0.9) * spacing, rng.uniform(0.01, 0.025)
                    start = foot + tier * UP
                    if norm3(self._axis_points(start, direction, length, 8)).min() < BRANCH_RANGE_M[1] + 0.2:
                        continue
                    b_axis = unit(direction + np.array([0.0, rng.uniform(-0.1, 0.05), 0.0]))
                    self._cone(start, b_axis, length, r0, 0.4 * r0, self._bark(tile, r0, tint), 0)

    def build(self) -> SceneDescription:
        """Draw the whole scene."""
        sky, light = self._sky_and_light()
        branches, ground_y = self._main_tree()
        tree_cones, tree_leaves = list(self.cones), list(self.leaves)
        self.cones, self.leaves = [], []
        bark = self._bark_tile()
        if self.orchard:
            self._row_behind(bark, ground_y)
        elif self.options.background_trees:
            self._background_trees(bark, ground_y)
        layers = [self._ground(ground_y), *self._tree_rows(ground_y, bark)]
        canopy = self._canopy()
        if canopy is not None:
            layers.append(canopy)
        exposure_target = float(self.rng.uniform(0.36, 0.5))
        if self.options.orchard_hardware or self.orchard:  # drawn last: without it a seed's scene is what it always was
            self._hardware(ground_y)
        return SceneDescription(
            self.pose,
            self.foliage,
            self.leaf_shape,
            tuple(tree_cones + self.cones),
            tuple(tree_leaves),
            tuple(layers),
            sky,
            light,
            tuple(branches),
            exposure_target,
            self.detail,
        )

    def _hardware(self, ground_y: float) -> None:
        """Trellis wires, posts, a stake and rods around the tree (`stereo.synth.hardware`), as background cones."""
        r_ground = self.trunk[3]
        for piece in orchard_hardware(self.rng, self.trunk_foot, r_ground, ground_y, self.frame.right):
            material = BarkMaterial(MipTile(piece.tile), 1, max(0.3, 2 * np.pi * piece.radius))
            self._cone(piece.base, piece.axis, piece.length, piece.radius, piece.radius, material, 0)


def build_scene(rng: np.random.Generator, camera: SynthCamera, options: SynthOptions) -> SceneDescription:
    """Draw one random tree scene for `camera` (all randomness from `rng`)."""
    return _SceneBuilder(rng, camera, options).build()
