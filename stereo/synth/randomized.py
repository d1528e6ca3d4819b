"""The randomized domain: scenes where every factor is drawn per scene, each with its own switch.

`render_randomized(seed, camera, switches)` draws a `ScenePlan` (every factor's value) and the
scene's geometry from `seed` alone — each factor from its own random stream, so switching one
factor off changes that factor and nothing else — ray-casts it with the renderer of
`stereo.synth.render`, develops both views as a camera would (`camera_effects`), and runs the
project's SGBM on the pair (`stereo_effects`). The same (seed, switches, camera) gives the same
bytes, so thousands of scenes can be cached by that key.

Labels (the convention of `stereo.synth.truth`, exact per pixel from the ray through each pixel
centre): the trees of the *near row* are the ones being pruned — their trunks and leaders are
`TRUNK_ID`, each first-order branch (a whole axis growing out of a trunk or leader, up to its tip)
gets its own instance id 1..K when any of it comes within the 4 m working range, and the shoots
growing from such a branch are `TWIG_ID`. A near-row branch entirely beyond 4 m, every tree in the
rows behind (however much they look like the near tree: they are the next rows, not this one),
posts, wires, pipes, nets, buildings, ground, fruit and sky are background (0); leaves and blossom
are `LEAF_ID`. The wood casts its shadow on the ground (`shadows`).
"""

from __future__ import annotations

import dataclasses
import zlib
from dataclasses import asdict, dataclass, field, fields

import cv2
import numpy as np

from stereo.synth import bark as bark_looks
from stereo.synth import camera_effects as effects
from stereo.synth.camera import SynthCamera
from stereo.synth.cones import BarkMaterial, Cone
from stereo.synth.growth import DEFAULT_FORM, FORM_NAMES, Skeleton, grow_tree
from stereo.synth.leaves import Leaf
from stereo.synth.lighting import DEFAULT_REGIME, LIGHT_REGIMES, draw_light
from stereo.synth.planes import PlaneLayer
from stereo.synth.primitives import norm3, unit
from stereo.synth.render import render_views
from stereo.synth.scene import CameraFrame, SceneDescription
from stereo.synth.season import SEASON_WEIGHTS, SEASONS, foliage, fruit_skin
from stereo.synth.shadows import ShadowedPlane, cast_on_ground
from stereo.synth.stereo_effects import Dropout, dropout_kind, dropped_out, sgbm_disparity
from stereo.synth.surroundings import (
    BACKDROPS,
    DEFAULT_COVER,
    GROUND_COVERS,
    buildings_layer,
    ground_layer,
    net_layer,
    structures,
    wood_layer,
)
from stereo.synth.textures import MipTile, detail_tile
from stereo.synth.truth import MAX_BRANCH_ID, TRUNK_ID, TWIG_ID

#: pruning-target branches come within this range (m) of the camera, as in `stereo.synth.scene`
WORKING_RANGE_M = 4.0
#: row spacing (m) of each form: trees in a row stand this far apart
_SPACING_M = {
    "central_leader": (1.2, 2.5),
    "tall_spindle": (0.7, 1.2),
    "open_v": (0.8, 1.5),
    "espalier": (2.0, 3.5),
    "vase": (3.0, 5.0),
    "park": (5.0, 9.0),
    "forest": (3.0, 7.0),
    "whip": (0.8, 1.5),
    "gnarled": (4.0, 8.0),
}
#: where the camera stands (`RandomizedSwitches.viewpoint`): among the branches, or on a ground robot
VIEWPOINTS = ("crown", "ground")
#: no wood comes nearer the lens than this (m): a shoot across the lens would hide the scene
MIN_RANGE_M = 0.3
#: the exposure gain of a daylit scene (the renderer's linear colours are dim): the sensor's analogue gain, which
#: scales its noise, is the exposure gain over this, at least 1
NOMINAL_GAIN = 2.0
#: the most trees grown for the rows behind (they reuse a few grown templates) and nodes per tree there
_MAX_TREES_BEHIND = 30
_BEHIND_NODES = 220


