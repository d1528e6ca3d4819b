"""Measuring how often the learned segmenter's cut points are right, to calibrate their confidence.

Scenes `CALIBRATION_SEEDS` (never trained on, and apart from the benchmark's held-out seeds from
50,000) go through the pipeline with SGBM — the onboard stereo stage, each branch refined on its own
pixels (`branchrange.core.branch_disparity`) as on board — and the model's raw confidences; each cut
point is correct when a true cut point lies within 5 cm. Each scene is also seen under the changes of
light of `CALIBRATION_LIGHT_CHANGES` (SGBM computed again), and every frame counts toward the class of
light it measures as (`branchrange.core.light_check`): what is right depends on the light (at dusk the
same raw confidence is right far less often), and the segmenter reads a frame's confidences through the
table of its own light. The isotonic fit of correct on raw confidence
(`branchrange.core.confidence.fit_calibration`) is stored in the model's JSON under
"confidence_calibrations", one table per width the network saw the 640×360 scenes at
(`LearnedSegmenterConfig.network_width`: the scores, and so what a raw confidence means, change with
it), trunk band and light, where `LearnedSegmenter` reads it, with the defaults each implies: the lowest
calibrated confidence at which ≥ 90 % of cut points are right (a target's minimum; null when none is)
and the highest that keeps ≥ 98 % of the right ones (an obstacle's minimum).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from branchrange.core.confidence import (
    ConfidenceCalibration,
    cut_point_outcomes,
    fit_calibration,
    highest_inclusive_threshold,
    lowest_reliable_threshold,
)
from branchrange.learning.light_changes import LIGHT_CHANGES
from branchrange.learning.samples import evaluation_scene, scene_in_light, spawned_pool

#: 240 scenes: fitted on either half, the default's ≥ 90 %-right threshold reads 0.65 or 0.76 (0.70 on all; one look
#: 0.72 or 0.73); in one process per core (`outcomes_in_workers`) they take about what 120 took in one
CALIBRATION_SEEDS = (2861, 3101)
#: how the network is calibrated seeing the scenes, (network width px, trunk band px): the default (the
#: scenes' own width, the trunk band looked at twice as large), one look as the onboard loop affords, and
#: twice the width in one look
CALIBRATION_SETTINGS = ((640, 40), (640, 0), (1280, 0))
#: the scenes are also calibrated under each of these changes of light (`light_changes`); every frame, in
#: its own light or changed, counts toward the class of light it measures as (`light_check.measure_light`)
CALIBRATION_LIGHT_CHANGES = tuple(LIGHT_CHANGES)
#: a class of light with fewer cut points than this gets no table of its own (it is read as "normal")
MIN_CUT_POINTS_PER_LIGHT = 200


#: (confidence, within 5 cm of a true cut point) of every cut point, by the class of light its frame measured as
OutcomesByLight = dict[str, list[tuple[float, bool]]]


def raw_outcomes(
    model: Path,
    seeds: tuple[int, int],
    cache: Path | None,
    settings: Sequence[tuple[int, int]],
    light_changes: Sequence[str] = (),
    on_branch_only: bool = False,
) -> dict[tuple[int, int], OutcomesByLight]:
    """Per (network width px, trunk band px) of `settings`: (raw confidence, within 5 cm of a true cut point) of
    every cut point on scenes `seeds` [first, last), by the class of light each frame measures as
    (`light_check.LIGHTS`); each scene in its own light and under each of `light_changes`
    (`branchrange.learning.samples.scene_in_light`), in seed order. Each scene is loaded once for all settings.
    With `on_branch_only`, only the cut points whose pixel lies on a true branch
    (`branchrange.learning.heldout.judged_pixels`, as a user's labelled frames judge them): what "within 5 cm" is
    given "on a branch" (`branchrange.learning.depth_factor`)."""
    from branchrange.core.pipeline import Pipeline, untracked_whole_frame
    from branchrange.core.segmentation.learned import LearnedSegmenter, LearnedSegmenterConfig
    from branchrange.learning.heldout import judged_pixels
    from branchrange.learning.samples import classes_from_instances

    segmenters = {
        (width, band): LearnedSegmenter(
            LearnedSegmenterConfig(model=str(model), calibrated=False, network_width=width, trunk_band_px=band)
        )
        for width, band in settings
    }
    outcomes: dict[tuple[int, int], OutcomesByLight] = {setting: {} for setting in segmenters}
    for seed in range(*seeds):
        scene = evaluation_scene(seed, cache)
        f, baseline, cx, cy = (float(v) for v in scene["camera"])
        truth = [t["cut_point_m"] for t in scene["truth"]]
        classes = classes_from_instances(scene["mask"]) if on_branch_only else None
        pipelines = {  # untracked: each frame is measured on its own; one per setting for the scene's camera
            setting: Pipeline(
                untracked_whole_frame(), focal_px=f, baseline_m=baseline, principal_point=(cx, cy), segmenter=segmenter
            )
            for setting, segmenter in segmenters.items()
        }
        for lit in [scene, *(scene_in_light(scene, seed, change, cache) for change in light_changes)]:
            for setting, pipeline in pipelines.items():
                result = pipeline.process_disparity(
                    lit["left"], lit["sgbm"], lit["sgbm_conf"], backend="sgbm", right=lit["right"]
                )
                light = pipeline.last.masks.light if pipeline.last and pipeline.last.masks else None
                branches = result.branches
                if classes is not None:
                    judged, _ = judged_pixels(classes, scene["mask"], [b.pixel for b in branches])
                    branches = tuple(b for b, ok in zip(branches, judged, strict=True) if ok)
                outcomes[setting].setdefault("normal" if light is None else light.light, []).extend(
                    cut_point_outcomes([(b.confidence, b.cut_point_m) for b in branches], truth)
                )
    return outcomes


def seed_ranges(seeds: tuple[int, int], parts: int) -> list[tuple[int, int]]:
    """[first, last) split into at most `parts` contiguous ranges of near-equal size, in order (none empty)."""
    first, last = seeds
    bounds = np.linspace(first, last, max(1, min(parts, last - first)) + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:], strict=True) if b > a]


def outcomes_in_workers(
    model: Path,
    seeds: tuple[int, int],
    cache: Path | None,
    settings: Sequence[tuple[int, int]],
    light_changes: Sequence[str],
    workers: int,
) -> dict[tuple[int, int], OutcomesByLight]:
    """`raw_outcomes` with the scenes split into `workers` contiguous ranges, each measured in its own process
    (1 = in this one), and joined in seed order: the same lists as one process makes, so the same fit.

    Why processes: a scene takes ~150 ms per setting and light, 240 scenes × 6 lights × 3 settings ~11 min in
    one process; the segmenter runs onnxruntime on one thread and numpy holds the GIL between its calls, so
    only processes use a second core. Each renders its own scenes: no two write one cache file."""
    ranges = seed_ranges(seeds, workers)
    if len(ranges) == 1:
        return raw_outcomes(model, seeds, cache, settings, light_changes)
    with spawned_pool(len(ranges)) as pool:
        futures = [pool.submit(raw_outcomes, model, r, cache, settings, light_changes) for r in ranges]
        parts = [future.result() for future in futures]
    joined: dict[tuple[int, int], OutcomesByLight] = {(width, band): {} for width, band in settings}
    for part in parts:
        for setting, by_light in part.items():
            for light, outcomes in by_light.items():
                joined[setting].setdefault(light, []).extend(outcomes)
    return joined


def calibrate_model(
    model: Path,
    seeds: tuple[int, int] = CALIBRATION_SEEDS,
    cache: Path | None = None,
    log: Callable[[str], object] = print,
    settings: tuple[tuple[int, int], ...] = CALIBRATION_SETTINGS,
    light_changes: Sequence[str] = CALIBRATION_LIGHT_CHANGES,
    min_cut_points: int = MIN_CUT_POINTS_PER_LIGHT,
    workers: int = 1,
    measure_ood: bool = True,
) -> dict[tuple[int, int, str], ConfidenceCalibration]:
    """Fit the confidence calibration of the ONNX `model` for each (network width, trunk band) of `settings`
    and each class of light with at least `min_cut_points` cut points (the scenes in their own light and under
    `light_changes`), and store them in the JSON beside it ("confidence_calibrations", replacing what was
    there). Each table records the least calibrated confidence at which ≥ 90 % of its cut points are right
    ("target_min_confidence", null when none is) and the highest that keeps ≥ 98 % of the right ones. A
    setting with which the model finds no cut point in normal light gets none (its confidences stay raw). The
    scenes are measured in `workers` processes (`outcomes_in_workers`); the tables do not depend on how many.
    With `measure_ood`, the model's out-of-distribution reference is then measured on the first 160 of the
    scenes and stored beside the tables (`measure_reference_on`, "ood")."""
    tables, calibrations = [], {}
    measured = outcomes_in_workers(model, seeds, cache, settings, light_changes, workers)
    for width, band in settings:
        by_light = measured[(width, band)]
        if not by_light.get("normal"):
            log(
                f"no cut points on scenes {seeds[0]}–{seeds[1] - 1} in normal light at width {width}, trunk band "
                f"{band} px: that setting stays uncalibrated"
            )
            continue
        for light, outcomes in by_light.items():
            if light != "normal" and len(outcomes) < min_cut_points:
                log(f"{light} light at width {width}, trunk band {band} px: only {len(outcomes)} cut points, no table")
                continue
            calibration = fit_calibration([c for c, _ in outcomes], [ok for _, ok in outcomes])
            calibrated = [(calibration(c), ok) for c, ok in outcomes]
            tables.append(
                {
                    "network_width": width,
                    "trunk_band_px": band,
                    "light": light,
                    **calibration.to_json_dict(),
                    "target_min_confidence": lowest_reliable_threshold(calibrated, 0.9),
                    "obstacle_min_confidence": highest_inclusive_threshold(calibrated, 0.98),
                    "seeds": list(seeds),
                    "light_changes": list(light_changes),
                    "stereo": "sgbm",
                    "cut_points": len(outcomes),
                    "share_correct": round(float(np.mean([ok for _, ok in outcomes])), 4),
                }
            )
            calibrations[(width, band, light)] = calibration
            log(
                f"confidence calibration at network width {width}, trunk band {band} px, {light} light, from "
                f"{len(outcomes)} cut points on scenes {seeds[0]}–{seeds[1] - 1}: {calibration}"
            )
    meta_path = model.with_suffix(".json")
    meta = json.loads(meta_path.read_text(encoding="utf-8")) if meta_path.is_file() else {}
    meta.pop("confidence_calibration", None)  # the single table of before widths were recorded
    meta["confidence_calibrations"] = tables
    meta_path.write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")
    if measure_ood:
        measure_reference_on(model, seeds, cache, log)
    return calibrations


def measure_reference_on(model: Path, seeds: tuple[int, int], cache: Path | None, log: Callable[[str], object]) -> None:
    """Measure the out-of-distribution reference of `model` on the first `OOD_FRAMES` of the calibration scenes
    `seeds` (`branchrange.learning.ood_reference.measure_model_reference`); with fewer than `ood.MIN_REFERENCE_FRAMES`
    of them, say so and leave the model's JSON as it is."""
    from branchrange.core.segmentation.ood import MIN_REFERENCE_FRAMES
    from branchrange.learning.ood_reference import OOD_FRAMES, measure_model_reference  # imports the segmenter

    first, last = seeds[0], min(seeds[1], seeds[0] + OOD_FRAMES)
    if last - first < MIN_REFERENCE_FRAMES:
        log(
            f"only {last - first} scenes: too few for an out-of-distribution reference "
            f"(at least {MIN_REFERENCE_FRAMES})"
        )
        return
    measure_model_reference(model, cache, (first, last), log)
