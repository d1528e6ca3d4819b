"""Does the segmenter know this scene? A per-frame out-of-distribution signal from its own class probabilities.

A segmenter trained on one kind of scene answers on any other too, and its confidences, calibrated on the
first kind, then mean nothing. This module says, per frame and for a few milliseconds, how far the network's
answer on it lies from its answers on the scenes it was trained for:

1. `frame_statistics`: a vector of `STATISTICS` from the class logits `(3, H, W)` of the network's first look at
   the frame (every `SUBSAMPLE`-th pixel each way): how its per-pixel certainty is spread (mean normalised
   entropy, the shares of pixels whose top probability is below 0.6 / 0.9 / 0.99), how much it calls trunk and
   branch, how certain it is where it calls them, and the logits' magnitude (mean log-sum-exp, the "energy",
   and the margin of the top logit over the next). A network on unfamiliar bark, light or tree form is less
   certain in more pixels and its logits are smaller; on a familiar scene they look like they did in training.
2. `OodReference`: those vectors' mean and (shrunk) covariance over frames of the training domain, stored in
   the model's JSON under "ood" (`measure_reference`; `branchrange train-segmenter --out DIR --ood-only`), and
   the Mahalanobis distances of more such frames, kept apart from the fit, to read a distance by.
3. `OodReference.reading`: a frame's distance, its `score` — the share of the reference's held-out frames
   that lie nearer (0..1: 0.5 is a typical training frame, 1 is farther than all of them) — and `flagged`
   when the distance exceeds the reference's `FLAG_QUANTILE` quantile (about 1 training frame in 100).

Why outputs, not features: the shipped ONNX files have one output, and exposing a feature map would mean
editing their graphs (the `onnx` package is not a run-time dependency) or shipping other files; the logits are
at hand, and the statistics cost ~1–2 ms a 640×360 frame (`benchmarks/shifted_domain.py` measures it).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

#: the key of a model JSON that holds its `OodReference`
OOD_KEY = "ood"
#: the statistics of one frame, in `frame_statistics`' order
STATISTICS = (
    "mean_entropy",
    "log_share_max_below_0.6",
    "log_share_max_below_0.9",
    "log_share_max_below_0.99",
    "log_share_trunk",
    "log_share_branch",
    "mean_branch_probability",
    "foreground_entropy",
    "mean_energy",
    "mean_margin",
)
#: the statistics are taken on every SUBSAMPLE-th pixel each way: a quarter of the pixels, the same statistics
SUBSAMPLE = 2
#: a share enters as log(share + this): shares of a few pixels and of none differ, and the log is near-normal
SHARE_FLOOR = 1e-3
#: the covariance is shrunk this far toward its diagonal: ~100 frames fit 10×10 entries (Ledoit–Wolf-like)
SHRINKAGE = 0.2
#: a frame is flagged when its distance exceeds this quantile of the reference's held-out distances
FLAG_QUANTILE = 0.99
#: of the frames `measure_reference` is given, this share fits the mean and covariance; the rest are held out
FIT_SHARE = 2 / 3
#: the fewest frames a reference may be measured on (fit and held out together)
MIN_REFERENCE_FRAMES = 12


class OodReferenceError(ValueError):
    """A model JSON's "ood" reference cannot be read (what is wrong is in the message)."""


def frame_statistics(logits: np.ndarray) -> np.ndarray:
    """`float64 (len(STATISTICS),)` statistics of class logits `(3, H, W)` (background, trunk, branch) of one
    frame; see the module docstring. Only every `SUBSAMPLE`-th pixel each way is read."""
    z = np.asarray(logits[:, ::SUBSAMPLE, ::SUBSAMPLE], dtype=np.float32).reshape(logits.shape[0], -1)
    top = z.max(axis=0)
    exp = np.exp(z - top)
    total = exp.sum(axis=0)
    p = exp / total
    entropy = -(p * np.log(np.maximum(p, 1e-12))).sum(axis=0) / math.log(z.shape[0])
    best = p.max(axis=0)
    label = p.argmax(axis=0)
    foreground = label > 0
    second = np.partition(z, -2, axis=0)[-2]
    count = max(1, z.shape[1])

    def log_share(mask: np.ndarray) -> float:
        return math.log(np.count_nonzero(mask) / count + SHARE_FLOOR)

    return np.array(
        [
            float(entropy.mean()),
            log_share(best < 0.6),
            log_share(best < 0.9),
            log_share(best < 0.99),
            log_share(label == 1),
            log_share(label == 2),
            float(p[2].mean()),
            float(entropy[foreground].mean()) if foreground.any() else 0.0,
            float((top + np.log(total)).mean()),
            float((top - second).mean()),
        ]
    )


@dataclass(frozen=True)
class OodReading:
    """One frame's out-of-distribution reading: Mahalanobis `distance` from the reference's mean, `score` (0..1,
    the share of held-out reference frames nearer) and `flagged` (distance over the reference's threshold)."""

    score: float
    distance: float
    flagged: bool