@dataclass(frozen=True)
class RandomizedSwitches:
    """Which factors are drawn per scene (True) or held at a neutral value (False), and their ranges.

    - `tree_form`: the training system or kind of tree (`growth.FORM_NAMES`); off: central leader.
    - `tree_count`: neighbours of the near tree in its row (one to many trees in view); off: one tree.
    - `bark`: bark colour, relief, lenticels, lichen, moss, wounds, wet (`bark`); off: plain grey-brown.
    - `rows_behind`: rows of trees `rows_behind_m` behind the near row, grown like it; off: none.
    - `ground_cover`: grass, dry grass, bare soil, mulch or snow; off: grass.
    - `backdrop`: a far wood, buildings, or open land to the horizon; off: a wood.
    - `structures`: posts, wires, stakes, rods, irrigation pipes, hail netting overhead and side nets; off: none.
    - `season`: dormant, blossom, leaf, fruit or autumn (`season.SEASON_WEIGHTS`); off: dormant.
    - `light`: sun, backlight, low sun, overcast or dusk (`lighting`); off: sun.
    - `exposure_drift`: auto-exposure off by up to `exposure_drift_ev` and white balance by up to
      `white_balance_drift` per channel; off: exact metering, neutral white balance.
    - `noise`: ZED Mini-like read and shot noise scaled by the analogue gain (`NOMINAL_GAIN`); off: none.
    - `motion_blur`: a streak of up to `motion_blur_px`; off: none.
    - `defocus`: depth of field up to `defocus_px_per_dioptre`; off: all sharp.
    - `vignetting`: up to `vignetting_strength` darkening in the corners; off: none.
    - `compression`: JPEG (quality `jpeg_quality`) or H.264-like (step `h264_step`) or none; off: none.
    - `capture`: captured at 640×360-like or at HD720 and scaled down (noise and artefacts at that
      size); off: at the output size.
    - `dropout`: disparity dropout, whole frame or regions (`dropout_rates`); off: none.
    - `viewpoint`: where the camera stands — among the branches (a drone in the crown: the neutral view) or, in
      `ground_view_share` of the scenes, on a ground robot `ground_camera_height_m` above the ground and
      `ground_view_m` from the near tree, level to 20° up: the whole tree small in view, the ground in front
      nearer than the tree and the tree as deep as the row beside it; off: among the branches.
    """

    tree_form: bool = True
    tree_count: bool = True
    bark: bool = True
    rows_behind: bool = True
    ground_cover: bool = True
    backdrop: bool = True
    structures: bool = True
    season: bool = True
    light: bool = True
    exposure_drift: bool = True
    noise: bool = True
    motion_blur: bool = True
    defocus: bool = True
    vignetting: bool = True
    compression: bool = True
    capture: bool = True
    dropout: bool = True
    viewpoint: bool = True
    rows_behind_m: tuple[float, float] = (1.5, 15.0)
    near_row_m: tuple[float, float] = (0.6, 2.5)
    exposure_drift_ev: float = 0.7
    white_balance_drift: float = 0.1
    motion_blur_px: float = 8.0
    defocus_px_per_dioptre: float = 3.0
    vignetting_strength: float = 0.5
    jpeg_quality: tuple[int, int] = (35, 95)
    h264_step: tuple[float, float] = (4.0, 24.0)
    dropout_rates: Dropout = field(default_factory=Dropout)
    ground_view_share: float = 0.35
    ground_view_m: tuple[float, float] = (1.5, 4.0)
    ground_camera_height_m: tuple[float, float] = (0.4, 1.5)

    def __post_init__(self) -> None:
        low, high = self.rows_behind_m
        if not 0.5 <= low <= high <= 40.0:
            raise ValueError(f"rows_behind_m must be (low, high) within 0.5–40 m, low ≤ high, got {self.rows_behind_m}")
        if not 0.3 <= self.near_row_m[0] <= self.near_row_m[1] <= 6.0:
            raise ValueError(f"near_row_m must be (low, high) within 0.3–6 m, low ≤ high, got {self.near_row_m}")
        if not 0.0 <= self.ground_view_share <= 1.0:
            raise ValueError(f"ground_view_share must lie in 0–1, got {self.ground_view_share}")
        if not 0.5 <= self.ground_view_m[0] <= self.ground_view_m[1] <= 10.0:
            raise ValueError(f"ground_view_m must be (low, high) within 0.5–10 m, low ≤ high, got {self.ground_view_m}")
        if not 0.1 <= self.ground_camera_height_m[0] <= self.ground_camera_height_m[1] <= 3.0:
            raise ValueError(
                "ground_camera_height_m must be (low, high) within 0.1–3 m, low ≤ high, "
                f"got {self.ground_camera_height_m}"
            )
        if not 1 <= self.jpeg_quality[0] <= self.jpeg_quality[1] <= 100:
            raise ValueError(f"jpeg_quality must be (low, high) within 1–100, got {self.jpeg_quality}")

    @classmethod
    def only(cls, *names: str) -> RandomizedSwitches:
        """Every factor off except `names` (a factor's own effect, in tests and previews)."""
        factors = switch_names()
        unknown = sorted(set(names) - set(factors))
        if unknown:
            raise ValueError(f"unknown factor(s) {unknown}; known factors: {', '.join(factors)}")
        flags: dict[str, object] = {name: name in names for name in factors}
        return dataclasses.replace(cls(), **flags)  # type: ignore[arg-type]


