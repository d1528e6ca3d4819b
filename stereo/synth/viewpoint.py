"""A drawn scene seen from another camera pose: its geometry carried rigidly into that camera's frame.

`build_scene` draws everything in the frame of the camera it was drawn for (the *scene frame*:
x right, y down, z forward, metres). A camera elsewhere — at `position` (m, scene frame) with
orientation `rotation` (3×3, scene ← camera: `X_scene = rotation · X_cam + position`) — sees
the same surfaces at `X_cam = rotationᵀ · (X_scene − position)`. Carrying the surfaces (cones,
leaves, planes, sun, sky orientation, branch truth) into that frame lets the renderer, which
casts rays from the origin along +z, draw any viewpoint without drawing the tree again; its
textures stay anchored to the surfaces, so a moving camera sees the same bark in every frame.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable

import numpy as np

from stereo.synth.camera import SynthCamera
from stereo.synth.cones import CLIP_Z_M, Cone
from stereo.synth.leaves import Leaf
from stereo.synth.scene import SceneDescription
from stereo.synth.truth import BranchTruth

#: A map of `(3,)` or `(N, 3)` scene-frame vectors into the camera frame.
ToCamera = Callable[[np.ndarray], np.ndarray]


def _vector(values: np.ndarray) -> tuple[float, float, float]:
    """A 3-vector as the plain-float tuple `BranchTruth` stores."""
    return float(values[0]), float(values[1]), float(values[2])


def _rows(vectors: Iterable[np.ndarray]) -> np.ndarray:
    """3-vectors stacked as float64 `(N, 3)` rows (`(0, 3)` for none)."""
    return np.array(list(vectors), dtype=np.float64).reshape(-1, 3)


def scene_in_camera(
    scene: SceneDescription, rotation: np.ndarray, position: np.ndarray, camera: SynthCamera
) -> SceneDescription:
    """`scene` (scene frame) carried into the frame of a camera at `position` `(3,)` m with `rotation` `(3, 3)`.

    Leaf blades reaching nearer than `CLIP_Z_M` to the camera's plane are dropped (the cones clip
    themselves there): a camera flying through the crown would otherwise cast every sample against
    blades straddling its plane. The branch truth is carried along and its `cut_pixel` re-projected
    into the left image of `camera` (NaN for a cut point behind the camera).
    """
    rotation = np.asarray(rotation, dtype=np.float64)
    position = np.asarray(position, dtype=np.float64)

    def point(p: np.ndarray) -> np.ndarray:
        return (np.asarray(p) - position) @ rotation

    def direction(d: np.ndarray) -> np.ndarray:
        return np.asarray(d) @ rotation

    # one matrix product per kind of vector, not one per object: foliage scenes hold thousands of them
    bases, axes = point(_rows(c.base for c in scene.cones)), direction(_rows(c.axis for c in scene.cones))
    cones = tuple(
        Cone(base=base, axis=axis, length=c.length, r0=c.r0, r1=c.r1, material=c.material, instance_id=c.instance_id)
        for c, base, axis in zip(scene.cones, bases, axes)
    )
    centres = point(_rows(leaf.centre for leaf in scene.leaves))
    normals, e1s = (direction(_rows(getattr(leaf, name) for leaf in scene.leaves)) for name in ("normal", "e1"))
    leaves = tuple(
        Leaf(
            centre=centre,
            normal=normal,
            e1=e1,
            half_length=leaf.half_length,
            half_width=leaf.half_width,
            colour=leaf.colour,
            instance_id=leaf.instance_id,
        )
        for leaf, centre, normal, e1 in zip(scene.leaves, centres, normals, e1s)
        if centre[2] - np.hypot(leaf.half_length, leaf.half_width) >= CLIP_Z_M
    )
    layers = tuple(
        dataclasses.replace(layer, point=point(layer.point), eu=direction(layer.eu), ev=direction(layer.ev))
        for layer in scene.layers
    )
    sky = dataclasses.replace(scene.sky, world_from_camera=scene.sky.world_from_camera @ rotation)
    lighting = dataclasses.replace(scene.lighting, sun_direction=direction(scene.lighting.sun_direction))
    branches = tuple(_branch_in_camera(branch, point, direction, camera) for branch in scene.branches)
    return dataclasses.replace(
        scene, cones=cones, leaves=leaves, layers=layers, sky=sky, lighting=lighting, branches=branches
    )


def _branch_in_camera(branch: BranchTruth, point: ToCamera, direction: ToCamera, camera: SynthCamera) -> BranchTruth:
    """One branch's truth in the camera frame, its cut pixel re-projected (visibility is the renderer's to fill)."""
    cut = point(branch.cut_point_m)
    pixel = camera.project(cut[None, :])[0] if cut[2] > 0 else np.full(2, np.nan)
    return dataclasses.replace(
        branch,
        base_m=_vector(point(branch.base_m)),
        direction=_vector(direction(branch.direction)),
        cut_point_m=_vector(cut),
        cut_pixel=(float(pixel[0]), float(pixel[1])),
        cut_visible=False,
        mask_pixels=0,
    )
