"""Segmenters without truth masks: cut-point recall, false cut points, speed, reliability; real trees.

Synthetic part: held-out scenes of `stereo.synth.render_scene` (seeds 50000+, never used for
training or calibrating the learned segmenter, which use seeds 1–2980; default options: ground,
background trees and far foliage rows, foliage drawn bare/sparse/dense per scene) at 640×360 (ZED
Mini). Per stereo source and segmenter (each name given — 'learned' runs its network at its default
width, the frame's own (640 px here), with the default second look at the trunk band; 'learned/0' one
look; 'learned@1280' one look at twice the width; '-int8' the quantized copy — plus 'truth' = the
scene's instance mask),
every frame goes through `Pipeline.process_disparity`. Stereo sources: 'sgbm' as the pipeline runs it
(each branch's disparity refined on its own pixels, `branchrange.core.branch_disparity`),
'sgbm-unrefined' (the same without the right image: the baseline of that step, same run) and 'truth'
(the renderer's exact disparity); cut points are matched
to the truth as in `branchrange.offline.evaluate_cuts` (recall within 5 cm, median 3D error of the
matches, false cut points per frame = estimates with no truth cut point within 5 cm). Time per frame
is the segmenter's own (`timing_ms.masks`). The reliability table pools each (stereo, segmenter)'s
cut points by confidence bin: the share within 5 cm of a truth cut point and the bin's mean confidence (alike
when the confidence is honest); beside it, the share correct at confidence ≥ 0.8 with its mean confidence
(what an honest confidence would get right there) and the lowest confidence from which ≥ 90 % are correct;
recall and false cut
points are also counted with only the cut points at or above each of `CONFIDENCE_FLOORS` (what a robot acting
at that threshold sees). Recall is also given per branch width class (`width_class`: thin stems are where
segmenters lose branches).

How sure the figures are: recall and false cut points a frame carry a 95 % interval from a bootstrap
over scenes (`CutScores.interval`; a scene's branches succeed or fail together), and each
segmenter's recall minus the first listed one's with the same stereo is given paired over the same
scenes (`recall_difference_interval`). On 60 scenes a single recall is uncertain by about ± 6
points and the first 60 read 1–3 points easier than the next 180 (benchmarks/RESULTS.md); on 240 about
± 3.3, and the share right at ≥ 0.8 about ± 2.5: hence 240 scenes by default (a change smaller than
that shows only in the paired figure; `--scenes 60` for a quicker look).

Changed light (`--light dusk glare haze warm high_gain`, `branchrange.learning.light_changes`): each
change adds the stereo mode 'sgbm-<change>' — both images under that light, SGBM computed again — with its recall
minus the same segmenter's in the scenes' own light, paired.

The pipeline as it flies (`--hd720`): the same seeds rendered at 1280×720 (the ZED Mini's HD720) go through
the roi mode with `deploy/onboard_cpu.toml`'s stereo settings — the segmenter sees the 640×360 coarse pass, each
branch is matched again at full resolution — as stereo mode 'roi-hd720', and whole-frame as a ground station
takes such a pair ('full-hd720': SGBM at 1280×720, the segmenter seeing the frame at its own width); scored
against the HD720 scene's own truth (about one seed in four places its branches differently at that size, so
neither is paired with 'sgbm').

Real part: `../shared/data/trees/*` (rectified pairs, hand polygons of branch / not-branch), sgbm
with the disparity range the README there gives, a nominal camera (f 700 px, B 0.06 m) since no
calibration exists: precision = cut points inside a branch polygon / cut points inside any
polygon; also how many of those lie on a trunk polygon (a main stem, which a pruner must not cut), how many of
the branches holding the annotation's cut candidates got one, and per annotated region where its pixels went
(`region_pixels`); overlays (polygons, instances, cut points) are written to --overlays.

Real orchard RGB-D (`--real-orchard`, alone: no synthetic scenes): `../shared/data/real_orchard_rgbd`, per season
the share of the hand-labelled trunk+leader pixels called trunk or branch and of the pixels far from that mask
called trunk / branch, with a relative disparity from the depth and with none (`benchmarks/real_orchard.py`);
--segmenters default to the shipped 'learned' there, overlays of six samples fixed by id go to --overlays. Each
256 px tile is seen enlarged to --real-orchard-width px (default 640, the product's smallest frame; 256: as it is).

    python benchmarks/segmenter.py --real-orchard [--segmenters learned] [--json out.json] [--real-orchard-width 640]
                                   [--overlays benchmarks/segmenter_overlays/real_orchard]
    python benchmarks/segmenter.py [--scenes 240] [--segmenters learned learned@1280 learned-int8 structure]
                                   [--light dusk ...] [--hd720] [--json out.json]
                                   [--overlays benchmarks/segmenter_overlays] [--cache out/segbench]
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from machine import cpu_name  # a script's own folder is on its import path
from real_orchard import PRODUCT_FRAME_WIDTH, REAL_ORCHARD, TILE, print_real_orchard, run_real_orchard

from branchrange.config.loader import load_config, pipeline_config
from branchrange.core.confidence import (
    cut_point_outcomes,
    expected_calibration_error,
    lowest_reliable_threshold,
    share_correct_above,
)
from branchrange.core.cutpoints import CutPointConfig
from branchrange.core.frame_result import Branch, FrameResult
from branchrange.core.masks import BranchMasks
from branchrange.core.pipeline import (
    Pipeline,
    PipelineConfig,
    target_minimum,
    untracked_whole_frame,
    with_exact_disparity,
)
from branchrange.core.segmentation.choose import make_segmenter
from branchrange.core.segmentation.learned import LearnedSegmenter, LearnedSegmenterConfig
from branchrange.core.segmentation.network_input import CLASSES
from branchrange.core.segmentation.segmenter import Segmenter
from branchrange.learning.light_changes import LIGHT_CHANGES
from branchrange.learning.samples import evaluation_scene, scene_in_light
from branchrange.offline.evaluate_cuts import CutScores, recall_difference_interval

ROOT = Path(__file__).resolve().parents[1]
TREES = ROOT.parent / "shared" / "data" / "trees"
FIRST_SEED = 50_000
SIZE = (640, 360)
#: the pipeline as it flies: ZED Mini at HD720, a coarse SGBM pass at 640×360 that the segmenter sees, then
#: each branch matched again at full resolution in its own box and disparity window (`stereo.mode = "roi"`)
HD720 = (1280, 720)
ONBOARD_CONFIG = ROOT / "deploy" / "onboard_cpu.toml"
#: nominal rectified camera for the real pairs (no calibration exists; see their README)
REAL_FOCAL_PX, REAL_BASELINE_M = 700.0, 0.06
#: sgbm disparity range per real scene, from the ranges in ../shared/data/trees/README.md
REAL_MAX_DISP = {"forest_1s": 64, "Jadeplant_Q": 160}
#: the cut points a robot acts on: the pipeline's default target threshold
TARGET_MIN_CONFIDENCE = CutPointConfig().target_min_confidence
BINS = (0.0, 0.2, 0.4, 0.6, 0.8, 0.9, 1.0001)
#: confidence floors at which recall and false cut points are also counted (only the cut points at or above each):
#: where obstacles are fenced (0.3), a middle one, the onboard target threshold (0.72) and the issue's 0.8
CONFIDENCE_FLOORS = (0.3, 0.5, 0.72, 0.8)
#: `piece_disparity_ratio` of the '+depth' variants: the best on the calibration scenes (benchmarks/RESULTS.md)
DEPTH_PIECES_RATIO = 0.04
#: the names of the learned segmenter's variants (`benchmark_segmenter`)
LEARNED_VARIANT = re.compile(
    r"learned(?P<int8>-int8)?(?:@(?P<width>\d+))?(?:/(?P<band>\d+))?(?P<depth>\+depth)?(?P<normal>~normal)?"
)
#: branch width classes (px in the 640×360 image) of the recall-by-width table
WIDTH_BINS_PX = (0.0, 3.0, 5.0, 8.0, np.inf)


def benchmark_segmenter(name: str) -> Segmenter:
    """`make_segmenter(name)`, and the learned segmenter's variants (`LEARNED_VARIANT`, parts in this order):
    'learned-int8' (its shipped int8 model), a network width after '@' (e.g. 'learned@1280'; `network_width`),
    a trunk band after '/' (e.g. 'learned/0': one look; `trunk_band_px`), then '+depth' for straight pieces that
    follow the disparity (`piece_disparity_ratio` = `DEPTH_PIECES_RATIO`) and a final '~normal' for every frame
    read through the normal-light calibration (`light_calibration` off). Without a '/', the default band at the
    frame's own width and none at another width (a second look at twice 1280 is not a setting anyone runs).
    ValueError for a learned variant out of that grammar (a part misplaced would otherwise be dropped)."""
    if name == "learned" or not name.startswith("learned") or name.startswith("learned:"):  # learned:BUNDLE too
        return make_segmenter(name)
    variant = LEARNED_VARIANT.fullmatch(name)
    if variant is None:
        raise ValueError(f"segmenter {name!r}: expected learned[-int8][@WIDTH][/BAND][+depth][~normal]")
    width, band = variant["width"], variant["band"]
    config = LearnedSegmenterConfig(
        precision="int8" if variant["int8"] else "fp32",
        network_width=int(width or 0),
        trunk_band_px=int(band) if band else LearnedSegmenterConfig().trunk_band_px if not width else 0,
        piece_disparity_ratio=DEPTH_PIECES_RATIO if variant["depth"] else 0.0,
        light_calibration=not variant["normal"],
    )
    return LearnedSegmenter(config)


def width_class(instance_mask: np.ndarray, branch_id: int, px_scale: float = 1.0) -> str:
    """Width class (`WIDTH_BINS_PX`) of a truth branch: twice the 90th percentile of its pixels' distance to
    its silhouette's edge, in px at 640×360 (`instance_mask`'s px × `px_scale`) — thin stems are where
    segmenters lose most branches."""
    own = (instance_mask == branch_id).astype(np.uint8)
    if not own.any():
        return "hidden"
    inside = cv2.distanceTransform(own, cv2.DIST_L2, 3)
    width = 2.0 * px_scale * float(np.percentile(inside[own > 0], 90))
    k = int(np.searchsorted(WIDTH_BINS_PX, width, side="right")) - 1
    lo, hi = WIDTH_BINS_PX[k], WIDTH_BINS_PX[k + 1]
    return f"≥{lo:g} px" if np.isinf(hi) else f"{lo:g}–{hi:g} px"


def reliability(pairs: list[tuple[float, bool]]) -> list[tuple[str, int, float, float]]:
    """(bin label, cut points, share correct, mean confidence) per confidence bin of (confidence, within 5 cm)
    pairs: an honest confidence has the two last alike in every bin."""
    rows = []
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        confidences = [c for c, _ in pairs if lo <= c < hi]
        correct = [ok for c, ok in pairs if lo <= c < hi]
        share, mean = (float(np.mean(v)) if v else float("nan") for v in (correct, confidences))
        rows.append((f"{lo:.1f}–{min(hi, 1.0):.1f}", len(correct), share, mean))
    return rows


def mean_confidence_above(pairs: list[tuple[float, bool]], threshold: float) -> float:
    """Mean confidence of the (confidence, within 5 cm) pairs at or above `threshold` (NaN without any): the share
    of them an honest confidence gets right — the issue's ≥ 0.8 → 90 % asks for about 0.9 there."""
    kept = [c for c, _ in pairs if c >= threshold]
    return float(np.mean(kept)) if kept else float("nan")