def switch_names() -> tuple[str, ...]:
    """The factors' switches (the boolean fields of `RandomizedSwitches`)."""
    return tuple(f.name for f in fields(RandomizedSwitches) if f.type in ("bool", bool))


@dataclass(frozen=True)
class ScenePlan:
    """Every factor's value for one scene (drawn by `draw_plan`; what a cache or a report keys on)."""

    seed: int
    form: str
    bark: bool
    neighbours: int
    row_gaps_m: tuple[float, ...]
    ground_cover: str
    backdrop: str
    structures: bool
    net: str
    season: str
    light: str
    exposure_ev: float
    white_balance: tuple[float, float, float]
    read_noise: float
    shot_noise: float
    motion_blur_px: float
    motion_angle_rad: float
    defocus_px_per_dioptre: float
    vignetting: float
    compression: str
    compression_level: float
    capture: str
    dropout: str
    viewpoint: str


def _stream(seed: int, factor: str, part: int = 0) -> np.random.Generator:
    """The random stream of one factor of one scene (independent of every other factor's)."""
    return np.random.default_rng([int(seed), zlib.crc32(factor.encode()), part])


def draw_plan(seed: int, switches: RandomizedSwitches) -> ScenePlan:
    """Every factor's value for scene `seed` (pure: the same arguments give the same plan)."""
    s = switches

    def pick(factor: str, on: bool, options: tuple[str, ...], neutral: str, p: tuple[float, ...] | None = None) -> str:
        return str(_stream(seed, factor).choice(options, p=p)) if on else neutral

    rows = _stream(seed, "rows_behind")
    gaps: list[float] = []
    if s.rows_behind:
        distance = rows.uniform(s.rows_behind_m[0], min(s.rows_behind_m[0] + 3.0, s.rows_behind_m[1]))
        spacing = rows.uniform(1.5, 5.0)
        while distance <= s.rows_behind_m[1] and len(gaps) < 4:
            gaps.append(float(distance))
            distance += spacing
    exposure, noise, blur = _stream(seed, "exposure_drift"), _stream(seed, "noise"), _stream(seed, "motion_blur")
    compression = _stream(seed, "compression")
    codec = str(compression.choice(["none", "jpeg", "h264"], p=[0.2, 0.4, 0.4])) if s.compression else "none"
    level = {
        "none": 0.0,
        "jpeg": float(compression.integers(s.jpeg_quality[0], s.jpeg_quality[1] + 1)),
        "h264": float(compression.uniform(*s.h264_step)),
    }[codec]
    drift = exposure.uniform(-1.0, 1.0, 4)
    balance = (1.0 + drift[1:] * s.white_balance_drift) if s.exposure_drift else np.ones(3)
    return ScenePlan(
        int(seed),
        pick("tree_form", s.tree_form, FORM_NAMES, DEFAULT_FORM),
        s.bark,
        int(_stream(seed, "tree_count").integers(0, 6)) if s.tree_count else 0,
        tuple(gaps),
        pick("ground_cover", s.ground_cover, tuple(GROUND_COVERS), DEFAULT_COVER),
        pick("backdrop", s.backdrop, BACKDROPS, "wood", (0.5, 0.25, 0.25)),
        s.structures and _stream(seed, "structures").random() < 0.7,
        str(_stream(seed, "structures", 1).choice(["none", "hail", "side"], p=[0.6, 0.25, 0.15]))
        if s.structures
        else "none",
        pick("season", s.season, SEASONS, "dormant", SEASON_WEIGHTS),
        pick("light", s.light, LIGHT_REGIMES, DEFAULT_REGIME, (0.3, 0.2, 0.2, 0.2, 0.1)),
        float(drift[0] * s.exposure_drift_ev) if s.exposure_drift else 0.0,
        (float(balance[0]), float(balance[1]), float(balance[2])),
        float(noise.uniform(0.5, 3.0)) if s.noise else 0.0,
        float(noise.uniform(0.02, 0.2)) if s.noise else 0.0,
        float(blur.uniform(0.0, s.motion_blur_px) * (blur.random() < 0.6)) if s.motion_blur else 0.0,
        float(blur.uniform(0.0, np.pi)),
        float(_stream(seed, "defocus").uniform(0.0, s.defocus_px_per_dioptre)) if s.defocus else 0.0,
        float(_stream(seed, "vignetting").uniform(0.0, s.vignetting_strength)) if s.vignetting else 0.0,
        codec,
        level,
        pick("capture", s.capture, ("vga", "hd720"), "vga"),
        dropout_kind(_stream(seed, "dropout"), s.dropout_rates) if s.dropout else "none",
        pick("viewpoint", s.viewpoint, VIEWPOINTS, "crown", (1.0 - s.ground_view_share, s.ground_view_share)),
    )


