"""Does the segmenter know this scene? A per-frame out-of-distribution signal from its own class logits.

A segmenter trained on one kind of scene answers on any other too, and its confidences, calibrated on the
first kind, then mean nothing. This module says, per frame and for about a millisecond, whether the network
hesitates where it should not:

1. `frame_statistic`: on the class logits `(3, H, W)` of the network's first look at a frame (every
   `SUBSAMPLE`-th pixel each way), the log share of *hesitant background*: pixels it calls background, more than
   a pixel away from any edge between its classes, whose top two logits lie within `HESITANT_MARGIN` of each
   other. On scenes like those it was trained on, the network hesitates only along the edges of trunks and
   branches; on a scene it does not know — other bark, a post or wire, a tree form or light it never saw — it
   hesitates over open background too.
2. `OodReference`: that statistic's mean and spread over frames of the model's training domain, stored in the
   model's JSON under "ood" (`branchrange.learning.ood_reference.measure_model_reference`; `branchrange train-segmenter
   --out DIR --ood-only`), and its values on more such frames kept apart from the fit, to read a frame's value by.
3. `OodReference.reading`: a frame's `z` (its statistic in standard deviations above the training frames'
   mean), its `score` — the share of the reference's held-out frames below it (0..1: 0.5 is a typical training
   frame, 1 beyond all of them) — and `flagged` when it exceeds the held-out frames' `FLAG_QUANTILE` quantile
   (about 1 training frame in 100).

How it was chosen (benchmarks/shifted_domain.py, benchmarks/RESULTS.md): on held-out training-domain frames
against frames of the shifted "orchard" domain (`SynthOptions.domain`) the statistics of the whole frame —
mean entropy, shares of pixels under a top probability, energy (log-sum-exp), logit margin, histograms of
them, and channel means and spreads of the network's feature maps at each scale — separated the two with an
AUROC of 0.68–0.87; the hesitant background alone 0.96 on a design set of orchard frames kept apart from
the ones it is reported on. The feature maps were also no better for a practical reason: the shipped ONNX
files have one output, and exposing another means editing their graphs (the `onnx` package is no run-time
dependency).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

log = logging.getLogger(__name__)

#: the key of a model JSON that holds its `OodReference`
OOD_KEY = "ood"
#: the name of the statistic (`frame_statistic`), stored with a reference so another one is not read by it
STATISTIC = "log_share_hesitant_background"
#: the statistic is taken on every SUBSAMPLE-th pixel each way: a quarter of the pixels, the same statistic
SUBSAMPLE = 2
#: a pixel hesitates when its top two class logits lie within this much of each other (probabilities ~0.73:0.27)
HESITANT_MARGIN = 1.0
#: the share enters as log(share + this): a few pixels and none differ, and its log is near-normal
SHARE_FLOOR = 1e-3
#: a frame is flagged when its statistic exceeds this quantile of the reference's held-out frames'
FLAG_QUANTILE = 0.99
#: of the frames a reference is measured on, this share fits the mean and spread; the rest are held out
FIT_SHARE = 2 / 3
#: the fewest frames a reference may be measured on (fit and held out together)
MIN_REFERENCE_FRAMES = 12
_BACKGROUND = 0
_NEIGHBOURS = np.ones((3, 3), np.uint8)


class OodReferenceError(ValueError):
    """A model JSON's "ood" reference cannot be read (what is wrong is in the message)."""


def frame_statistic(logits: np.ndarray) -> float:
    """The log share of hesitant background (see the module docstring) in class logits `(3, H, W)` (background,
    trunk, branch) of one frame; only every `SUBSAMPLE`-th pixel each way is read."""
    z = np.asarray(logits[:, ::SUBSAMPLE, ::SUBSAMPLE], dtype=np.float32)
    top, bottom = z.max(axis=0), z.min(axis=0)
    margin = 2 * top + bottom - z.sum(axis=0)  # top − second of three: second = sum − top − bottom
    label = z.argmax(axis=0).astype(np.uint8)
    edges = cv2.dilate(label, _NEIGHBOURS) != cv2.erode(label, _NEIGHBOURS)
    near_edge = cv2.dilate(edges.astype(np.uint8), _NEIGHBOURS) > 0
    hesitant = (label == _BACKGROUND) & ~near_edge & (margin < HESITANT_MARGIN)
    return math.log(np.count_nonzero(hesitant) / max(1, hesitant.size) + SHARE_FLOOR)


@dataclass(frozen=True)
class OodReading:
    """One frame's out-of-distribution reading: `z` (its statistic in standard deviations above the training
    frames' mean), `score` (0..1, the share of held-out reference frames below it) and `flagged`."""

    score: float
    z: float
    flagged: bool