def needed_for_target(pipeline: Pipeline) -> float:
    """The confidence a cut point of the pipeline's last frame needed to be a target (`pipeline.target_minimum`)."""
    return target_minimum(TARGET_MIN_CONFIDENCE, None if pipeline.last is None else pipeline.last.masks)


class Tallies:
    """Everything `run_synthetic` counts, per 'stereo/segmenter' key, frame by frame."""

    def __init__(self) -> None:
        self.scores: dict[str, CutScores] = {}
        self.confidences: dict[str, list[tuple[float, bool]]] = {}
        self.times: dict[str, list[float]] = {}
        self.confident: dict[str, CutScores] = {}  # only the cut points at or above the target default
        self.by_width: dict[str, dict[str, CutScores]] = {}  # recall per branch width class (all cut points)
        self.floors: dict[str, dict[float, CutScores]] = {}  # only the cut points at or above each confidence floor

    def add(self, key: str, truth: list[dict], widths: list[str], result: FrameResult, pipeline: Pipeline) -> None:
        """One frame's `result` of `pipeline` against its `truth` cut points (with their width classes)."""
        stereo, name = key.split("/", 1)
        self.scores.setdefault(key, CutScores(stereo, name)).add_frame(truth, result.branches, result.target)
        for width in set(widths):
            in_class = [t for t, w in zip(truth, widths) if w == width]
            self.by_width.setdefault(key, {}).setdefault(width, CutScores(stereo, name)).add_frame(
                in_class, result.branches
            )
        for floor in CONFIDENCE_FLOORS:
            self.floors.setdefault(key, {}).setdefault(floor, CutScores(stereo, name)).add_frame(
                truth, [x for x in result.branches if x.confidence >= floor]
            )
        needed = needed_for_target(pipeline)
        acted_on = [x for x in result.branches if x.confidence >= needed]
        self.confident.setdefault(key, CutScores(stereo, name)).add_frame(truth, acted_on, result.target)
        self.times.setdefault(key, []).append(segmenter_ms(result))
        self.confidences.setdefault(key, []).extend(
            cut_point_outcomes(
                [(b.confidence, b.cut_point_m) for b in result.branches], [t["cut_point_m"] for t in truth]
            )
        )