@dataclass(frozen=True)
class RandomizedSample:
    """One randomized scene as rendered and as the segmenter would see it.

    - `left`, `right`: uint8 RGB `H×W×3` after the camera effects;
    - `disparity`: float32 `H×W` px, SGBM of the pair after dropout (0 = invalid);
    - `exact_disparity`: float32 `H×W` px, `f·B/Z` of the left view (0 on sky);
    - `instances`: uint16 `H×W` renderer ids (see the module docstring); `plan`: the factors drawn.
    """

    left: np.ndarray
    right: np.ndarray
    disparity: np.ndarray
    exact_disparity: np.ndarray
    instances: np.ndarray
    plan: ScenePlan


class BranchLabels:
    """Hands out instance ids to the near row's first-order branches, 1..MAX_BRANCH_ID."""

    def __init__(self) -> None:
        self.next_id = 1

    def take(self) -> int:
        """The next id (the last one again once all are taken)."""
        taken = min(self.next_id, MAX_BRANCH_ID)
        self.next_id += 1
        return taken


@dataclass
class _Builder:
    """Collects the cones and leaves of one scene in the left camera frame."""

    camera: SynthCamera
    frame: CameraFrame
    skin: MipTile
    cones: list[Cone] = field(default_factory=list)
    leaves: list[Leaf] = field(default_factory=list)

    def tree(
        self,
        skeleton: Skeleton,
        foot: np.ndarray,
        yaw: float,
        materials: tuple[BarkMaterial, BarkMaterial],
        labels: BranchLabels | None,
        season: tuple[np.random.Generator, str, int],
    ) -> None:
        """Place `skeleton` with its foot at world `foot`, turned `yaw` rad about the vertical; label it when
        `labels` is given (a near-row tree), else background; `season`: (stream, season, leaves per tip)."""
        turn = np.array([[np.cos(yaw), 0.0, -np.sin(yaw)], [0.0, 1.0, 0.0], [np.sin(yaw), 0.0, np.cos(yaw)]])
        start = self.frame.point(foot + skeleton.start @ turn.T)
        end = self.frame.point(foot + skeleton.end @ turn.T)
        ids = near_row_ids(skeleton, start, end, labels) if labels is not None else np.zeros(len(start), np.int64)
        # segments thinner than a fifth of a pixel across (far twigs) are left out: they cost casting, not looks
        visible = skeleton.r0 * self.camera.focal_px / np.maximum(np.minimum(start[:, 2], end[:, 2]), 1e-3) >= 0.2
        clear = _distance_to_origin(start, end) >= MIN_RANGE_M + skeleton.r0
        keep = np.flatnonzero(visible & clear & (np.maximum(start[:, 2], end[:, 2]) > 0.05))
        old, young = materials
        for k in keep:
            axis = end[k] - start[k]
            length = float(np.linalg.norm(axis))
            if length < 1e-4:
                continue
            axis /= length
            # reach back into the parent by the radius so bends leave no gap between segments
            back = min(float(skeleton.r0[k]), 0.3 * length)
            material = old if skeleton.r0[k] > 0.012 else young
            self.cones.append(
                Cone(
                    start[k] - back * axis,
                    axis,
                    length + back,
                    float(skeleton.r0[k]),
                    float(skeleton.r1[k]),
                    _wrapped(material, float(skeleton.r0[k])),
                    int(ids[k]),
                )  # fmt: skip
            )
        rng, name, per_tip = season
        tips = np.flatnonzero(skeleton.tip)
        headings = end[tips] - start[tips]
        leaves, fruit = foliage(rng, name, end[tips], headings / np.maximum(norm3(headings), 1e-9)[:, None], per_tip,
                               self.skin)  # fmt: skip
        self.leaves.extend(leaf for leaf in leaves if leaf.centre[2] > 0.1)
        self.cones.extend(cone for cone in fruit if cone.base[2] > 0.1)


