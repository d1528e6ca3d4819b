"""The segmenter on real orchard trees with depth (`../shared/data/real_orchard_rgbd`): does it find the trunk?

Each sample there is one 512×512 RGBA PNG, a 2×2 grid of 256×256 tiles: winter and summer images (RGB, the
alpha channel an 8-bit relative depth growing with distance, 0 = none) over their hand masks (white = the trunk
and the two main leaders of the tree in front; side branches, trees behind, posts and wires are not labelled).
The set is a test set: nothing here trains or tunes on it.

Per sample and season the segmenter runs on the image with two disparities:
- 'depth': a relative disparity 1 / depth where depth > 0, scaled so that the median over the labelled tree is
  `TREE_MEDIAN_DISPARITY_PX` (the scale is picked with the mask — allowed for a measurement, a robot would not
  have it), validity (the confidence) 1 where depth > 0 and 0 elsewhere;
- 'none': no disparity at all (every pixel invalid): what the image alone gives.
Geometry: the ZED Mini scaled to the tile (f 128 px, B 0.063 m), so the tree's 8 px stand about 1 m away.

Frame size: each tile is first enlarged to `frame_width` px (default `PRODUCT_FRAME_WIDTH`, 640: the smallest
frame the product runs on — 640×360 from the ZED Mini — where that geometry's focal length is the camera's own
320 px), the image linearly, depth and mask by nearest neighbour, and the tree's median disparity and the far
distance grow with it: the scene as the camera would hand it to the segmenter. A 256 px tile as it is shows every
stem 2.5 times thinner than any frame the product sees (`frame_width` 256 keeps the tiles as they are).

Counted per image, as pixels: the labelled ones (the mask), those of them the final masks call trunk or branch
('found'); the far ones (more than `FAR_PX` px from the mask by a distance transform: posts, wires, grass, soil,
sky) called trunk and called branch. Side branches near the tree are neither: only the trunk is judged far from
the mask; branch there is reported. For the learned segmenter the network's own arg-max before its instance step
is counted too ('network'). A season's shares pool its pixels over the samples.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from branchrange.core.geometry import StereoGeometry
from branchrange.core.masks import BranchMasks
from branchrange.core.segmentation.learned import LearnedSegmenter
from branchrange.core.segmentation.network_input import CLASSES
from branchrange.core.segmentation.segmenter import Segmenter

REAL_ORCHARD = Path(__file__).resolve().parents[2] / "shared" / "data" / "real_orchard_rgbd"
SEASONS = ("winter", "summer")
TILE = 256
#: the labelled tree's median relative disparity (px), as the issue measured the shipped model
TREE_MEDIAN_DISPARITY_PX = 8.0
#: pixels farther than this from the mask count as surely not the labelled structure (px)
FAR_PX = 10.0
DISPARITY_MODES = ("depth", "none")
#: the smallest frame width the product runs on (px): the ZED Mini's 640×360
PRODUCT_FRAME_WIDTH = 640


def tile_geometry(width: int = TILE) -> StereoGeometry:
    """The ZED Mini at 1920 px (f 960 px, B 0.063 m) scaled to a square frame `width` px wide."""
    return StereoGeometry(focal_px=960.0 * width / 1920, baseline_m=0.063, cx=(width - 1) / 2, cy=(width - 1) / 2)


TILE_GEOMETRY = tile_geometry()
OVERLAY_COUNT = 6
TRUNK_CLASS, BRANCH_CLASS = CLASSES.index("trunk"), CLASSES.index("branch")


@dataclass
class PixelCounts:
    """Pixel counts of one or more images: labelled (the mask), found (labelled and called trunk or branch),
    far (more than `FAR_PX` from the mask) and far ones called trunk / branch."""

    labelled: int = 0
    found: int = 0
    far: int = 0
    far_trunk: int = 0
    far_branch: int = 0

    def __iadd__(self, other: PixelCounts) -> PixelCounts:
        for key, value in asdict(other).items():
            setattr(self, key, getattr(self, key) + value)
        return self

    def shares(self) -> dict[str, float | None]:
        """found / labelled, far_trunk / far and far_branch / far (None where nothing is counted)."""
        return {
            "found_share": self.found / self.labelled if self.labelled else None,
            "far_trunk_share": self.far_trunk / self.far if self.far else None,
            "far_branch_share": self.far_branch / self.far if self.far else None,
        }


def read_sample(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """season → (RGB `uint8 256×256×3`, depth `uint8 256×256` (0 = none), mask `bool 256×256`) of one sample
    PNG; ValueError for a file that is not a 512×512 RGBA image."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None or image.shape != (2 * TILE, 2 * TILE, 4):
        found = "unreadable" if image is None else f"shape {image.shape}"
        raise ValueError(f"{path}: expected a {2 * TILE}×{2 * TILE} RGBA PNG, found {found}")
    out = {}
    for column, season in enumerate(SEASONS):
        tile = image[:TILE, column * TILE : (column + 1) * TILE]
        mask_tile = image[TILE:, column * TILE : (column + 1) * TILE, :3]
        rgb = np.ascontiguousarray(cv2.cvtColor(tile[..., :3], cv2.COLOR_BGR2RGB))
        out[season] = (rgb, np.ascontiguousarray(tile[..., 3]), mask_tile.mean(axis=2) >= 128)
    return out