def segmenter_ms(result: FrameResult) -> float:
    """The segmenter's time in `result` (ms): in the roi mode it runs in the stereo stage on the coarse pass
    ('segment') and, with `[roi] full_resolution_instances`, its instance step again after the fine pass
    ('instances'); otherwise in the geometry stage ('masks')."""
    timing = result.timing_ms
    return timing["segment"] + timing.get("instances", 0.0) if "segment" in timing else timing["masks"]


def onboard_roi() -> PipelineConfig:
    """The benchmark's pipeline settings with the stereo of `ONBOARD_CONFIG`: the roi mode at HD720."""
    flown = pipeline_config(load_config(ONBOARD_CONFIG))
    return replace(untracked_whole_frame(), stereo=flown.stereo, roi=flown.roi)


def score_hd720(
    seed: int, cache: Path | None, hardware: bool, built: dict[str, Segmenter], config: PipelineConfig, tallies: Tallies
) -> None:
    """Scene `seed` rendered at HD720, for each segmenter of `built` and truth masks, two ways: 'roi-hd720' through
    `config` (`onboard_roi`: the segmenter sees the 640×360 coarse pass, the cut points come from each branch
    matched again at 1280×720) and 'full-hd720' as a ground station takes an HD720 pair (`deploy/serve.toml`'s
    mode): whole-frame SGBM at 1280×720, the segmenter seeing the frame at its own width."""
    scene = evaluation_scene(seed, cache, size=HD720, hardware=hardware)
    f, b, cx, cy = (float(v) for v in scene["camera"])
    scale = SIZE[0] / HD720[0]
    widths = [width_class(scene["mask"], k + 1, scale) for k in range(len(scene["truth"]))]
    for name in [*built, "truth"]:
        mask = scene["mask"] if name == "truth" else None
        flown = Pipeline(config, focal_px=f, baseline_m=b, principal_point=(cx, cy), segmenter=built.get(name))
        result = flown.process(scene["left"], scene["right"], mask=mask)
        tallies.add(f"roi-hd720/{name}", scene["truth"], widths, result, flown)
        ground = Pipeline(
            untracked_whole_frame(), focal_px=f, baseline_m=b, principal_point=(cx, cy), segmenter=built.get(name)
        )
        result = ground.process_disparity(
            scene["left"], scene["sgbm"], scene["sgbm_conf"], mask=mask, backend="sgbm", right=scene["right"]
        )
        tallies.add(f"full-hd720/{name}", scene["truth"], widths, result, ground)