def near_row_ids(skeleton: Skeleton, start: np.ndarray, end: np.ndarray, labels: BranchLabels) -> np.ndarray:
    """Mask id `(N,)` of each segment of a near-row tree whose segments run `start` → `end` (`(N, 3)` each,
    camera frame, m): trunk and leaders `TRUNK_ID`; each first-order branch with any segment within
    `WORKING_RANGE_M` a new id from `labels`, its shoots `TWIG_ID`; branches wholly beyond the range, with their
    shoots, 0."""
    ids = np.zeros(len(skeleton.start), dtype=np.int64)
    ids[skeleton.order == 0] = TRUNK_ID
    root = skeleton.first_order_root
    near = np.minimum(norm3(start), norm3(end)) <= WORKING_RANGE_M
    for axis in np.unique(root[root >= 0]):
        mine = root == axis
        if not (near & mine & (skeleton.order == 1)).any():
            continue
        ids[mine & (skeleton.order == 1)] = labels.take()
        ids[mine & (skeleton.order > 1)] = TWIG_ID
    return ids


def _distance_to_origin(start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """`(N,)` distance (m) from the camera to each segment `start`→`end` (`(N, 3)` each)."""
    along = end - start
    t = np.clip(-np.sum(start * along, axis=1) / np.maximum(np.sum(along * along, axis=1), 1e-12), 0.0, 1.0)
    return norm3(start + t[:, None] * along)


def _wrapped(material: BarkMaterial, radius: float) -> BarkMaterial:
    """`material` wrapped on a cylinder of `radius` m (about 12 cm of bark per tile round a trunk)."""
    around = int(np.clip(round(2 * np.pi * radius / 0.12), 1, 12))
    return BarkMaterial(material.tile, around, 2.5 * 2 * np.pi * radius / around, material.tint)


def _materials(rng: np.random.Generator, on: bool) -> tuple[BarkMaterial, BarkMaterial]:
    """Old-wood and young-shoot bark of one tree (`bark`), random or plain."""
    look = bark_looks.draw_look(rng) if on else bark_looks.plain_look()
    old = MipTile(bark_looks.old_wood_tile(rng, look))
    young = MipTile(bark_looks.young_wood_tile(rng, look))
    return BarkMaterial(old, 1, 0.3), BarkMaterial(young, 1, 0.3)


def build_randomized_scene(plan: ScenePlan, camera: SynthCamera, switches: RandomizedSwitches) -> SceneDescription:
    """The geometry, light and background of `plan`'s scene, in the left camera frame."""
    seed = plan.seed
    layout = _stream(seed, "layout")
    trees = _stream(seed, "trees")
    near = grow_tree(trees, plan.form)
    height = float(-near.end[:, 1].min())
    lowest_branch = float(-near.start[near.order == 1, 1].max()) if (near.order == 1).any() else 0.5 * height
    # the drone flies among the branches: from just under the crown to near the top
    ground_y = float(np.clip(layout.uniform(0.6 * lowest_branch, 0.9 * height), 0.4, 14.0))
    pitch, roll = np.radians(layout.uniform(-30.0, 35.0)), np.radians(layout.uniform(-5.0, 5.0))
    view = _stream(seed, "viewpoint", 1)  # a ground robot's pose replaces the crown's, whose draws stay as they were
    if plan.viewpoint == "ground":
        ground_y = float(view.uniform(*switches.ground_camera_height_m))
        pitch = np.radians(view.uniform(0.0, 20.0))
    frame = CameraFrame(pitch, roll)
    builder = _Builder(camera, frame, fruit_skin(_stream(seed, "season", 3)))
    yaw_row = np.radians(layout.uniform(-35.0, 35.0))
    row_axis = np.array([np.cos(yaw_row), 0.0, np.sin(yaw_row)])
    distance = layout.uniform(*switches.near_row_m) + float(near.r0.max())
    if plan.viewpoint == "ground":
        distance = float(view.uniform(*switches.ground_view_m)) + float(near.r0.max())
    tan_half = (camera.width / 2) / camera.focal_px
    lateral = layout.uniform(-0.5, 0.5) * distance * tan_half
    foot = np.array([0.0, ground_y, distance]) + lateral * row_axis / max(row_axis[0], 0.5)
    spacing = layout.uniform(*_SPACING_M[plan.form])
    season_rng = _stream(seed, "season", 1)
    bark_rng = _stream(seed, "bark", 1)
    labels = BranchLabels()
    materials = _materials(bark_rng, switches.bark)
    builder.tree(near, foot, layout.uniform(0, 2 * np.pi), materials, labels, (season_rng, plan.season, 6))
    for k in range(1, plan.neighbours + 1):  # neighbours alternate left and right of the near tree
        side = (1 if k % 2 else -1) * ((k + 1) // 2)
        skeleton = grow_tree(trees, plan.form)
        spot = foot + side * spacing * row_axis + layout.normal(0.0, 0.1, 3) * np.array([1.0, 0.0, 1.0])
        builder.tree(skeleton, spot, layout.uniform(0, 2 * np.pi), materials, labels, (season_rng, plan.season, 6))
    _rows_behind(builder, plan, foot, row_axis, spacing, switches, tan_half)
    light = draw_light(_stream(seed, "light", 1), plan.light, frame.world_from_camera, 0.0)
    sky = light.sky
    if plan.net == "hail":
        veil = _stream(seed, "structures", 4)
        shade = np.full(3, 0.05) if veil.random() < 0.5 else np.full(3, 0.85)  # black or white netting
        sky = dataclasses.replace(sky, veil_rgb=shade, veil_opacity=float(veil.uniform(0.2, 0.5)))
    layers = _layers(plan, frame, ground_y, distance)
    if plan.structures:
        for piece in structures(_stream(seed, "structures", 2), foot, float(near.r0.max()), ground_y, row_axis):
            material = BarkMaterial(MipTile(piece.tile), 1, max(0.3, 2 * np.pi * piece.radius))
            base, axis = frame.point(piece.base), unit(frame.direction(piece.axis))
            builder.cones.append(Cone(base, axis, piece.length, piece.radius, piece.radius, material, 0))
    layers[0] = ShadowedPlane.of(layers[0], cast_on_ground(builder.cones, layers[0], light.lighting.sun_direction))
    return SceneDescription(
        "randomized",
        plan.season,
        "broad",
        tuple(builder.cones),
        tuple(builder.leaves),
        tuple(layers),
        sky,
        light.lighting,
        (),
        light.exposure_target,
        MipTile(detail_tile(season_rng)),
    )


def _rows_behind(
    builder: _Builder,
    plan: ScenePlan,
    foot: np.ndarray,
    row_axis: np.ndarray,
    spacing: float,
    switches: RandomizedSwitches,
    tan_half: float,
) -> None:
    """Rows of trees of the near tree's form, `plan.row_gaps_m` behind it, across the whole view (background)."""
    if not plan.row_gaps_m:
        return
    rng = _stream(plan.seed, "rows_behind", 1)
    templates = [grow_tree(rng, plan.form, _BEHIND_NODES) for _ in range(3)]
    materials = _materials(rng, switches.bark)  # one cultivar a row, like the near row's own
    season_rng = _stream(plan.seed, "season", 2)
    across = np.array([-row_axis[2], 0.0, row_axis[0]])
    placed = 0
    for gap in plan.row_gaps_m:
        centre = foot + gap * across
        reach = float(centre[2]) * tan_half + 3.0
        offsets = np.arange(-reach + rng.uniform(0, spacing), reach, spacing)
        for offset in offsets:
            if placed >= _MAX_TREES_BEHIND:
                return
            spot = centre + offset * row_axis
            skeleton = templates[int(rng.integers(len(templates)))]
            builder.tree(skeleton, spot, rng.uniform(0, 2 * np.pi), materials, None, (season_rng, plan.season, 3))
            placed += 1


def _layers(plan: ScenePlan, frame: CameraFrame, ground_y: float, distance: float) -> list[PlaneLayer]:
    """Ground, backdrop and net of `plan`."""
    rng = _stream(plan.seed, "ground_cover", 1)
    layers = [ground_layer(rng, plan.ground_cover, frame, ground_y)]
    backdrop = _stream(plan.seed, "backdrop", 1)
    far = distance + (plan.row_gaps_m[-1] if plan.row_gaps_m else 0.0) + backdrop.uniform(10.0, 40.0)
    if plan.backdrop == "wood":
        layers.append(wood_layer(backdrop, frame, ground_y, far))
    elif plan.backdrop == "buildings":
        layers.append(buildings_layer(backdrop, frame, ground_y, far))
    if plan.net == "side":
        layers.append(net_layer(_stream(plan.seed, "structures", 3), frame, ground_y, distance))
    return layers


def render_randomized(
    seed: int,
    camera: SynthCamera | None = None,
    switches: RandomizedSwitches | None = None,
    supersample: int = 2,
    threads: int = 1,
) -> RandomizedSample:
    """Render randomized scene `seed` with `camera` (default ZED Mini at 640×360) under `switches` (default
    every factor on); the same arguments give the same bytes."""
    camera = camera if camera is not None else SynthCamera.zed_mini(640, 360)
    switches = switches if switches is not None else RandomizedSwitches()
    plan = draw_plan(seed, switches)
    scene = build_randomized_scene(plan, camera, switches)
    views = render_views(scene, camera, supersample, threads)
    gain = effects.metered_gain(views.left, scene.exposure_target) * 2.0**plan.exposure_ev
    noise = _stream(seed, "noise", 1)
    left, right = (
        _developed(image, depth, plan, gain, noise, float(np.median(views.depth[np.isfinite(views.depth)]))
                   if np.isfinite(views.depth).any() else 5.0)
        for image, depth in ((views.left, views.depth), (views.right, views.right_depth))
    )  # fmt: skip
    max_disp = max(16, 16 * round(camera.width * 128 / 640 / 16))
    disparity = sgbm_disparity(left, right, max_disp)
    disparity = dropped_out(disparity, _stream(seed, "dropout", 1), plan.dropout, switches.dropout_rates)
    return RandomizedSample(left, right, disparity, camera.disparity_from_depth(views.depth), views.ids, plan)


def _developed(
    image: np.ndarray, depth: np.ndarray, plan: ScenePlan, gain: float, noise: np.random.Generator, focus_m: float
) -> np.ndarray:
    """One rendered view (linear float32 `H×W×3`) → uint8 RGB as the camera of `plan` would record it."""
    out = effects.exposed(image, gain, np.array(plan.white_balance))
    if plan.vignetting > 0:
        out = effects.vignetted(out, plan.vignetting)
    if plan.defocus_px_per_dioptre > 0:
        out = effects.defocused(out, depth, focus_m, plan.defocus_px_per_dioptre * image.shape[1] / 640)
    out = effects.motion_blurred(out, plan.motion_blur_px * image.shape[1] / 640, plan.motion_angle_rad)
    height, width = out.shape[:2]
    if plan.capture == "hd720":
        out = cv2.resize(out, (2 * width, 2 * height), interpolation=cv2.INTER_LINEAR)
    if plan.read_noise > 0:
        out = effects.noisy(out, noise, plan.read_noise, plan.shot_noise, max(1.0, gain / NOMINAL_GAIN))
    recorded = effects.quantised(out)
    if plan.compression == "jpeg":
        recorded = effects.jpeg_compressed(recorded, int(plan.compression_level))
    elif plan.compression == "h264":
        recorded = effects.h264_like(recorded, plan.compression_level)
    if plan.capture == "hd720":
        recorded = cv2.resize(recorded, (width, height), interpolation=cv2.INTER_AREA)
    return recorded


def plan_summary(plan: ScenePlan) -> dict[str, object]:
    """`plan` as JSON-ready values (what a written sample's side file records)."""
    return asdict(plan)
