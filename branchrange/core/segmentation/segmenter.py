"""Branch instances without a mask file: the `Segmenter` interface and a weight-free geometric one.

`Segmenter` is the one small interface a learned instance-segmentation model plugs into later: it
gets the rectified left image, the disparity and the camera, and returns `BranchMasks`.

`GeometricSegmenter` proposes branches from disparity and image evidence alone:
1. foreground = valid disparity whose depth lies in the working range;
2. depth edges (a relative depth jump between neighbours) cut the foreground, so a branch in front
   of the trunk or of another branch is separated from it;
3. per connected region, a morphological opening with a disk of the largest branch diameter (in
   pixels at that region's depth) keeps the thick parts: trunk and foliage blobs; what remains
   outside them is thin structure;
4. thin components that are long enough (metres) and elongated enough are branches; pixels that
   look like leaves (excess-green index) are not counted as branch;
5. the largest elongated thick part is reported as the trunk, so cut points know the base side.

Where it fails (by construction):
- branches that touch or cross in the image at the same depth merge into one instance (one line
  fit through both: a wrong axis or a dropped branch); forks stay one instance;
- branches thicker than `max_branch_diameter_m` are taken for trunk; a thin trunk or a sapling
  is taken for a branch;
- dense foliage around a branch hides it or, when the leaves are not green (autumn, dusk, IR),
  leaf clusters that happen to be elongated become false branches;
- branches seen end-on are not elongated and are missed;
- anything the stereo backend misses (textureless bark, thin branches below the matcher's
  resolution) is invisible to it; sgbm noise streaks can pass as thin structures;
- background at working-range depth (a hedge, a wall, the ground) becomes foreground and its thin
  parts can pass as branches; ground that meets the trunk's foot in the image joins the trunk's
  thick part and is reported as trunk with it (the synthetic "parallel" views show it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import cv2
import numpy as np

from branchrange.core.geometry import StereoGeometry, disparity_to_depth, valid_disparity
from branchrange.core.masks import DEFAULT_TRUNK_ID, BranchMasks
from branchrange.core.settings_check import Checks, Limit, Settings, in_physical_range


class SegmenterConfigError(ValueError):
    """A segmenter setting out of its range; the message names the key."""


@runtime_checkable
class Segmenter(Protocol):
    """Anything that turns a rectified left image and its disparity into branch instances."""

    name: str

    def segment(
        self, left: np.ndarray, disparity: np.ndarray, geometry: StereoGeometry, confidence: np.ndarray | None = None
    ) -> BranchMasks:
        """Instances for `left` (`uint8 H×W×3` RGB) and `disparity` (`float32 H×W` px)."""
        ...


def working_foreground(
    disparity: np.ndarray, geometry: StereoGeometry, confidence: np.ndarray | None, cfg: BuiltinSegmenterConfig
) -> tuple[np.ndarray, np.ndarray]:
    """(foreground `H×W` bool, depth `H×W` m, inf where invalid) of a built-in segmenter's settings `cfg`:
    valid, at least `min_confidence`, within [`min_range_m`, `max_range_m`], not on a depth edge
    (`depth_edge_ratio`) — what both built-in segmenters start from."""
    valid = valid_disparity(disparity)
    if confidence is not None:
        valid &= np.nan_to_num(confidence, nan=0.0) >= cfg.min_confidence
    depth = disparity_to_depth(disparity, geometry)
    depth[~valid] = np.inf
    foreground = valid & (depth >= cfg.min_range_m) & (depth <= cfg.max_range_m)
    foreground &= ~foreground_depth_edges(foreground, depth, cfg.depth_edge_ratio)
    return foreground, depth


@dataclass(frozen=True)
class BuiltinSegmenterConfig(Settings):
    """The settings both built-in segmenters share (metres unless named otherwise); each segmenter's
    config extends it, and may change its defaults.

    - `min_range_m`, `max_range_m`: the working range; nearer or farther pixels are background.
    - `max_branch_diameter_m`: thicker structure is trunk or foliage.
    - `min_branch_length_m`: shorter thin pieces are ignored.
    - `min_elongation`: length / mean width a branch must reach.
    - `depth_edge_ratio`: neighbours whose depths differ by more than this fraction are cut apart.
    - `min_confidence`: stereo confidence below this is treated as no depth.
    - `excess_green`: pixels with 2G − R − B above this (0..510) are leaves, not branch; < 0 = off.
    - `trunk_id`: the id the trunk gets in the returned instances.
    """

    min_range_m: float = 0.3
    max_range_m: float = 3.0
    max_branch_diameter_m: float = 0.08
    min_branch_length_m: float = 0.12
    min_elongation: float = 4.0
    depth_edge_ratio: float = 0.06
    min_confidence: float = 0.05
    excess_green: float = 60.0
    trunk_id: int = DEFAULT_TRUNK_ID

    section = "segmenter"
    error = SegmenterConfigError
    limits = {
        "min_range_m": Limit.physical("distance_m"),
        "max_range_m": Limit.physical("distance_m"),
        "max_branch_diameter_m": Limit(exclusive_minimum=0, expected="> 0 m"),
        "min_branch_length_m": Limit(exclusive_minimum=0, expected="> 0 m"),
        "min_elongation": Limit(minimum=1, expected="≥ 1 (length / width)"),
        "depth_edge_ratio": Limit(exclusive_minimum=0, expected="> 0 (relative depth jump)"),
        "min_confidence": Limit(minimum=0, maximum=1, expected="a confidence in [0, 1]"),
        "trunk_id": Limit(minimum=1, maximum=65535),
    }

    def checks(self) -> Checks:
        """The shared settings' ranges (the working range within the physical distance range); subclasses add theirs."""
        near_ok, distances = in_physical_range("distance_m", self.min_range_m)
        far_ok, _ = in_physical_range("distance_m", self.max_range_m)
        return {
            "min_range_m": (near_ok, distances),
            "max_range_m": (
                far_ok and self.max_range_m > self.min_range_m,
                f"> min_range_m ({self.min_range_m} m), {distances}",
            ),
            "trunk_id": (0 < self.trunk_id <= 65535, "an id in 1..65535"),
        }


