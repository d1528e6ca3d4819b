"""What a fine-tuned bundle's confidence means: "on a branch" (the user's labels) × "within 5 cm given on a branch".

A user's labelled frames say whether a cut point lies on a branch (`branchrange.learning.heldout`), not whether its 3-D
position is right: that needs true depth, which a user's frames do not have. A confidence of "on a branch"
alone is over-confident for flying — a cut point on the right pixels with a poor disparity is 10 cm off and
would still read 0.95, and `cutpoints.target_min_confidence` (chosen for the shipped model's "within 5 cm")
would let it through. So a bundle's confidence is the product of two measured probabilities, each a
monotone function of the raw confidence c:

    confidence(c) = P(on a labelled branch | c)            held-out labelled frames (`calibration_table`)
                  × P(within 5 cm | on a true branch, c)    synthetic calibration scenes (`depth_factor`)

The second is measured for the fine-tuned model itself on `DEPTH_FACTOR_SCENES` of the shipped calibration
scenes (never trained on): SGBM, each branch refined on its own pixels, as on board; its cut points whose
pixel lies on a true branch (judged as the labelled frames are) scored by the shipped calibration's 5 cm
rule. The product then means what the shipped model's confidence means — the share of such cut points
within 5 cm — so the same `target_min_confidence` asks the same of both. What it assumes: that on a branch,
the stereo error on the user's trees is like the synthetic scenes' (640×360, ranges 0.8–3 m); the manual
says so.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from branchrange.core.confidence import ConfidenceCalibration, fit_calibration
from branchrange.core.segmentation.learned import SCENE_WIDTH
from branchrange.learning.calibration import CALIBRATION_SEEDS, raw_outcomes

#: how many of the calibration scenes (from the first of `CALIBRATION_SEEDS`) the depth factor is measured on
DEPTH_FACTOR_SCENES = 60
#: fewer on-branch cut points than this: no depth factor, and the bundle's confidences are not calibrated
MIN_ON_BRANCH_CUT_POINTS = 20


def depth_factor(
    model: Path,
    scenes: int,
    band: int,
    cache: Path | None,
    log: Callable[[str], object] = print,
    min_cut_points: int = MIN_ON_BRANCH_CUT_POINTS,
) -> ConfidenceCalibration | None:
    """P(within 5 cm | on a true branch) as a function of the ONNX `model`'s raw confidence, seen with trunk band
    `band` px on the first `scenes` calibration scenes (rendered into `cache` when not there); None (and the log
    says why) when fewer than `min_cut_points` of its cut points lie on a branch."""
    first = CALIBRATION_SEEDS[0]
    seeds = (first, first + scenes)
    measured = raw_outcomes(model, seeds, cache, [(SCENE_WIDTH, band)], on_branch_only=True)
    outcomes = [o for by_light in measured.values() for group in by_light.values() for o in group]
    if len(outcomes) < min_cut_points:
        log(
            f"trunk band {band} px: {len(outcomes)} cut points on a branch in synthetic scenes {first}–{seeds[1] - 1} "
            f"(at least {min_cut_points} are needed to say how often they are within 5 cm)"
        )
        return None
    factor = fit_calibration([c for c, _ in outcomes], [ok for _, ok in outcomes])
    share = float(np.mean([ok for _, ok in outcomes]))
    log(
        f"trunk band {band} px: {share:.0%} of {len(outcomes)} cut points on a branch in synthetic scenes "
        f"{first}–{seeds[1] - 1} lie within 5 cm (at raw confidence 0.5: {factor(0.5):.0%}, 0.9: {factor(0.9):.0%})"
    )
    return factor