@dataclass(frozen=True)
class OodReference:
    """The training domain's statistics (see the module docstring): `mean` `(K,)`, `precision` `(K, K)` (inverse
    of the shrunk covariance), the held-out reference frames' `distances` `(M,)` sorted, and `threshold`, the
    distance a frame is flagged beyond. `frames`: how many frames were measured; `domain`: what they were."""

    mean: np.ndarray
    precision: np.ndarray
    distances: np.ndarray
    threshold: float
    frames: int
    domain: str

    def distance(self, statistics: np.ndarray) -> float:
        """The Mahalanobis distance of one frame's `frame_statistics` from the reference's mean."""
        d = np.asarray(statistics, dtype=np.float64) - self.mean
        return float(math.sqrt(max(0.0, float(d @ self.precision @ d))))

    def reading(self, statistics: np.ndarray) -> OodReading:
        """The `OodReading` of one frame's `frame_statistics`."""
        distance = self.distance(statistics)
        score = float(np.searchsorted(self.distances, distance, side="right")) / max(1, self.distances.size)
        return OodReading(round(score, 4), round(distance, 3), distance > self.threshold)

    def to_json_dict(self) -> dict[str, Any]:
        """The form stored under `OOD_KEY` in a model JSON (`from_json_dict` reads it back)."""
        return {
            "statistics": list(STATISTICS),
            "subsample": SUBSAMPLE,
            "mean": [round(float(v), 6) for v in self.mean],
            "precision": [[round(float(v), 6) for v in row] for row in self.precision],
            "held_out_distances": [round(float(v), 4) for v in self.distances],
            "threshold": round(float(self.threshold), 4),
            "flag_quantile": FLAG_QUANTILE,
            "frames": self.frames,
            "domain": self.domain,
        }

    @classmethod
    def from_json_dict(cls, data: Any) -> OodReference:
        """The reference stored by `to_json_dict`; `OodReferenceError` naming what is wrong (another statistics
        list means it was measured by another version of this module: measure it again)."""
        if not isinstance(data, dict):
            raise OodReferenceError("'ood' must be an object (measure it with branchrange train-segmenter --ood-only)")
        if data.get("statistics") != list(STATISTICS) or data.get("subsample") != SUBSAMPLE:
            raise OodReferenceError(
                "'ood' holds other statistics than this version computes: measure it again with "
                "branchrange train-segmenter --out DIR --ood-only"
            )
        try:
            k = len(STATISTICS)
            mean = np.asarray(data["mean"], dtype=np.float64)
            precision = np.asarray(data["precision"], dtype=np.float64)
            distances = np.sort(np.asarray(data["held_out_distances"], dtype=np.float64))
            threshold = float(data["threshold"])
            frames, domain = int(data["frames"]), str(data.get("domain", ""))
        except (KeyError, TypeError, ValueError) as exc:
            raise OodReferenceError(f"'ood' is incomplete or not numeric ({exc})") from None
        if mean.shape != (k,) or precision.shape != (k, k) or distances.ndim != 1 or distances.size == 0:
            raise OodReferenceError(f"'ood' needs a mean of {k} values, a {k}×{k} precision and held-out distances")
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(precision)) and math.isfinite(threshold)):
            raise OodReferenceError("'ood' holds values that are not finite numbers")
        return cls(mean, precision, distances, threshold, frames, domain)


def reference_in(meta: dict[str, Any]) -> OodReference | None:
    """The `OodReference` of a model's JSON metadata (a shipped model's, or a model bundle's: any dict with the
    `OOD_KEY` key), None when it has none; `OodReferenceError` when it cannot be read."""
    data = meta.get(OOD_KEY)
    return None if data is None else OodReference.from_json_dict(data)


def fitted_reference(statistics: Iterable[np.ndarray], domain: str, fit_share: float = FIT_SHARE) -> OodReference:
    """An `OodReference` from the `frame_statistics` of training-domain frames: the first `fit_share` of them fit
    the mean and covariance, the rest give the held-out distances and the flag threshold (their
    `FLAG_QUANTILE` quantile). ValueError with fewer than `MIN_REFERENCE_FRAMES` frames."""
    rows = np.asarray(list(statistics), dtype=np.float64)
    if rows.ndim != 2 or rows.shape[0] < MIN_REFERENCE_FRAMES:
        raise ValueError(f"an OOD reference needs at least {MIN_REFERENCE_FRAMES} frames, got {len(rows)}")
    fit = max(2, min(rows.shape[0] - 2, round(rows.shape[0] * fit_share)))
    mean = rows[:fit].mean(axis=0)
    covariance = np.cov(rows[:fit], rowvar=False)
    diagonal = np.diag(np.diag(covariance))
    shrunk = (1 - SHRINKAGE) * covariance + SHRINKAGE * diagonal + 1e-9 * np.eye(rows.shape[1])
    precision = np.linalg.inv(shrunk)
    reference = OodReference(mean, precision, np.zeros(1), math.inf, rows.shape[0], domain)
    held_out = np.sort([reference.distance(row) for row in rows[fit:]])
    threshold = float(np.quantile(held_out, FLAG_QUANTILE))
    return OodReference(mean, precision, held_out, threshold, rows.shape[0], domain)


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
            "training domain (this one: distance %.1f, score %.2f); its confidences were calibrated elsewhere, so "
            "check its cut points before trusting a target, and fine-tune it on frames of this orchard "
            "(docs/segmenter-ood.md)",
            self.flagged,
            self.seen,
            reading.distance,
            reading.score,
        )
        self.last_warning, self.seen, self.flagged = now, 0, 0
        return True