@dataclass(frozen=True)
class GeometricSegmenterConfig(BuiltinSegmenterConfig):
    """`[segmenter.geometric]`, settings of `GeometricSegmenter`: the shared ones (`BuiltinSegmenterConfig`)
    at their defaults."""

    section = "segmenter.geometric"


def foreground_depth_edges(foreground: np.ndarray, depth: np.ndarray, ratio: float) -> np.ndarray:
    """Boolean `H×W`: the pixels of the boolean `H×W` `foreground` on a depth edge — whose depth (m, `H×W`,
    inf unknown) exceeds a foreground 4-neighbour's by more than `ratio` of the nearer one. Only the farther
    pixel of a pair is marked (the nearer keeps its full silhouette); a pixel of unknown depth beside a known
    one is the farther. Background neighbours count as unknown, so they mark nothing.

    Why per foreground pixel, not per frame pixel: the foreground is a few % of an HD720 frame, and the
    frame-wide comparison (four shifted `H×W` arrays) cost 12 ms a call in the roi mode's instance step."""
    height, width = foreground.shape
    pixels = np.flatnonzero(foreground)
    flat_foreground, flat_depth = foreground.ravel(), depth.ravel()
    own = flat_depth[pixels]
    column = pixels % width
    edge = np.zeros(len(pixels), dtype=bool)
    for step, inside in ((-width, pixels >= width), (width, pixels < (height - 1) * width)):
        _mark_farther(edge, inside, pixels + step, own, flat_foreground, flat_depth, ratio)
    for step, inside in ((-1, column > 0), (1, column < width - 1)):
        _mark_farther(edge, inside, pixels + step, own, flat_foreground, flat_depth, ratio)
    edges = np.zeros(foreground.shape, dtype=bool)
    edges.ravel()[pixels[edge]] = True
    return edges


