"""What the depth's precision at the cut adds to a cut point's confidence (`[cutpoints] cut_disparity_noise_px`).

A cut point is right when it lies within 5 cm of a true one, and a matcher's depth error grows with Z²
(Z = f·B / d), so the same fit is less sure far away. This benchmark takes every cut point of the learned
segmenter with SGBM (the default setting, and one look as on board) on the calibration scenes
(`CALIBRATION_SEEDS`; the recorded JSON is from 2861–2980, before they were 240) and on held-out scenes
(50000 on), with the factor left out and no calibration: the raw confidence, the cut point's depth and
whether it is right. Then, for each σ_d of `--sigmas`, the score is that raw confidence
times `cutpoints.depth_precision_score` at the cut point's depth, an isotonic map is fitted on the
calibration scenes (as `branchrange.learning.calibration` does) and read on the held-out ones. It prints:
- the share right by distance, over both sets, for all cut points and for the top quarter of raw
  confidence — why the factor exists;
- per σ_d the area under the ROC curve on both sets (how well the score ranks right above wrong) and,
  held out, the cut points at calibrated ≥ 0.8 and ≥ 0.9 with their share right (the issue's test).
σ_d is chosen on the calibration scenes alone; the held-out columns only check it. No timing.

    PYTHONPATH=. .venv/bin/python benchmarks/depth_precision.py --cache-calibration out/segdata/calibration \
        --cache out/segbench --json benchmarks/depth_precision_results.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from benchmarks.machine import cpu_name
from benchmarks.segmenter import FIRST_SEED
from branchrange.core.confidence import cut_point_outcomes, fit_calibration
from branchrange.core.cutpoints import CutPointConfig, depth_precision_score
from branchrange.core.geometry import StereoGeometry
from branchrange.core.pipeline import Pipeline, untracked_whole_frame, with_exact_disparity
from branchrange.core.segmentation.learned import LearnedSegmenter, LearnedSegmenterConfig
from branchrange.learning.calibration import CALIBRATION_SEEDS
from branchrange.learning.samples import evaluation_scene

#: the learned segmenter's settings compared: trunk band (px) of the default and of one look
SETTINGS = {"default": 40, "one look": 0}
DISTANCE_BINS_M = (0.0, 1.0, 1.5, 2.0, 2.5, 3.0, 5.0)


def cut_points(trunk_band_px: int, seeds: range, cache: Path | None) -> np.ndarray:
    """`(N, 5)` per cut point: raw confidence without the depth factor, depth Z (m), f (px), B (m), right (0/1)."""
    segmenter = LearnedSegmenter(LearnedSegmenterConfig(calibrated=False, trunk_band_px=trunk_band_px))
    config = with_exact_disparity(untracked_whole_frame())  # the factor left out: σ_d 0, as for exact disparity
    rows = []
    for seed in seeds:
        scene = evaluation_scene(seed, cache)
        f, b, cx, cy = (float(v) for v in scene["camera"])
        pipeline = Pipeline(config, focal_px=f, baseline_m=b, principal_point=(cx, cy), segmenter=segmenter)
        result = pipeline.process_disparity(
            scene["left"], scene["sgbm"], scene["sgbm_conf"], backend="sgbm", right=scene["right"]
        )
        outcomes = cut_point_outcomes(
            [(branch.confidence, branch.cut_point_m) for branch in result.branches],
            [t["cut_point_m"] for t in scene["truth"]],
        )
        rows += [
            (raw, branch.cut_point_m[2], f, b, float(right)) for (raw, right), branch in zip(outcomes, result.branches)
        ]
    return np.array(rows, dtype=np.float64).reshape(-1, 5)


def with_depth_factor(points: np.ndarray, sigma_px: float) -> np.ndarray:
    """`(N,)` raw confidences of `points` (`cut_points`' rows) times the depth factor for σ_d = `sigma_px`."""
    config = CutPointConfig(cut_disparity_noise_px=sigma_px)
    factor = [depth_precision_score(z, StereoGeometry(f, b, 0.0, 0.0), config) for z, f, b in points[:, 1:4]]
    return np.asarray(points[:, 0] * np.array(factor), dtype=np.float64)


def roc_area(score: np.ndarray, right: np.ndarray) -> float:
    """Area under the ROC curve: the chance that a right cut point scores above a wrong one (ties half)."""
    right = right.astype(bool)
    ranks = np.empty(len(score))
    order = np.argsort(score, kind="stable")
    ranks[order] = np.arange(1, len(score) + 1)
    for value in np.unique(score):  # ties share their mean rank
        tied = score == value
        ranks[tied] = ranks[tied].mean()
    n_right, n_wrong = int(right.sum()), int((~right).sum())
    return float((ranks[right].sum() - n_right * (n_right + 1) / 2) / (n_right * n_wrong))


def sweep(calibration: np.ndarray, held_out: np.ndarray, sigmas: list[float]) -> list[dict]:
    """Per σ_d: ROC areas on both sets and the held-out cut points at calibrated ≥ 0.8 / ≥ 0.9."""
    rows = []
    for sigma in sigmas:
        fit_scores, test_scores = with_depth_factor(calibration, sigma), with_depth_factor(held_out, sigma)
        calibrate = fit_calibration(fit_scores.tolist(), (calibration[:, 4] > 0).tolist())
        calibrated = np.array([calibrate(s) for s in test_scores])
        row = {
            "sigma_px": sigma,
            "roc_area_calibration": roc_area(fit_scores, calibration[:, 4]),
            "roc_area_held_out": roc_area(test_scores, held_out[:, 4]),
        }
        for level in (0.8, 0.9):
            kept = calibrated >= level
            row[f"at_{level}"] = [int(kept.sum()), float(held_out[kept, 4].mean()) if kept.any() else None]
        rows.append(row)
    return rows


def by_distance(points: np.ndarray) -> list[dict]:
    """Share right per distance bin, for all cut points and for the top quarter of raw confidence."""
    top = points[:, 0] >= np.quantile(points[:, 0], 0.75)
    rows = []
    for low, high in zip(DISTANCE_BINS_M[:-1], DISTANCE_BINS_M[1:]):
        inside = (points[:, 1] >= low) & (points[:, 1] < high)
        rows.append(
            {
                "depth_m": [low, high],
                "cut_points": int(inside.sum()),
                "right": float(points[inside, 4].mean()) if inside.any() else None,
                "top_quarter": int((inside & top).sum()),
                "top_quarter_right": float(points[inside & top, 4].mean()) if (inside & top).any() else None,
            }
        )
    return rows


def _percent(value: float | None) -> str:
    return "   –  " if value is None else f"{100 * value:5.1f}%"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=60, help="held-out scenes from seed 50000 (default 60)")
    parser.add_argument("--sigmas", type=float, nargs="+", default=[0.0, 0.05, 0.1, 0.15, 0.2, 0.3])
    parser.add_argument("--cache", type=Path, help="folder caching the held-out scenes")
    parser.add_argument("--cache-calibration", type=Path, help="folder caching the calibration scenes")
    parser.add_argument("--json", type=Path, help="write all numbers here")
    args = parser.parse_args()
    report: dict = {"cpu": cpu_name(), "settings": {}}
    print(f"CPU: {report['cpu']} (no timing here)")
    for name, band in SETTINGS.items():
        calibration = cut_points(band, range(*CALIBRATION_SEEDS), args.cache_calibration)
        held_out = cut_points(band, range(FIRST_SEED, FIRST_SEED + args.scenes), args.cache)
        distances, rows = (
            by_distance(np.concatenate([calibration, held_out])),
            sweep(calibration, held_out, args.sigmas),
        )
        report["settings"][name] = {"trunk_band_px": band, "by_distance": distances, "sweep": rows}
        print(f"\n{name} (trunk band {band} px): {len(calibration)} calibration / {len(held_out)} held-out cut points")
        print("depth        cut points  right   top quarter  right")
        for d in distances:
            low, high = d["depth_m"]
            print(
                f"{low:.1f}–{high:.1f} m   {d['cut_points']:10d}  {_percent(d['right'])}  "
                f"{d['top_quarter']:11d}  {_percent(d['top_quarter_right'])}"
            )
        print("σ_d px  ROC area cal / held out   held out ≥ 0.8        ≥ 0.9")
        for r in rows:
            (n8, s8), (n9, s9) = r["at_0.8"], r["at_0.9"]
            print(
                f"{r['sigma_px']:5.2f}   {r['roc_area_calibration']:.3f} / {r['roc_area_held_out']:.3f}"
                f"          {n8:4d} {_percent(s8)}   {n9:4d} {_percent(s9)}"
            )
    if args.json:
        args.json.write_text(json.dumps(report, indent=1), encoding="utf-8")


if __name__ == "__main__":
    main()
