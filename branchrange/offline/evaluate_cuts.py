"""How far estimated cut points are from the truth, over a synthetic set written by `emcstereo synth`.

Per frame, the truth branches whose cut point is visible in the left image (`cut_visible`) are
matched one-to-one to the estimated cut points, nearest pair first (3D distance, gate 25 cm).
Scores:
- recall: share of visible truth branches whose matched cut point lies within 5 cm;
- median and 90th-percentile 3D cut-point error over the matched pairs (m);
- median distance error: |estimated − true camera distance| / true distance, in %;
- false cut points per frame: estimates with no truth cut point (visible or not) within 5 cm;
- target within 5 cm: share of frames with a target (the result's `target`, by the pipeline's target
  policy) whose cut point lies within 5 cm of a truth cut point.
Stereo: the set's exact disparity ('gt', the geometry's own error), 'sgbm', or 'emcstereo' (with
weights); masks: the set's instance masks ('gt') or the built-in segmenter ('segmenter').
"""

from __future__ import annotations

import json
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from branchrange.core.confidence import CORRECT_WITHIN_M
from branchrange.core.frame_result import Branch
from branchrange.core.pipeline import Pipeline, PipelineConfig, untracked_whole_frame, with_exact_disparity

RECALL_RADIUS_M = CORRECT_WITHIN_M
MATCH_GATE_M = 0.25
#: Depth (cm) at or beyond which the set's EXR marks sky (fp16 maximum 65504).
SKY_CM = 65000.0
STEREO_MODES = ("gt", "sgbm", "emcstereo")
MASK_MODES = ("gt", "segmenter")


class SynthSetError(ValueError):
    """A folder that is not a readable synthetic set; the message names the file at fault."""


@dataclass(frozen=True)
class SynthFrame:
    """One scene of a synthetic set: RGB pair, exact disparity (px, 0 on sky), instance mask
    (uint16), truth branches (dicts of the branches JSON) and the rig (f px, B m, cx, cy px)."""

    index: int
    left: np.ndarray
    right: np.ndarray
    disparity: np.ndarray
    mask: np.ndarray
    branches: list[dict]
    focal_px: float
    baseline_m: float
    principal_point: tuple[float, float]


def scene_indices(root: Path, split: str | None = None) -> list[int]:
    """Scene indices of a set: those listed in `virtualtree_<split>.txt`, or every branches file."""
    if split is not None:
        listing = root / f"virtualtree_{split}.txt"
        if not listing.is_file():
            raise SynthSetError(f"{listing} does not exist (splits: train, val, test)")
        return [int(m.group(1)) for m in re.finditer(r"left_(\d+)\.png", listing.read_text(encoding="utf-8"))]
    found = sorted(
        int(m.group(1))
        for p in (root / "branches").glob("branches_*.json")
        if (m := re.fullmatch(r"branches_(\d+)\.json", p.name))
    )
    if not found:
        raise SynthSetError(f"{root} holds no branches/branches_N.json: not a set written by `emcstereo synth`")
    return found


