"""Rendered frames with their truth as a labelled COCO data set: the labelling step, simulated.

A fine-tune on a new orchard starts from frames a person labelled (`branchrange export-frames`, corrected in
CVAT or Label Studio). To measure that loop without a person, synthetic frames of a domain
(`SynthOptions.domain`) are written the same way with their truth masks as the labels: the same COCO layout
and writer (`coco_export.write_coco`: images/, annotations.json with RLE masks, annotations_polygons.json),
branch instances as "branch", the trunk as "trunk"; twigs and leaves are neither (a labeller leaves them).
Each frame's SGBM disparity, confidence and camera go to `stereo/` as `export-frames` writes them (what
`train-segmenter --coco` reads). What scoring needs and a labelled set has not is kept beside it, one file a frame:

    DIR/truth/frame_000123.npz   right (uint8 H×W×3), disparity (exact, float32 px), sgbm, sgbm_conf, camera
                                 (f px, B m, cx, cy), truth (JSON: the branches' cut points and visibility)
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from branchrange.core.geometry import StereoGeometry
from branchrange.core.masks import BranchMasks
from branchrange.learning.samples import LEAF_ID, TRUNK_ID, TWIG_ID, evaluation_scene
from branchrange.offline.coco_export import LabelledFrame, write_coco

TRUTH_DIR = "truth"


def truth_masks(instance_mask: np.ndarray) -> BranchMasks:
    """The renderer's instance mask `uint16 H×W` as `BranchMasks`: branches 1..K, the trunk, twigs and leaves
    as background (what a labeller of branch / trunk leaves unlabelled)."""
    labels = instance_mask.astype(np.int32)
    labels[(labels == TWIG_ID) | (labels == LEAF_ID)] = 0
    return BranchMasks(labels, TRUNK_ID, "truth")


def export_domain_frames(
    out_dir: Path,
    seeds: Iterable[int],
    domain: str,
    cache: Path | None = None,
    version: str = "",
    size: tuple[int, int] = (640, 360),
) -> Path:
    """Render scenes `seeds` of `domain` at `size` (`branchrange.learning.samples.evaluation_scene`: SGBM, truth cut
    points; cached in `cache`), write them to `out_dir` as a COCO data set labelled with their truth (`truth_masks`) and
    each frame's right view, disparities, camera and truth cut points under `TRUTH_DIR`; the annotations.json
    path. A frame's index in the set is its seed."""
    truth_dir = out_dir / TRUTH_DIR
    truth_dir.mkdir(parents=True, exist_ok=True)

    def frames() -> Iterable[LabelledFrame]:
        for seed in seeds:
            scene = evaluation_scene(seed, cache, size=size, domain=domain)
            focal, baseline, cx, cy = (float(v) for v in scene["camera"])
            frame = LabelledFrame(
                scene["left"],
                truth_masks(scene["mask"]),
                seed,
                0,
                disparity=scene["sgbm"],  # what a user's export carries: the stereo as the vehicle measured it
                confidence=scene["sgbm_conf"],
                geometry=StereoGeometry(focal, baseline, cx, cy),
            )
            np.savez_compressed(
                truth_dir / f"{Path(frame.file_name).stem}.npz",
                right=scene["right"],
                disparity=scene["disparity"],
                sgbm=scene["sgbm"],
                sgbm_conf=scene["sgbm_conf"],
                camera=scene["camera"],
                truth=np.array(json.dumps(scene["truth"])),
            )
            yield frame

    return write_coco(out_dir, frames(), f"synthetic {domain} scenes (truth labels)", version)
