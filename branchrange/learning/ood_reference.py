"""Measuring a model's out-of-distribution reference (`ood.OodReference`) on frames of its training domain.

The shipped models' reference is measured on the first 160 calibration scenes (`OOD_SEEDS`: the training
distribution, never trained on, in their own light), the network seeing each 640×360 scene at
its own width as `LearnedSegmenter` does by default: the first two thirds fit the statistic's mean and
spread, the last third gives the values a frame is read by and the flag threshold. A fine-tuned model
(a model bundle) has another training domain: measure its reference with `model_reference` on frames of it —
its user frames together with the synthetic ones it was trained with — so that its flag clears where it
learnt.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from branchrange.core.segmentation.learned import LearnedSegmenter, LearnedSegmenterConfig
from branchrange.core.segmentation.ood import OOD_KEY, OodReference, fitted_reference, frame_statistic
from branchrange.learning.samples import evaluation_scene

#: the scenes a model's reference is measured on: the first `OOD_FRAMES` of the calibration scenes (2861–3100),
#: so a calibrated model's are rendered already
OOD_FRAMES = 160
OOD_SEEDS = (2861, 2861 + OOD_FRAMES)
#: what the shipped models' reference frames are (`OodReference.domain`)
SHIPPED_DOMAIN = "synthetic park scenes {first}–{last}, 640×360, SGBM, own light"


def first_look_statistic(segmenter: LearnedSegmenter, left: np.ndarray, disparity: np.ndarray) -> float:
    """`ood.frame_statistic` of a frame (`uint8 H×W×3`, disparity `float32 H×W` px) as `segmenter` computes
    them at run time: on its first look's logits (`LearnedSegmenter.first_look`)."""
    return frame_statistic(segmenter.first_look(left, np.asarray(disparity, dtype=np.float32)))


def model_reference(
    model: Path, frames: Iterable[tuple[np.ndarray, np.ndarray]], domain: str, threads: int = 1
) -> OodReference:
    """The `OodReference` of the ONNX `model` from training-domain `frames` (left image, disparity), in order:
    the first two thirds fit, the rest are held out (`ood.fitted_reference`)."""
    segmenter = LearnedSegmenter(LearnedSegmenterConfig(model=str(model), calibrated=False, ood=False, threads=threads))
    return fitted_reference((first_look_statistic(segmenter, left, d) for left, d in frames), domain)


def store_reference(model: Path, reference: OodReference) -> None:
    """Write `reference` under `ood.OOD_KEY` into the JSON beside `model` (made when absent), keeping the rest."""
    meta_path = model.with_suffix(".json")
    meta = json.loads(meta_path.read_text(encoding="utf-8")) if meta_path.is_file() else {}
    meta[OOD_KEY] = reference.to_json_dict()
    meta_path.write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")


def measure_model_reference(
    model: Path,
    cache: Path | None,
    seeds: tuple[int, int] = OOD_SEEDS,
    log: Callable[[str], object] = print,
) -> OodReference:
    """Measure the reference of the ONNX `model` on the synthetic scenes `seeds` [first, last) (rendered into, or
    read from, `cache`) and store it in its JSON (`store_reference`)."""
    frames = ((scene["left"], scene["sgbm"]) for scene in (evaluation_scene(s, cache) for s in range(*seeds)))
    reference = model_reference(model, frames, SHIPPED_DOMAIN.format(first=seeds[0], last=seeds[1] - 1))
    store_reference(model, reference)
    log(
        f"out-of-distribution reference of {model.name} from {reference.frames} frames (scenes {seeds[0]}–"
        f"{seeds[1] - 1}): a frame is flagged beyond {reference.threshold:.2f} "
        f"(held-out median {float(np.median(reference.held_out)):.2f}, "
        f"fitted {reference.mean:.2f} ± {reference.std:.2f})"
    )
    return reference
