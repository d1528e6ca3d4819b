"""VirtualTree (the authors' UE5 orchard set) and anything written in its layout, e.g. `emcstereo synth`.

Layout under the dataset root (`Virtual_branches_data/`)::

    left image/left_N.png    right image/right_N.png    left depth/depth_N.exr

Split files list one pair per line as three root-relative paths, left image, left depth, right
image. The folder names contain a space, so a line usually splits into six whitespace tokens that
are rejoined pairwise; a three-token line is read as left, depth, right.

Depth is stored in centimetres (EXR R channel); disparity = f·B / depth with the ZED Mini rig of
the set, f = 960 px at 1920 px width and B = 6.3 cm. Depth ≥ 65000 cm (sky, ≈ 65504 in fp16),
non-finite or ≤ 0 is invalid and becomes disparity 0.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from stereo.datasets.base import DatasetError, PairRecord, StereoDataset, require_dir
from stereo.io import read_exr_depth
from stereo.pinhole import disparity_from_depth

#: The VirtualTree rig: focal length in pixels at 1920 px width, baseline in centimetres.
VIRTUALTREE_FOCAL_PX = 960.0
VIRTUALTREE_BASELINE_CM = 6.3
#: Depth at or beyond this (cm) is sky / no hit.
SKY_DEPTH_CM = 65000.0

LEFT_DIR, RIGHT_DIR, DEPTH_DIR = "left image", "right image", "left depth"
_LEFT_NAME = re.compile(r"^left_(\d+)\.png$")


def depth_cm_to_disparity(
    depth_cm: np.ndarray, focal_px: float = VIRTUALTREE_FOCAL_PX, baseline_cm: float = VIRTUALTREE_BASELINE_CM
) -> np.ndarray:
    """Disparity (px, float32 `H×W`) from depth (cm, `H×W`); invalid depth (sky, ≤0, non-finite) → 0."""
    depth = np.asarray(depth_cm, dtype=np.float64)
    valid = np.isfinite(depth) & (depth > 0) & (depth < SKY_DEPTH_CM)
    disparity = np.zeros(depth.shape, dtype=np.float32)
    disparity[valid] = disparity_from_depth(depth[valid], focal_px, baseline_cm).astype(np.float32)
    return disparity


def parse_split_line(line: str, *, source: str = "<split>", line_no: int = 0) -> tuple[str, str, str]:
    """(left, depth, right) root-relative paths of one split-file line (6-token or 3-token form)."""
    tokens = line.split()
    if len(tokens) == 6:
        return f"{tokens[0]} {tokens[1]}", f"{tokens[2]} {tokens[3]}", f"{tokens[4]} {tokens[5]}"
    if len(tokens) == 3:
        return tokens[0], tokens[1], tokens[2]
    raise DatasetError(
        f"{source}:{line_no}: expected 3 paths (left image, left depth, right image) — 6 tokens when the "
        f"folder names contain a space — but found {len(tokens)} tokens in {line.strip()!r}"
    )


def read_split_file(path: Path) -> list[tuple[str, str, str]]:
    """All (left, depth, right) triples of a VirtualTree split file, blank lines skipped."""
    if not path.is_file():
        raise DatasetError(f"{path}: split file not found")
    triples = []
    for line_no, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if line.strip():
            triples.append(parse_split_line(line, source=str(path), line_no=line_no))
    if not triples:
        raise DatasetError(f"{path}: split file lists no pairs")
    return triples


def discover_triples(root: Path) -> list[tuple[str, str, str]]:
    """Every `left image/left_N.png` under `root` with its depth and right image, by increasing N."""
    left_dir = require_dir(root / LEFT_DIR, f"'{LEFT_DIR}/left_N.png' files of a VirtualTree-layout dataset")
    found = sorted((int(m.group(1)), p.name) for p in left_dir.iterdir() if (m := _LEFT_NAME.match(p.name)))
    if not found:
        raise DatasetError(f"{left_dir}: no left_N.png images")
    return [(f"{LEFT_DIR}/{name}", f"{DEPTH_DIR}/depth_{n}.exr", f"{RIGHT_DIR}/right_{n}.png") for n, name in found]


def resolve_split_file(root: Path, split: str | Path) -> Path:
    """A split given as a file path, or as a name looked up as `NAME.txt` / `virtualtree_NAME.txt` in root."""
    direct = Path(split)
    if direct.is_file():
        return direct
    candidates = [root / f"{split}.txt", root / f"virtualtree_{split}.txt", root / "splits" / f"{split}.txt"]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    raise DatasetError(
        f"split {str(split)!r}: no such file; tried {direct} and " + ", ".join(str(c) for c in candidates)
    )


class VirtualTreeDataset(StereoDataset):
    """VirtualTree pairs from a split file (or every pair in the folders when `split` is None)."""

    name = "virtualtree"

    def __init__(
        self,
        root: str | Path,
        split: str | Path | None = None,
        *,
        focal_px: float = VIRTUALTREE_FOCAL_PX,
        baseline_cm: float = VIRTUALTREE_BASELINE_CM,
        max_disp: float | None = None,
    ) -> None:
        self.root = require_dir(
            Path(root), "a VirtualTree-layout dataset ('left image/', 'right image/', 'left depth/')"
        )
        self.focal_px = focal_px
        self.baseline_cm = baseline_cm
        triples = (
            discover_triples(self.root) if split is None else read_split_file(resolve_split_file(self.root, split))
        )
        super().__init__(self._records(triples), max_disp=max_disp)

    def _records(self, triples: Sequence[tuple[str, str, str]]) -> list[PairRecord]:
        """Records for (left, depth, right) triples, checking that every file exists."""
        records = []
        for left, depth, right in triples:
            paths = [self.root / left, self.root / right, self.root / depth]
            for path in paths:
                if not path.is_file():
                    raise DatasetError(f"{path}: listed for pair {left!r} but not found under {self.root}")
            records.append(PairRecord(paths[0], paths[1], paths[2], name=left))
        return records

    def read_ground_truth(self, record: PairRecord) -> np.ndarray:
        """Disparity from the pair's EXR depth (cm) with this dataset's focal length and baseline."""
        assert record.ground_truth is not None
        return depth_cm_to_disparity(read_exr_depth(record.ground_truth), self.focal_px, self.baseline_cm)