def _mark_farther(
    edge: np.ndarray,
    inside: np.ndarray,
    neighbour: np.ndarray,
    own: np.ndarray,
    flat_foreground: np.ndarray,
    flat_depth: np.ndarray,
    ratio: float,
) -> None:
    """Set `edge` `(N,)` where a foreground pixel (depth `own` `(N,)`) lies farther than its neighbour at the
    flat index `neighbour` `(N,)` by more than `ratio` of the nearer depth; `inside` `(N,)`: the neighbour is
    in the frame."""
    near = neighbour[inside]
    other = np.where(flat_foreground[near], flat_depth[near], np.inf)
    mine = own[inside]
    with np.errstate(invalid="ignore"):  # inf − inf: two unknown depths are no edge
        jump = (np.abs(mine - other) > ratio * np.minimum(mine, other)) & (mine > other)
    edge[inside] |= jump


def elongation(component: np.ndarray) -> tuple[float, float]:
    """(length px, mean width px) of a boolean `H×W` region from its pixels' principal axis."""
    v, u = np.nonzero(component)
    return pixel_elongation(u, v)


def pixel_elongation(u: np.ndarray, v: np.ndarray) -> tuple[float, float]:
    """(length px, mean width px) of the pixels (u, v) `(N,)` along their principal axis."""
    pixels = np.stack([u, v], axis=1).astype(np.float64)
    centred = pixels - pixels.mean(axis=0)
    _, vectors = np.linalg.eigh(centred.T @ centred)
    s = centred @ vectors[:, -1]
    length = float(np.ptp(s)) + 1.0
    return length, len(pixels) / length


def leaf_pixels(left: np.ndarray, excess_green: float) -> np.ndarray:
    """Boolean `H×W`: pixels of `left` (RGB) whose excess-green index 2G − R − B exceeds the threshold (< 0: none)."""
    if excess_green < 0:
        return np.zeros(left.shape[:2], dtype=bool)
    rgb = left.astype(np.int16)
    return (2 * rgb[..., 1] - rgb[..., 0] - rgb[..., 2]) > excess_green


class GeometricSegmenter:
    """Weight-free branch proposals from depth: thin, elongated foreground in the working range."""

    name = "geometric"

    def __init__(self, config: GeometricSegmenterConfig = GeometricSegmenterConfig()) -> None:
        self.config = config

    def segment(
        self, left: np.ndarray, disparity: np.ndarray, geometry: StereoGeometry, confidence: np.ndarray | None = None
    ) -> BranchMasks:
        """Branch instances (1..K) and the trunk (`trunk_id`) for one rectified frame."""
        cfg = self.config
        disparity = np.asarray(disparity, dtype=np.float32)
        if left.shape[:2] != disparity.shape:
            raise ValueError(f"left image {left.shape[:2]} and disparity {disparity.shape} differ in size")
        foreground, depth = working_foreground(disparity, geometry, confidence, self.config)
        leaves = leaf_pixels(left, cfg.excess_green)
        labels = np.zeros(disparity.shape, dtype=np.int32)
        count, regions = cv2.connectedComponents(foreground.astype(np.uint8), connectivity=8)
        trunk_candidates: list[tuple[float, np.ndarray]] = []
        next_id = 1
        for region_id in range(1, count):
            region = regions == region_id
            z = float(np.median(depth[region]))
            radius_px = max(1, int(round(cfg.max_branch_diameter_m / 2 * geometry.focal_px / z)))
            disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1, 2 * radius_px + 1))
            thick = cv2.morphologyEx(region.astype(np.uint8), cv2.MORPH_OPEN, disk).astype(bool)
            if thick.any():
                length, width = elongation(thick)
                if length >= cfg.min_elongation * width / 2:
                    trunk_candidates.append((float(thick.sum()), thick))
            grown = cv2.dilate(thick.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5)))
            thin = region & ~grown.astype(bool) & ~leaves
            n_thin, thin_labels = cv2.connectedComponents(thin.astype(np.uint8), connectivity=8)
            for thin_id in range(1, n_thin):
                piece = thin_labels == thin_id
                if piece.sum() < 20:
                    continue
                length_px, width_px = elongation(piece)
                length_m = length_px * float(np.median(depth[piece])) / geometry.focal_px
                if length_m >= cfg.min_branch_length_m and length_px >= cfg.min_elongation * width_px:
                    labels[piece] = next_id
                    next_id += 1
        if trunk_candidates:
            trunk = max(trunk_candidates, key=lambda item: item[0])[1]
            labels[trunk & (labels == 0)] = cfg.trunk_id
        return BranchMasks(labels, cfg.trunk_id, self.name)