def run_synthetic(
    segmenters: list[str],
    scenes: int,
    cache: Path | None,
    hardware: bool = False,
    light: Sequence[str] = (),
    hd720: bool = False,
) -> dict:
    """Scores per 'stereo/segmenter' over `scenes` held-out scenes (with orchard hardware when `hardware`); each
    change of `light` (`branchrange.learning.samples.scene_in_light`) adds the stereo mode 'sgbm-<change>': both images
    under that light, SGBM computed again, the pipeline as with 'sgbm'. `hd720` adds 'roi-hd720' and 'full-hd720': the
    scene rendered at 1280×720 through the pipeline as it flies (`onboard_roi`) and whole-frame (`score_hd720`)."""
    built = {name: benchmark_segmenter(name) for name in segmenters}
    flown = onboard_roi() if hd720 else None
    tallies = Tallies()
    for i in range(scenes):
        scene = evaluation_scene(FIRST_SEED + i, cache, hardware=hardware)
        f, b, cx, cy = (float(v) for v in scene["camera"])
        widths = [width_class(scene["mask"], k + 1) for k in range(len(scene["truth"]))]
        views = {
            "sgbm": (scene["left"], scene["sgbm"], scene["sgbm_conf"], scene["right"]),
            "sgbm-unrefined": (scene["left"], scene["sgbm"], scene["sgbm_conf"], None),
            "truth": (scene["left"], scene["disparity"], None, None),
        }
        for change in light:
            lit = scene_in_light(scene, FIRST_SEED + i, change, cache, hardware=hardware)
            views[f"sgbm-{change}"] = (lit["left"], lit["sgbm"], lit["sgbm_conf"], lit["right"])
        for stereo, (left, disparity, confidence, right) in views.items():
            for name in [*segmenters, "truth"]:
                pipeline = Pipeline(
                    with_exact_disparity(untracked_whole_frame()) if stereo == "truth" else untracked_whole_frame(),
                    focal_px=f,
                    baseline_m=b,
                    principal_point=(cx, cy),
                    segmenter=built.get(name),
                )  # process_disparity: no backend is built
                mask = scene["mask"] if name == "truth" else None
                result = pipeline.process_disparity(left, disparity, confidence, mask=mask, backend=stereo, right=right)
                tallies.add(f"{stereo}/{name}", scene["truth"], widths, result, pipeline)
        if flown is not None:
            score_hd720(FIRST_SEED + i, cache, hardware, built, flown, tallies)
        print(f"  scene {i + 1}/{scenes}", end="\r", file=sys.stderr)
    out = {}
    for key, s in tallies.scores.items():
        stereo, name = key.split("/", 1)
        baseline = tallies.scores[f"{stereo}/{segmenters[0]}"]
        interval = s.interval()
        normal_light = (
            tallies.scores[f"sgbm/{name}"] if stereo.startswith("sgbm-") and stereo != "sgbm-unrefined" else None
        )
        out[key] = {
            "recall": s.recall,
            "recall_ci95": interval["recall"],
            "recall_minus_normal_light": None
            if normal_light is None
            else {
                "difference": s.recall - normal_light.recall,
                "ci95": recall_difference_interval(s, normal_light),
            },
            "false_per_frame_ci95": interval["false_per_frame"],
            # paired over the same scenes: what the scenes share (which are hard) cancels
            "recall_minus_first": None
            if s is baseline
            else {
                "first": segmenters[0],
                "difference": s.recall - baseline.recall,
                "ci95": recall_difference_interval(s, baseline),
            },
            "median_error_cm": 100 * s.error_quantile(0.5),
            "false_per_frame": s.false_per_frame,
            "ms_per_frame": float(np.median(tallies.times[key])),
            "frames": s.frames,
            "recall_by_width": {
                w: {"branches": c.truth, "recall": c.recall} for w, c in sorted(tallies.by_width[key].items())
            },
            "reliability": reliability(tallies.confidences[key]),
            "at_0.8": share_correct_above(tallies.confidences[key], 0.8),
            "mean_confidence_at_0.8": mean_confidence_above(tallies.confidences[key], 0.8),
            "min_confidence_for_90pct": lowest_reliable_threshold(tallies.confidences[key]),
            "calibration_error": expected_calibration_error(tallies.confidences[key]),
            "at_confidence_floors": {
                str(floor): {"recall": c.recall, "false_per_frame": c.false_per_frame}
                for floor, c in tallies.floors[key].items()
            },
            "at_target_min_confidence": {
                "threshold": TARGET_MIN_CONFIDENCE,
                "recall": tallies.confident[key].recall,
                "false_per_frame": tallies.confident[key].false_per_frame,
                "target_within_5cm": tallies.confident[key].target_accuracy,
            },
        }
    return out