def read_frame(root: Path, index: int) -> SynthFrame:
    """Scene `index` of the set at `root`, with disparity from the EXR depth (cm)."""
    from branchrange.core.masks import read_mask
    from stereo.io import read_exr_depth, read_rgb

    record_path = root / "branches" / f"branches_{index}.json"
    try:
        record = json.loads(record_path.read_text(encoding="utf-8"))
        camera, files = record["camera"], record["files"]
        focal, baseline = float(camera["focal_px"]), float(camera["baseline_m"])
        principal = (float(camera["cx"]), float(camera["cy"]))
        branches = list(record["branches"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SynthSetError(f"{record_path}: not a readable branches file ({exc})") from exc
    depth_cm = read_exr_depth(root / files["depth"])
    valid = np.isfinite(depth_cm) & (depth_cm > 0) & (depth_cm < SKY_CM)
    disparity = np.zeros(depth_cm.shape, dtype=np.float32)
    disparity[valid] = focal * baseline / (depth_cm[valid] / 100.0)
    mask = read_mask(root / files["mask"], kind="instance").labels
    return SynthFrame(
        index,
        read_rgb(root / files["left"]),
        read_rgb(root / files["right"]),
        disparity,
        mask,
        branches,
        focal,
        baseline,
        principal,
    )


@dataclass
class CutScores:
    """Accumulated scores of one (stereo, masks) combination."""

    stereo: str
    masks: str
    frames: int = 0
    truth: int = 0
    recalled: int = 0
    errors_m: list[float] = field(default_factory=list)
    distance_errors_pct: list[float] = field(default_factory=list)
    false_cut_points: int = 0
    targets: int = 0
    targets_within: int = 0
    seconds: float = 0.0
    #: per frame: (truth branches found within 5 cm, visible truth branches, false cut points)
    frame_counts: list[tuple[int, int, int]] = field(default_factory=list)

    @property
    def recall(self) -> float:
        """Share of visible truth branches found within 5 cm."""
        return self.recalled / self.truth if self.truth else float("nan")

    def error_quantile(self, q: float) -> float:
        """Quantile `q` of the matched 3D errors (m); nan with no match."""
        return float(np.quantile(self.errors_m, q)) if self.errors_m else float("nan")

    @property
    def median_distance_error_pct(self) -> float:
        """Median |distance error| in % of the true distance."""
        return float(np.median(self.distance_errors_pct)) if self.distance_errors_pct else float("nan")

    @property
    def false_per_frame(self) -> float:
        """Estimated cut points with no truth within 5 cm, per frame."""
        return self.false_cut_points / self.frames if self.frames else float("nan")

    @property
    def target_accuracy(self) -> float:
        """Share of the frames' targets that lie within 5 cm of a truth cut point."""
        return self.targets_within / self.targets if self.targets else float("nan")

    def add_frame(self, truth: Sequence[dict], estimated: Sequence[Branch], target: Branch | None = None) -> None:
        """Match one frame's estimates (and its `target` branch, if any) to its truth (the set's branch
        records: `cut_point_m`, optional `cut_visible`) and accumulate the scores."""
        self.frames += 1
        recalled_before = self.recalled
        true_points = [np.asarray(b["cut_point_m"], dtype=np.float64) for b in truth]
        if target is not None:
            self.targets += 1
            aim = np.asarray(target.cut_point_m, dtype=np.float64)
            self.targets_within += any(float(np.linalg.norm(aim - t)) <= RECALL_RADIUS_M for t in true_points)
        guesses = [np.asarray(b.cut_point_m, dtype=np.float64) for b in estimated]
        pairs = sorted(
            (float(np.linalg.norm(g - t)), ti, gi) for ti, t in enumerate(true_points) for gi, g in enumerate(guesses)
        )
        used_truth: set[int] = set()
        used_guess: set[int] = set()
        close_matches = 0
        for distance, ti, gi in pairs:
            if distance > MATCH_GATE_M:
                break
            if ti in used_truth or gi in used_guess:
                continue
            used_truth.add(ti)
            used_guess.add(gi)
            if truth[ti].get("cut_visible", True):
                self.errors_m.append(distance)
                self.recalled += distance <= RECALL_RADIUS_M
                true_range = float(np.linalg.norm(true_points[ti]))
                self.distance_errors_pct.append(
                    100.0 * abs(float(np.linalg.norm(guesses[gi])) - true_range) / true_range
                )
            close_matches += distance <= RECALL_RADIUS_M
        visible = sum(1 for b in truth if b.get("cut_visible", True))
        self.frame_counts.append((self.recalled - recalled_before, visible, len(guesses) - close_matches))
        self.truth += visible
        self.false_cut_points += len(guesses) - close_matches

    def interval(self, level: float = 0.95, resamples: int = 2000, seed: int = 0) -> dict[str, tuple[float, float]]:
        """`level` intervals of `recall` and `false_per_frame` from a bootstrap over frames: the frames are
        drawn again with replacement `resamples` times (seeded, so a run repeats), and the statistic's
        central `level` range over the draws is returned. Why frames and not branches: one scene's branches
        succeed or fail together (its stereo, its light, its trunk), so a binomial interval over branches
        would be too narrow. NaN bounds with fewer than two frames."""
        counts = np.asarray(self.frame_counts, dtype=np.float64).reshape(-1, 3)
        if len(counts) < 2:
            return {"recall": (float("nan"),) * 2, "false_per_frame": (float("nan"),) * 2}
        sums = counts[_frame_draws(len(counts), resamples, seed)].sum(axis=1)  # (resamples, 3)
        return {
            "recall": _central(sums[:, 0] / np.maximum(sums[:, 1], 1.0), level),
            "false_per_frame": _central(sums[:, 2] / len(counts), level),
        }


def recall_difference_interval(
    scores: CutScores, baseline: CutScores, level: float = 0.95, resamples: int = 2000, seed: int = 0
) -> tuple[float, float]:
    """`level` interval of `scores.recall − baseline.recall` when both scored the same frames in the same
    order: the frames are drawn again together (paired), so what the frames share — which scenes are
    hard — cancels, and a difference too small to show in either interval alone can still be told apart."""
    mine = np.asarray(scores.frame_counts, dtype=np.float64).reshape(-1, 3)
    theirs = np.asarray(baseline.frame_counts, dtype=np.float64).reshape(-1, 3)
    if len(mine) != len(theirs) or not np.array_equal(mine[:, 1], theirs[:, 1]):
        raise ValueError("recall_difference_interval: the two scores did not see the same frames")
    if len(mine) < 2:
        return (float("nan"), float("nan"))
    draws = _frame_draws(len(mine), resamples, seed)
    visible = np.maximum(mine[draws, 1].sum(axis=1), 1.0)
    return _central((mine[draws, 0].sum(axis=1) - theirs[draws, 0].sum(axis=1)) / visible, level)


def _frame_draws(frames: int, resamples: int, seed: int) -> np.ndarray:
    """`(resamples, frames)` frame indices drawn with replacement, seeded."""
    return np.random.default_rng(seed).integers(0, frames, size=(resamples, frames))


def _central(values: np.ndarray, level: float) -> tuple[float, float]:
    """The central `level` range (low, high) of `values`."""
    low, high = np.percentile(values, [50.0 * (1.0 - level), 50.0 * (1.0 + level)])
    return float(low), float(high)


def _disparities(frame: SynthFrame, stereo: str, backend) -> tuple[np.ndarray, np.ndarray | None]:
    """(disparity, confidence) of a frame for a stereo mode: the set's truth or a backend's."""
    if stereo == "gt":
        return frame.disparity, None
    result = backend.compute(frame.left, frame.right)
    return result.disparity, result.confidence


def evaluate_cuts(
    root: str | Path,
    stereo_modes: Sequence[str] = ("gt", "sgbm"),
    mask_modes: Sequence[str] = MASK_MODES,
    *,
    weights: str | None = None,
    max_disp: int = 192,
    limit: int | None = None,
    split: str | None = None,
    min_confidence: float = 0.0,
    config: PipelineConfig | None = None,
) -> list[CutScores]:
    """Scores of every (stereo, masks) combination over the set at `root` (first `limit` scenes).

    Estimated cut points below `min_confidence` are not counted. The stereo backend runs once per
    frame and serves both mask modes.
    """
    root = Path(root)
    for mode in stereo_modes:
        if mode not in STEREO_MODES:
            raise ValueError(f"stereo mode {mode!r} is not one of {', '.join(STEREO_MODES)}")
        if mode == "emcstereo" and weights is None:
            raise ValueError("stereo mode 'emcstereo' needs weights (an untrained network gives meaningless depth)")
    for mode in mask_modes:
        if mode not in MASK_MODES:
            raise ValueError(f"mask mode {mode!r} is not one of {', '.join(MASK_MODES)}")
    indices = scene_indices(root, split)[:limit]
    config = config or untracked_whole_frame(max_disp)
    backends = {}
    for mode in stereo_modes:
        if mode != "gt":
            from stereo.backends import make_backend

            backends[mode] = make_backend(mode, weights=weights if mode == "emcstereo" else None, max_disp=max_disp)
    scores = {(s, m): CutScores(s, m) for s in stereo_modes for m in mask_modes}
    segmenter = config.segmenter.build()  # once: a learned one loads and checks its model file
    for index in indices:
        frame = read_frame(root, index)
        for stereo in stereo_modes:
            pipeline = Pipeline(
                with_exact_disparity(config) if stereo == "gt" else config,
                focal_px=frame.focal_px,
                baseline_m=frame.baseline_m,
                principal_point=frame.principal_point,
                segmenter=segmenter,
            )
            start = time.perf_counter()
            disparity, confidence = _disparities(frame, stereo, backends.get(stereo))
            stereo_seconds = time.perf_counter() - start
            for masks in mask_modes:
                start = time.perf_counter()
                result = pipeline.process_disparity(
                    frame.left,
                    disparity,
                    confidence,
                    mask=frame.mask if masks == "gt" else None,
                    backend=stereo,
                    right=None if stereo == "gt" else frame.right,  # a matcher's disparity is refined as on board
                )
                estimated = [b for b in result.branches if b.confidence >= min_confidence]
                entry = scores[(stereo, masks)]
                entry.add_frame(frame.branches, estimated, result.target)
                entry.seconds += stereo_seconds + time.perf_counter() - start
    return list(scores.values())


def format_table(scores: Sequence[CutScores]) -> str:
    """The scores as a fixed-width text table, one row per (stereo, masks)."""
    header = (
        f"{'stereo':<10} {'masks':<10} {'frames':>6} {'branches':>8} {'recall@5cm':>10} {'[95 % over frames]':>18} "
        f"{'median 3D':>10} {'p90 3D':>8} {'med dist err':>12} {'false/frame':>11} {'target@5cm':>10} "
        f"{'s/frame':>8}"
    )
    lines = [header, "-" * len(header)]
    for s in scores:
        low, high = s.interval()["recall"]
        lines.append(
            f"{s.stereo:<10} {s.masks:<10} {s.frames:>6} {s.truth:>8} {100 * s.recall:>9.1f}% "
            f"{f'[{100 * low:.1f}–{100 * high:.1f}%]':>18} "
            f"{100 * s.error_quantile(0.5):>8.2f}cm {100 * s.error_quantile(0.9):>6.2f}cm "
            f"{s.median_distance_error_pct:>11.2f}% {s.false_per_frame:>11.2f} "
            f"{100 * s.target_accuracy:>9.1f}% {s.seconds / max(s.frames, 1):>8.2f}"
        )
    return "\n".join(lines)


def scores_as_dict(scores: Sequence[CutScores]) -> list[dict]:
    """The scores as JSON-ready dicts (metres, %, counts)."""
    return [
        {
            "stereo": s.stereo,
            "masks": s.masks,
            "frames": s.frames,
            "branches": s.truth,
            "recall": s.recall,
            "recall_ci95": s.interval()["recall"],
            "median_error_m": s.error_quantile(0.5),
            "p90_error_m": s.error_quantile(0.9),
            "median_distance_error_pct": s.median_distance_error_pct,
            "false_per_frame": s.false_per_frame,
            "targets": s.targets,
            "target_within_5cm": s.target_accuracy,
            "seconds_per_frame": s.seconds / max(s.frames, 1),
        }
        for s in scores
    ]