def enlarged(
    rgb: np.ndarray, depth: np.ndarray, mask: np.ndarray, width: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A tile's (RGB, depth, mask) as a `width`×`width` frame: the image linearly, depth and mask by nearest
    neighbour (no depth is invented between a stem and what lies behind it); unchanged at the tile's own size."""
    if width == rgb.shape[1]:
        return rgb, depth, mask
    size = (width, width)
    return (
        cv2.resize(rgb, size, interpolation=cv2.INTER_LINEAR),
        cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST),
        cv2.resize(mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST).astype(bool),
    )


def relative_disparity(
    depth: np.ndarray, mask: np.ndarray, tree_median_px: float = TREE_MEDIAN_DISPARITY_PX
) -> np.ndarray:
    """`float32` 1 / `depth` where depth > 0 (0 elsewhere), scaled so its median over the `mask` pixels with a
    depth is `tree_median_px` (over all pixels with a depth when the mask has none; all zero without any
    depth)."""
    valid = depth > 0
    inverse = np.zeros(depth.shape, np.float32)
    inverse[valid] = 1.0 / depth[valid].astype(np.float32)
    reference = inverse[valid & mask] if np.any(valid & mask) else inverse[valid]
    if reference.size == 0:
        return inverse
    return inverse * np.float32(tree_median_px / float(np.median(reference)))


def far_from(mask: np.ndarray, distance_px: float = FAR_PX) -> np.ndarray:
    """`bool H×W`: pixels more than `distance_px` from every mask pixel (Euclidean distance transform); all
    of them when the mask is empty."""
    if not mask.any():
        return np.ones(mask.shape, bool)
    return cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 5) > distance_px


def count_pixels(trunk: np.ndarray, branch: np.ndarray, mask: np.ndarray, far_px: float = FAR_PX) -> PixelCounts:
    """`PixelCounts` of a prediction (`trunk`, `branch`: `bool H×W`) against a hand `mask` (`bool H×W`), far
    meaning more than `far_px` from it."""
    far = far_from(mask, far_px)
    return PixelCounts(
        labelled=int(np.count_nonzero(mask)),
        found=int(np.count_nonzero(mask & (trunk | branch))),
        far=int(np.count_nonzero(far)),
        far_trunk=int(np.count_nonzero(far & trunk)),
        far_branch=int(np.count_nonzero(far & branch)),
    )


def masks_trunk_branch(masks: BranchMasks) -> tuple[np.ndarray, np.ndarray]:
    """(trunk, branch) `bool H×W` of a segmenter's final instances."""
    trunk = masks.trunk()
    if trunk is None:
        trunk = np.zeros(masks.labels.shape, bool)
    return trunk, np.isin(masks.labels, masks.branch_ids())


def disparity_inputs(
    mode: str, depth: np.ndarray, mask: np.ndarray, tree_median_px: float = TREE_MEDIAN_DISPARITY_PX
) -> tuple[np.ndarray, np.ndarray]:
    """(disparity `float32 H×W` px, confidence `float32 H×W`) of a `DISPARITY_MODES` mode."""
    if mode == "none":
        empty = np.zeros(depth.shape, np.float32)
        return empty, empty
    return relative_disparity(depth, mask, tree_median_px), (depth > 0).astype(np.float32)


def score_image(
    segmenter: Segmenter, rgb: np.ndarray, depth: np.ndarray, mask: np.ndarray, mode: str
) -> tuple[dict[str, PixelCounts], np.ndarray, np.ndarray]:
    """{"final": counts of the final masks, "network": of the learned network's arg-max (learned segmenters
    only)} and the final (trunk, branch) masks of one square image (a tile, or one `enlarged`: the disparity,
    geometry and far distance scale with its width) in one disparity mode."""
    scale = rgb.shape[1] / TILE
    disparity, confidence = disparity_inputs(mode, depth, mask, TREE_MEDIAN_DISPARITY_PX * scale)
    geometry = tile_geometry(rgb.shape[1])
    trunk, branch = masks_trunk_branch(segmenter.segment(rgb, disparity, geometry, confidence))
    counts = {"final": count_pixels(trunk, branch, mask, FAR_PX * scale)}
    if isinstance(segmenter, LearnedSegmenter):
        classes = segmenter.logits(rgb, disparity).argmax(axis=0)
        counts["network"] = count_pixels(classes == TRUNK_CLASS, classes == BRANCH_CLASS, mask, FAR_PX * scale)
    return counts, trunk, branch