def polygon_at(annotations: dict, pixel: tuple[float, float]) -> int | None:
    """Index of the annotated region holding a left-image pixel (x, y); None when it lies in none (regions never
    overlap, `../shared/data/trees/README.md`)."""
    for index, region in enumerate(annotations["regions"]):
        contour = np.asarray(region["polygon"], dtype=np.float32).reshape(-1, 1, 2)
        if cv2.pointPolygonTest(contour, (float(pixel[0]), float(pixel[1])), False) >= 0:
            return index
    return None


def polygon_hits(annotations: dict, pixel: tuple[float, float]) -> str:
    """'branch', 'not_branch' or 'unlabelled' for a left-image pixel (x, y)."""
    index = polygon_at(annotations, pixel)
    return "unlabelled" if index is None else annotations["regions"][index]["label"]


def real_pair_scores(annotations: dict, branches: Sequence[Branch], target_min_confidence: float) -> dict:
    """A result's cut points on a hand-labelled real pair (`../shared/data/trees/README.md`, "How to score"):
    how many lie on branch polygons, on not-branch ones and on none, the issue's precision, and — because a
    pruner reads them differently — how many of those on branch polygons lie on a trunk (a main stem: the
    issue's precision counts them, a robot must not cut there), how many of the branches holding the
    annotation's cut candidates got a cut point, and the counts among the cut points at or above
    `target_min_confidence` (what a robot would act on)."""
    regions = annotations["regions"]
    at = [polygon_at(annotations, b.pixel) for b in branches]
    hits = ["unlabelled" if i is None else regions[i]["label"] for i in at]
    labelled = [h for h in hits if h != "unlabelled"]
    on_branch = hits.count("branch")
    candidates = {c["region"] for c in annotations.get("cut_candidates", [])}
    return {
        "cut_points": len(hits),
        "on_branch": on_branch,
        "on_trunk": sum(
            i is not None and regions[i]["label"] == "branch" and regions[i]["kind"] == "trunk" for i in at
        ),
        "on_not_branch": len(labelled) - on_branch,
        "unlabelled": len(hits) - len(labelled),
        "precision": on_branch / len(labelled) if labelled else None,
        "candidate_branches": len(candidates),
        "candidate_branches_reached": len(candidates & set(at)),
        "acted_on": {
            label: sum(h == label for h, b in zip(hits, branches) if b.confidence >= target_min_confidence)
            for label in ("branch", "not_branch", "unlabelled")
        },
    }


#: the learned network's class indices (`CLASSES`)
TRUNK_CLASS, BRANCH_CLASS = CLASSES.index("trunk"), CLASSES.index("branch")


def network_classes(pipeline: Pipeline) -> np.ndarray | None:
    """`H×W` arg-max class (`CLASSES` index) of the learned network on the pipeline's last frame, with the
    segmenter's looks at its width; None for other segmenters. The disparity is the frame's final one: where
    `[stereo] refine_branches` refined the branch instances' own pixels, the network's input differs there
    from the one it segmented (a diagnostic, not the segmentation itself)."""
    segmenter, last = pipeline.segmenter, pipeline.last
    if not isinstance(segmenter, LearnedSegmenter) or last is None:
        return None
    return segmenter.logits(last.left, last.disparity).argmax(axis=0)