@dataclass(frozen=True)
class OodReference:
    """The training domain's statistic (see the module docstring): its `mean` and `std` over the fitted frames,
    the held-out frames' values `held_out` `(M,)` sorted, and `threshold`, the value a frame is flagged beyond.
    `frames`: how many frames were measured; `domain`: what they were."""

    mean: float
    std: float
    held_out: np.ndarray
    threshold: float
    frames: int
    domain: str

    def reading(self, statistic: float) -> OodReading:
        """The `OodReading` of one frame's `frame_statistic`."""
        score = float(np.searchsorted(self.held_out, statistic, side="right")) / max(1, self.held_out.size)
        z = (statistic - self.mean) / self.std
        return OodReading(round(score, 4), round(z, 3), statistic > self.threshold)

    def to_json_dict(self) -> dict[str, Any]:
        """The form stored under `OOD_KEY` in a model JSON (`from_json_dict` reads it back)."""
        return {
            "statistic": STATISTIC,
            "subsample": SUBSAMPLE,
            "hesitant_margin": HESITANT_MARGIN,
            "mean": round(self.mean, 6),
            "std": round(self.std, 6),
            "held_out": [round(float(v), 5) for v in self.held_out],
            "threshold": round(self.threshold, 5),
            "flag_quantile": FLAG_QUANTILE,
            "frames": self.frames,
            "domain": self.domain,
        }

    @classmethod
    def from_json_dict(cls, data: Any) -> OodReference:
        """The reference stored by `to_json_dict`; `OodReferenceError` naming what is wrong (another statistic
        means it was measured by another version of this module: measure it again)."""
        if not isinstance(data, dict):
            raise OodReferenceError("'ood' must be an object (measure it with branchrange train-segmenter --ood-only)")
        measured = (data.get("statistic"), data.get("subsample"), data.get("hesitant_margin"))
        if measured != (STATISTIC, SUBSAMPLE, HESITANT_MARGIN):
            raise OodReferenceError(
                "'ood' holds another statistic than this version computes: measure it again with "
                "branchrange train-segmenter --out DIR --ood-only"
            )
        try:
            mean, std, threshold = float(data["mean"]), float(data["std"]), float(data["threshold"])
            held_out = np.sort(np.asarray(data["held_out"], dtype=np.float64))
            frames, domain = int(data["frames"]), str(data.get("domain", ""))
        except (KeyError, TypeError, ValueError) as exc:
            raise OodReferenceError(f"'ood' is incomplete or not numeric ({exc})") from None
        if held_out.ndim != 1 or held_out.size == 0 or not np.all(np.isfinite(held_out)):
            raise OodReferenceError("'ood' needs a non-empty list of finite held-out values")
        if not (math.isfinite(mean) and math.isfinite(threshold) and math.isfinite(std) and std > 0):
            raise OodReferenceError("'ood' needs a finite mean and threshold and a positive std")
        return cls(mean, std, held_out, threshold, frames, domain)


def reference_in(meta: dict[str, Any]) -> OodReference | None:
    """The `OodReference` of a model's JSON metadata (a shipped model's, or a model bundle's: any dict with the
    `OOD_KEY` key), None when it has none; `OodReferenceError` when it cannot be read."""
    data = meta.get(OOD_KEY)
    return None if data is None else OodReference.from_json_dict(data)


def fitted_reference(statistics: Iterable[float], domain: str, fit_share: float = FIT_SHARE) -> OodReference:
    """An `OodReference` from the `frame_statistic` of training-domain frames, in order: the first `fit_share` of
    them give the mean and spread, the rest the held-out values and the flag threshold (their `FLAG_QUANTILE`
    quantile). ValueError with fewer than `MIN_REFERENCE_FRAMES` frames."""
    values = np.asarray(list(statistics), dtype=np.float64)
    if values.size < MIN_REFERENCE_FRAMES:
        raise ValueError(f"an OOD reference needs at least {MIN_REFERENCE_FRAMES} frames, got {values.size}")
    fit = max(2, min(values.size - 2, round(values.size * fit_share)))
    held_out = np.sort(values[fit:])
    std = max(float(values[:fit].std(ddof=1)), 1e-6)
    threshold = float(np.quantile(held_out, FLAG_QUANTILE))
    return OodReference(float(values[:fit].mean()), std, held_out, threshold, int(values.size), domain)


#: a flagged frame is warned about at most once in this many seconds (`OodWarnings`)
WARNING_INTERVAL_S = 30.0


class OodWarnings:
    """Logs, at most once every `interval_s` seconds, that frames were flagged (`OodReading.flagged`), with how
    many of the frames seen since the last warning were: a user is told, from the log, that the segmenter's
    model does not know this orchard before trusting a target — and a flight of flagged frames is one line
    every `interval_s`, not one a frame. `clock`: seconds, monotonic (the daemon's and the tests')."""

    def __init__(self, interval_s: float = WARNING_INTERVAL_S, clock: Callable[[], float] = time.monotonic) -> None:
        self.interval_s, self.clock = interval_s, clock
        self.last_warning: float | None = None
        self.seen = self.flagged = 0

    def note(self, reading: OodReading | None) -> bool:
        """Count one frame's reading (None: no signal, not counted) and warn when due; whether it warned."""
        if reading is None:
            return False
        self.seen += 1
        self.flagged += reading.flagged
        now = self.clock()
        if not reading.flagged or (self.last_warning is not None and now - self.last_warning < self.interval_s):
            return False
        log.warning(
            "the segmenter's model does not look like it knows this scene: %d of the last %d frames are out of its "
            "training domain (this one: z %.1f, score %.2f); its confidences were calibrated elsewhere, so "
            "check its cut points before trusting a target, and fine-tune it on frames of this orchard "
            "(docs/segmenter-ood.md)",
            self.flagged,
            self.seen,
            reading.z,
            reading.score,
        )
        self.last_warning, self.seen, self.flagged = now, 0, 0
        return True