def overlay_ids(ids: list[str], count: int = OVERLAY_COUNT) -> list[str]:
    """`count` ids spread evenly over the sorted `ids` (first and last included): fixed by id, not by result."""
    ordered = sorted(ids)
    if len(ordered) <= count:
        return ordered
    return [ordered[round(k * (len(ordered) - 1) / (count - 1))] for k in range(count)]


def tinted(rgb: np.ndarray, mask: np.ndarray, trunk: np.ndarray, branch: np.ndarray) -> np.ndarray:
    """BGR `uint8` image: trunk tinted cyan, branch magenta, the mask's outline green."""
    image = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR).astype(np.float32)
    for called, colour in ((trunk, (255, 255, 0)), (branch, (255, 0, 255))):
        image[called] = 0.45 * image[called] + 0.55 * np.asarray(colour, np.float32)
    image = image.astype(np.uint8)
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(image, contours, -1, (0, 255, 0), 1)
    return image


def write_overlay(path: Path, panels: list[np.ndarray]) -> None:
    """The panels (BGR tiles: a row per season, a column per disparity mode) as one JPEG (quality 80: a photo
    grid of 512×512 px stays well under 150 kB)."""
    rows = [np.concatenate(panels[i : i + len(DISPARITY_MODES)], axis=1) for i in range(0, len(panels), 2)]
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.concatenate(rows, axis=0), [cv2.IMWRITE_JPEG_QUALITY, 80])


def run_real_orchard(
    segmenter: Segmenter,
    folder: Path = REAL_ORCHARD,
    overlays: Path | None = None,
    frame_width: int = PRODUCT_FRAME_WIDTH,
) -> dict[str, Any]:
    """Counts per sample, season and disparity mode, pooled per season ("seasons"), each tile seen `enlarged` to
    `frame_width` px, with overlays of `overlay_ids` written to `overlays` (`<id>.jpg`: rows winter / summer,
    columns 'depth' / 'none', at the tiles' size). FileNotFoundError when `folder` holds no samples."""
    paths = sorted((folder / "samples").glob("*.png"))
    if not paths:
        raise FileNotFoundError(f"no real orchard samples in {folder / 'samples'}")
    drawn = set(overlay_ids([p.stem for p in paths]))
    pooled: dict[str, dict[str, dict[str, PixelCounts]]] = {}
    samples: dict[str, dict[str, Any]] = {}
    for path in paths:
        panels = []
        for season, tile in read_sample(path).items():
            rgb, depth, mask = enlarged(*tile, frame_width)
            for mode in DISPARITY_MODES:
                counts, trunk, branch = score_image(segmenter, rgb, depth, mask, mode)
                samples.setdefault(path.stem, {}).setdefault(season, {})[mode] = {
                    kind: {**asdict(c), **c.shares()} for kind, c in counts.items()
                }
                for kind, c in counts.items():
                    total = pooled.setdefault(season, {}).setdefault(mode, {}).setdefault(kind, PixelCounts())
                    total += c
                panels.append(cv2.resize(tinted(rgb, mask, trunk, branch), (TILE, TILE), interpolation=cv2.INTER_AREA))
        if overlays is not None and path.stem in drawn:
            write_overlay(overlays / f"{path.stem}.jpg", panels)
    seasons = {
        season: {
            mode: {kind: {**asdict(c), **c.shares()} for kind, c in kinds.items()} for mode, kinds in modes.items()
        }
        for season, modes in pooled.items()
    }
    return {
        "samples": len(paths),
        "frame_width": frame_width,
        "overlay_ids": sorted(drawn),
        "seasons": seasons,
        "per_sample": samples,
    }


def print_real_orchard(name: str, result: dict[str, Any]) -> None:
    """The per-season table of `run_real_orchard`'s `result` for segmenter `name`."""
    print(
        f"\nreal orchard RGB-D, {result['samples']} samples seen {result['frame_width']} px wide, segmenter {name}: "
        f"labelled trunk+leader pixels found as trunk or branch; pixels > {FAR_PX:g} px of the tile from the mask "
        "called trunk / branch"
    )
    print(f"{'season':<8} {'disparity':<10} {'counted':<8} {'found':>7} {'far trunk':>10} {'far branch':>11}")
    for season, modes in result["seasons"].items():
        for mode, kinds in modes.items():
            for kind, r in kinds.items():
                print(
                    f"{season:<8} {mode:<10} {kind:<8} {r['found_share']:>7.1%} {r['far_trunk_share']:>10.2%} "
                    f"{r['far_branch_share']:>11.2%}"
                )