def region_pixels(
    annotations: dict, masks: BranchMasks, disparity: np.ndarray, network_classes: np.ndarray | None
) -> list[dict]:
    """Per annotated region: its label, kind, pixel count, median valid disparity (px: how near it is against
    the other regions — the pairs have no calibration), the shares of its pixels the segmenter's final masks
    give to a branch instance ("as_branch") and to the trunk ("as_trunk"), and, given the learned network's
    arg-max classes (`CLASSES` indices, `H×W`), the shares it called branch and trunk before the instance step
    ("network_branch", "network_trunk"): whether a stem was not seen, or seen and then dropped."""
    height, width = masks.labels.shape
    trunk = masks.trunk()
    if trunk is None:
        trunk = np.zeros((height, width), bool)
    branch = np.isin(masks.labels, masks.branch_ids())
    out = []
    for index, region in enumerate(annotations["regions"]):
        inside = np.zeros((height, width), np.uint8)
        # vertices at 1/16 px (`shift` 4); the annotations' origin is the top-left pixel's centre, as OpenCV's
        points = np.round(np.asarray(region["polygon"], dtype=np.float64) * 16).astype(np.int32)
        cv2.fillPoly(inside, [points], 1, lineType=cv2.LINE_8, shift=4)
        pixels = inside.astype(bool)
        size = int(np.count_nonzero(pixels))
        count = max(1, size)  # the divisor of the shares: a polygon thinner than a pixel has none
        valid = disparity[pixels & (disparity > 0)]
        row = {
            "region": index,
            "label": region["label"],
            "kind": region["kind"],
            "pixels": size,
            "median_disparity_px": round(float(np.median(valid)), 1) if valid.size else None,
            "as_branch": np.count_nonzero(pixels & branch) / count,
            "as_trunk": np.count_nonzero(pixels & trunk) / count,
        }
        if network_classes is not None:
            row["network_branch"] = np.count_nonzero(pixels & (network_classes == BRANCH_CLASS)) / count
            row["network_trunk"] = np.count_nonzero(pixels & (network_classes == TRUNK_CLASS)) / count
        out.append(row)
    return out


def shares_by_kind(regions: list[dict]) -> dict[str, dict[str, float]]:
    """`region_pixels` rows pooled by kind of region, each share weighted by the region's pixels."""
    pooled: dict[str, dict[str, float]] = {}
    for row in regions:
        kind = pooled.setdefault(row["kind"], {"pixels": 0})
        kind["pixels"] += row["pixels"]
        for key in ("as_branch", "as_trunk", "network_branch", "network_trunk"):
            if key in row:
                kind[key] = kind.get(key, 0.0) + row[key] * row["pixels"]
    return {
        kind: {
            key: (value if key == "pixels" else round(value / max(1, totals["pixels"]), 3))
            for key, value in totals.items()
        }
        for kind, totals in pooled.items()
    }


def draw_overlay(
    path: Path, left: np.ndarray, annotations: dict, masks: BranchMasks | None, branches: Sequence[Branch]
) -> None:
    """Left image with instances tinted (the trunk cyan), polygons (green branch, red not-branch) and cut points."""
    image = cv2.cvtColor(left, cv2.COLOR_RGB2BGR).astype(np.float32)
    if masks is not None:
        rng = np.random.default_rng(1)
        for value in np.unique(masks.labels):
            if value == 0 or value in masks.ignored_ids:
                continue
            colour = (255, 255, 0) if value == masks.trunk_id else rng.integers(60, 255, 3)
            tinted = masks.labels == value
            image[tinted] = 0.5 * image[tinted] + 0.5 * np.asarray(colour, np.float32)
    image = image.astype(np.uint8)
    for region in annotations["regions"]:
        colour = (0, 200, 0) if region["label"] == "branch" else (0, 0, 220)
        cv2.polylines(image, [np.round(np.asarray(region["polygon"])).astype(np.int32)], True, colour, 1)
    marks = {"branch": (0, 255, 0), "not_branch": (0, 0, 255), "unlabelled": (0, 255, 255)}
    for b in branches:
        x, y = b.pixel
        cv2.circle(image, (int(round(x)), int(round(y))), 6, marks[polygon_hits(annotations, (x, y))], 2)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), image)


def run_real(segmenters: list[str], overlays: Path | None) -> dict:
    """Cut-point precision on the hand-labelled real pairs, per segmenter."""
    from stereo.io import read_rgb

    out: dict[str, dict] = {}
    if not TREES.is_dir():
        return out
    for folder in sorted(p for p in TREES.iterdir() if (p / "annotations.json").is_file()):
        annotations = json.loads((folder / "annotations.json").read_text())
        left, right = read_rgb(folder / "left.png"), read_rgb(folder / "right.png")
        for name in segmenters:
            config = untracked_whole_frame(REAL_MAX_DISP.get(folder.name, 192))
            pipeline = Pipeline(
                config, focal_px=REAL_FOCAL_PX, baseline_m=REAL_BASELINE_M, segmenter=benchmark_segmenter(name)
            )
            result = pipeline.process(left, right)
            masks = pipeline.last.masks
            regions = (
                None
                if masks is None
                else region_pixels(annotations, masks, pipeline.last.disparity, network_classes(pipeline))
            )
            out[f"{folder.name}/{name}"] = {
                **real_pair_scores(annotations, result.branches, needed_for_target(pipeline)),
                "pixels_by_kind": None if regions is None else shares_by_kind(regions),
                "pixels_by_region": regions,
                "ms_segmenter": result.timing_ms["masks"],
            }
            if overlays is not None:
                draw_overlay(
                    overlays / f"{folder.name}_{name.replace('/', '_band')}.png",
                    left,
                    annotations,
                    masks,
                    result.branches,
                )
    return out


