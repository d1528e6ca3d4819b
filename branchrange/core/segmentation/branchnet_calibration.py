"""Measuring how often the learned segmenter's cut points are right, to calibrate their confidence.

Scenes `CALIBRATION_SEEDS` (never trained on, and apart from the benchmark's held-out seeds from
50,000) go through the pipeline with SGBM — the onboard stereo stage, each branch refined on its own
pixels (`branchrange.core.branch_disparity`) as on board — and the model's raw confidences; each cut
point is correct when a true cut point lies within 5 cm. The isotonic fit of
correct on raw confidence (`branchrange.core.confidence.fit_calibration`) is stored in the model's
JSON under "confidence_calibrations", one table per width the network saw the 640×360 scenes at
(`LearnedSegmenterConfig.network_width`: the scores, and so what a raw confidence means, change with
it), where `LearnedSegmenter` reads it, with the defaults each implies: the lowest calibrated
confidence at which ≥ 90 % of cut points are right (a target's minimum) and the highest that keeps
≥ 98 % of the right ones (an obstacle's minimum).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

from branchrange.core.confidence import (
    ConfidenceCalibration,
    cut_point_outcomes,
    fit_calibration,
    highest_inclusive_threshold,
    lowest_reliable_threshold,
)
from branchrange.core.segmentation.branchnet_data import evaluation_scene

CALIBRATION_SEEDS = (2861, 2981)
#: how the network is calibrated seeing the scenes, (network width px, trunk band px): the default (the
#: scenes' own width, the trunk band looked at twice as large), one look as the onboard loop affords, and
#: twice the width in one look
CALIBRATION_SETTINGS = ((640, 40), (640, 0), (1280, 0))


def raw_outcomes(
    model: Path, seeds: tuple[int, int], cache: Path | None, network_width: int, trunk_band_px: int = 0
) -> list[tuple[float, bool]]:
    """(raw confidence, within 5 cm of a true cut point) of every cut point on scenes `seeds` [first, last),
    the network seeing them at `network_width` px (and the trunk band, `trunk_band_px`)."""
    from branchrange.core.pipeline import Pipeline, untracked_whole_frame
    from branchrange.core.segmentation.learned import LearnedSegmenter, LearnedSegmenterConfig

    config = LearnedSegmenterConfig(
        model=str(model), calibrated=False, network_width=network_width, trunk_band_px=trunk_band_px
    )
    segmenter = LearnedSegmenter(config)
    outcomes = []
    for seed in range(*seeds):
        scene = evaluation_scene(seed, cache)
        f, b, cx, cy = (float(v) for v in scene["camera"])
        pipeline = Pipeline(
            untracked_whole_frame(), focal_px=f, baseline_m=b, principal_point=(cx, cy), segmenter=segmenter
        )
        result = pipeline.process_disparity(
            scene["left"], scene["sgbm"], scene["sgbm_conf"], backend="sgbm", right=scene["right"]
        )
        outcomes += cut_point_outcomes(
            [(b.confidence, b.cut_point_m) for b in result.branches], [t["cut_point_m"] for t in scene["truth"]]
        )
    return outcomes


def calibrate_model(
    model: Path,
    seeds: tuple[int, int] = CALIBRATION_SEEDS,
    cache: Path | None = None,
    log: Callable[[str], object] = print,
    settings: tuple[tuple[int, int], ...] = CALIBRATION_SETTINGS,
) -> dict[tuple[int, int], ConfidenceCalibration]:
    """Fit the confidence calibration of the ONNX `model` for each (network width, trunk band) of `settings`
    and store them in the JSON beside it ("confidence_calibrations", replacing what was there); a setting
    with which the model finds no cut point on those scenes gets none (its confidences stay raw)."""
    tables, calibrations = [], {}
    for width, band in settings:
        outcomes = raw_outcomes(model, seeds, cache, width, band)
        if not outcomes:
            log(
                f"no cut points on scenes {seeds[0]}–{seeds[1] - 1} at width {width}, trunk band {band} px: "
                "that setting stays uncalibrated"
            )
            continue
        calibration = fit_calibration([c for c, _ in outcomes], [ok for _, ok in outcomes])
        calibrated = [(calibration(c), ok) for c, ok in outcomes]
        tables.append(
            {
                "network_width": width,
                "trunk_band_px": band,
                **calibration.to_json_dict(),
                "target_min_confidence": lowest_reliable_threshold(calibrated, 0.9),
                "obstacle_min_confidence": highest_inclusive_threshold(calibrated, 0.98),
                "seeds": list(seeds),
                "stereo": "sgbm",
                "cut_points": len(outcomes),
                "share_correct": round(float(np.mean([ok for _, ok in outcomes])), 4),
            }
        )
        calibrations[(width, band)] = calibration
        log(
            f"confidence calibration at network width {width}, trunk band {band} px, from {len(outcomes)} cut "
            f"points on scenes {seeds[0]}–{seeds[1] - 1}: {calibration}"
        )
    meta_path = model.with_suffix(".json")
    meta = json.loads(meta_path.read_text(encoding="utf-8")) if meta_path.is_file() else {}
    meta.pop("confidence_calibration", None)  # the single table of before widths were recorded
    meta["confidence_calibrations"] = tables
    meta_path.write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")
    return calibrations