def print_tables(synthetic: dict, real: dict) -> None:
    print(
        f"{'stereo/segmenter':<28} {'recall≤5cm [95 % interval]':>26} {'median err':>10} "
        f"{'false/frame [95 %]':>19} {'ms/frame':>9}"
        f"   at confidence ≥ {TARGET_MIN_CONFIDENCE}: recall, false/frame, target ≤ 5 cm"
    )
    for key, r in synthetic.items():
        acted = r["at_target_min_confidence"]
        (low, high), (f_low, f_high) = r["recall_ci95"], r["false_per_frame_ci95"]
        print(
            f"{key:<28} {r['recall']:>10.1%} [{low:5.1%}–{high:5.1%}] {r['median_error_cm']:>8.2f}cm "
            f"{r['false_per_frame']:>6.2f} [{f_low:4.2f}–{f_high:4.2f}] {r['ms_per_frame']:>9.1f}   "
            f"{acted['recall']:>6.1%} {acted['false_per_frame']:>6.2f} {acted['target_within_5cm']:>6.0%}"
        )
    lit = {key: r["recall_minus_normal_light"] for key, r in synthetic.items() if r["recall_minus_normal_light"]}
    if lit:
        print(
            "\nrecall under changed light minus the same segmenter's in the scenes' own light, paired [95 % interval]"
        )
        for key, d in lit.items():
            low, high = d["ci95"]
            print(f"{key:<28} {d['difference']:>+7.1%} [{low:+6.1%} … {high:+6.1%}]")
    paired = {key: r["recall_minus_first"] for key, r in synthetic.items() if r["recall_minus_first"]}
    if paired:
        print("\nrecall minus the first segmenter's with the same stereo, paired over the same scenes [95 % interval]")
        for key, d in paired.items():
            low, high = d["ci95"]
            print(f"{key:<28} {d['difference']:>+7.1%} [{low:+6.1%} … {high:+6.1%}]  (vs {d['first']})")
    print("\ncounting only the cut points at or above a confidence floor (recall, false cut points a frame)")
    for key, r in synthetic.items():
        cells = "  ".join(
            f"≥ {floor}: {c['recall']:>5.1%} {c['false_per_frame']:>5.2f}"
            for floor, c in r["at_confidence_floors"].items()
        )
        print(f"{key:<28} {cells}")
    print("\nrecall within 5 cm by branch width (px at 640×360: branches, recall)")
    for key, r in synthetic.items():
        cells = "  ".join(
            f"{w}: {c['branches']:>3} {c['recall']:>5.0%}" for w, c in r["recall_by_width"].items() if w != "hidden"
        )
        print(f"{key:<28} {cells}")
    print("\nreliability (confidence bin: cut points, share within 5 cm (their mean confidence))")
    for key, r in synthetic.items():
        cells = "  ".join(
            f"{label}: {n:>3} {share:>4.0%} ({mean:.2f})" if n else f"{label}: {n:>3}   -         "
            for label, n, share, mean in r["reliability"]
        )
        count, share = r["at_0.8"]
        print(
            f"{key:<28} {cells}   ≥0.8: {count} cut points, {share:.0%} correct "
            f"(mean confidence {r['mean_confidence_at_0.8']:.2f}); "
            f"≥90 % correct from confidence {r['min_confidence_for_90pct']}; "
            f"calibration error {r['calibration_error']:.3f}"
        )
    if real:
        print(
            f"\n{'real pair/segmenter':<28} {'cuts':>5} {'branch':>6} {'(trunk)':>7} {'not br.':>7} {'unlab.':>6} "
            f"{'precision':>9} {'cand.':>5} {'ms':>6}   at its target confidence: branch, not br., unlab."
        )
        for key, r in real.items():
            print(
                f"{key:<28} {r['cut_points']:>5} {r['on_branch']:>6} {r['on_trunk']:>7} {r['on_not_branch']:>7} "
                f"{r['unlabelled']:>6} {'-' if r['precision'] is None else format(r['precision'], '.2f'):>9} "
                f"{r['candidate_branches_reached']:>2}/{r['candidate_branches']:<2} {r['ms_segmenter']:>6.0f}   "
                f"{r['acted_on']['branch']:>6} {r['acted_on']['not_branch']:>7} {r['acted_on']['unlabelled']:>6}"
            )
        print(
            "\nshare of each kind of annotated region's pixels in a branch instance / the trunk "
            "(in brackets the learned network's arg-max before the instance step: branch / trunk)"
        )
        for key, r in real.items():
            cells = "  ".join(
                f"{kind}: {c['as_branch']:>4.0%} / {c['as_trunk']:>4.0%}"
                + (f" ({c['network_branch']:>4.0%} / {c['network_trunk']:>4.0%})" if "network_branch" in c else "")
                for kind, c in (r["pixels_by_kind"] or {}).items()
            )
            print(f"{key:<28} {cells}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=240, help="held-out synthetic scenes (default 240)")
    parser.add_argument(
        "--segmenters",
        nargs="+",
        help="segmenter names (default learned structure; with --real-orchard: learned)",
    )
    parser.add_argument("--cache", type=Path, help="folder caching rendered scenes and their sgbm disparity")
    parser.add_argument("--overlays", type=Path, help="write real-pair overlays here")
    parser.add_argument(
        "--hardware",
        action="store_true",
        help="the synthetic scenes with orchard hardware around the tree (wires, posts, stakes, painted rods)",
    )
    parser.add_argument(
        "--light",
        nargs="+",
        default=[],
        choices=list(LIGHT_CHANGES),
        help="also score the scenes under these changes of light (both images; stereo 'sgbm-<change>')",
    )
    parser.add_argument(
        "--hd720",
        action="store_true",
        help="also score the scenes rendered at 1280×720 through the onboard pipeline (stereo 'roi-hd720')",
    )
    parser.add_argument("--skip-real", action="store_true", help="leave out the real pairs")
    parser.add_argument(
        "--real-orchard",
        action="store_true",
        help="only the real orchard RGB-D samples (../shared/data/real_orchard_rgbd): trunk+leader pixels found",
    )
    parser.add_argument(
        "--real-orchard-width",
        type=int,
        default=PRODUCT_FRAME_WIDTH,
        help=f"the real orchard tiles enlarged to this width, px (default {PRODUCT_FRAME_WIDTH}: the product's "
        f"smallest frame; {TILE}: the tiles as they are)",
    )
    parser.add_argument("--json", type=Path, help="write all numbers here")
    args = parser.parse_args(argv)
    print(f"CPU: {cpu_name()} (shared machine: absolute times are noisy)")
    if args.real_orchard:
        if not TILE <= args.real_orchard_width <= 4096:
            parser.error(f"--real-orchard-width must lie in {TILE}..4096 px")
        return main_real_orchard(args.segmenters or ["learned"], args.overlays, args.json, args.real_orchard_width)
    args.segmenters = args.segmenters or ["learned", "structure"]
    start = time.perf_counter()
    synthetic = run_synthetic(args.segmenters, args.scenes, args.cache, args.hardware, args.light, args.hd720)
    real = {} if args.skip_real else run_real(args.segmenters, args.overlays)
    print_tables(synthetic, real)
    print(
        f"\n{args.scenes} scenes at {SIZE[0]}×{SIZE[1]}{' with orchard hardware' if args.hardware else ''}, "
        f"seeds {FIRST_SEED}–{FIRST_SEED + args.scenes - 1}; "
        f"{time.perf_counter() - start:.0f} s"
    )
    if args.json is not None:
        numbers = {"cpu": cpu_name(), "orchard_hardware": args.hardware, "synthetic": synthetic, "real": real}
        write_json(args.json, numbers)
    return 0


def main_real_orchard(
    segmenters: list[str],
    overlays: Path | None,
    json_path: Path | None,
    frame_width: int = PRODUCT_FRAME_WIDTH,
    folder: Path = REAL_ORCHARD,
) -> int:
    """`--real-orchard`: each segmenter on the real orchard samples in `folder` (`real_orchard.run_real_orchard`),
    its table printed, overlays in `overlays`/<segmenter> when more than one is run; 0 (a message and nothing run
    when the data set is absent: a checkout without ../shared skips it)."""
    if not (folder / "samples").is_dir():
        print(f"real orchard RGB-D: no data set at {folder} (skipped; see its README for the format)", file=sys.stderr)
        return 0
    start = time.perf_counter()
    results = {}
    for name in segmenters:
        where = None if overlays is None else overlays / name if len(segmenters) > 1 else overlays
        results[name] = run_real_orchard(benchmark_segmenter(name), folder, where, frame_width)
        print_real_orchard(name, results[name])
    print(
        f"\n{time.perf_counter() - start:.0f} s; the 'depth' disparity's scale is picked with the hand mask "
        "(allowed for a measurement, not what a robot has)"
    )
    if json_path is not None:
        write_json(json_path, {"cpu": cpu_name(), "real_orchard": results})
    return 0


def write_json(path: Path, numbers: dict) -> None:
    """`numbers` as indented JSON at `path` (its folder made)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(numbers, indent=1) + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
