"""How noisy one cut point is, in the pixels `[tracking]` states its noise in — measured, not assumed.

The fused tracks' covariance (`branchrange/onboard/mavlink/world_tracks.py`) takes each cut point's noise as
`lateral_sigma_px`·r / f across the line of sight and `disparity_sigma_px`·r² / (f·B) along it (× s^α for a
branch the region budget matched s times smaller, α = `tracking.scale_exponent`), and a `bias_share` of that
variance as a bias
that views from one spot share. This benchmark measures the three on rendered flights (`synth-flight`, the
approach benchmark's recipe, but another scene seed — 2 by default — so that nothing is chosen on the
flights `benchmarks/approach.py` judges, seed 1): each flight is replayed offline through the pipeline of
`deploy/onboard_cpu.toml` (every frame, as the daemon's pipeline), with the recording's truth masks and with
the built-in segmenter; every cut point within `MATCH_M` of a true cut point of its frame is an observation,
its error split along the line of sight to the true point and across it and turned into px:
depth px = e_los · f·B / (s^α·r²), lateral px = |e_across| · f / (s^α·r) / √2 (per axis).

It prints, per masks: observations, the 1-σ of each (the 68.3 % quantile of |error| — robust to the few
gross errors the match gate lets through), the RMS, and the share of the frame's cut points beyond the gate;
then `bias_share` (from the hover alone in the "all" row): per true cut point, the variance of its views'
mean error (shared) against the variance about that mean (independent), pooled over cut points, both in px;
then, per region `disparity_scale` s, the 1-σ in those px and at full resolution: if α is right, the first
is the same at every s (α = 1 would be the shrunk image's px, α = 0 no growth).

    .venv/bin/python benchmarks/cut_point_noise.py --json benchmarks/results/cut_point_noise.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]

from approach import DEPLOY_CONFIG, daemon_config, render_flight  # noqa: E402
from machine import cpu_name  # noqa: E402

from branchrange.core.frame_results import read_runs  # noqa: E402
from branchrange.offline.flight import FlightTruth  # noqa: E402
from branchrange.offline.flight_score import frame_positions  # noqa: E402
from branchrange.offline.replay import replay_recording  # noqa: E402

#: a cut point farther than this (m) from every true cut point of its frame is not an observation of one
MATCH_M = 0.10
#: the quantile of |error| that is 1 σ for a normal error
ONE_SIGMA_QUANTILE = 0.6827


def observation_errors_px(
    cut_m: np.ndarray, true_m: np.ndarray, focal_px: float, baseline_m: float, noise_scale: float = 1.0
) -> tuple[float, np.ndarray]:
    """(depth error px, lateral error (2,) px) of a cut point `cut_m` (3,) m against the true `true_m` (3,) m,
    both in the camera frame: the error along the line of sight to the true point scaled by f·B / (k·r²), and
    across it (two axes) by f / (k·r), k = `noise_scale` (s^α) — the units `disparity_sigma_px` and
    `lateral_sigma_px` are in (`focal_px` at full resolution)."""
    r = float(np.linalg.norm(true_m))
    los = true_m / r
    error = cut_m - true_m
    along = float(error @ los)
    across = error - along * los
    helper = np.array([1.0, 0.0, 0.0]) if abs(los[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    first = np.cross(los, helper)
    first /= np.linalg.norm(first)
    second = np.cross(los, first)
    lateral = np.array([across @ first, across @ second]) * focal_px / (noise_scale * r)
    return along * focal_px * baseline_m / (noise_scale * r * r), lateral


def one_sigma(values: Sequence[float]) -> float | None:
    """The `ONE_SIGMA_QUANTILE` of |values| (None for none): a normal error's σ, robust to a few gross ones."""
    return float(np.quantile(np.abs(values), ONE_SIGMA_QUANTILE)) if len(values) else None


def bias_share(groups: dict[int, list[np.ndarray]]) -> float | None:
    """Share of the error variance that views of one cut point share, from each cut point's error vectors (px):
    between-groups variance of the group means (less the part the within-group noise explains, σ²_w / n) over
    that plus the pooled within-group variance; None without two groups of ≥ 3 views."""
    kept = [np.asarray(v) for v in groups.values() if len(v) >= 3]
    if len(kept) < 2:
        return None
    within = float(np.mean([np.mean(np.sum((v - v.mean(0)) ** 2, axis=1)) * len(v) / (len(v) - 1) for v in kept]))
    shared = float(np.mean([np.sum(v.mean(0) ** 2) - within / len(v) for v in kept]))
    shared = max(0.0, shared)
    return shared / (shared + within) if shared + within > 0 else None


def flight_observations(directory: Path, masks: str, width: int, extra: Sequence[str]) -> dict[str, Any]:
    """Replay `directory` offline with `masks` ('truth' or 'builtin') and collect its observations' errors."""
    cfg = daemon_config(directory, width, extra)
    truth = FlightTruth.load(directory)
    with tempfile.TemporaryDirectory() as work:
        out = Path(work) / "results.jsonl"
        replay_recording(directory, cfg, out, progress=False, ignore_masks=masks != "truth")
        (_, results), *_ = read_runs(out)
    positions = frame_positions(truth)
    exponent = cfg.tracking.scale_exponent
    depth, lateral, scales, beyond, total = [], [], [], 0, 0
    by_cut: dict[int, list[np.ndarray]] = defaultdict(list)
    for result in results:
        position = positions.get(int(result["frame"]["index"]))
        if position is None:
            continue
        true_points = truth.cut_points_in_camera(position)
        camera = result["camera"]
        for branch in result["branches"]:
            total += 1
            cut = np.asarray(branch["cut_point_m"], dtype=np.float64)
            cut_id, true_m = min(true_points.items(), key=lambda item: float(np.linalg.norm(item[1] - cut)))
            if float(np.linalg.norm(true_m - cut)) > MATCH_M:
                beyond += 1
                continue
            scale = int(branch.get("disparity_scale") or 1)
            noise_scale = scale**exponent
            d, lat = observation_errors_px(cut, true_m, camera["focal_px"], camera["baseline_m"], noise_scale)
            depth.append(d)
            lateral.extend(lat.tolist())
            scales.append(scale)
            by_cut[cut_id].append(np.array([d, *lat]))
    return {
        "depth_px": depth,
        "lateral_px": lateral,
        "scales": scales,
        "exponent": exponent,
        "by_cut": by_cut,
        "beyond": beyond,
        "cut_points": total,
    }


def by_disparity_scale(found: dict[str, Any]) -> dict[str, dict[str, float | int | None]]:
    """Per region `disparity_scale` s (the budget matches a near branch s× smaller): observations and the 1-σ
    of depth and lateral error in the px `[tracking]` states σ in (full resolution ÷ s^α, α the run's
    `exponent`) and at full resolution — with the right α the first does not change with s."""
    scales = np.asarray(found["scales"], dtype=np.int64)
    exponent = float(found["exponent"])
    depth = np.asarray(found["depth_px"], dtype=np.float64)
    lateral = np.asarray(found["lateral_px"], dtype=np.float64).reshape(-1, 2)
    rows: dict[str, dict[str, float | int | None]] = {}
    for scale in sorted(set(scales.tolist())):
        chosen = scales == scale
        rows[str(scale)] = {
            "observations": int(chosen.sum()),
            "disparity_sigma_px": one_sigma(depth[chosen].tolist()),
            "disparity_sigma_full_px": one_sigma((scale**exponent * depth[chosen]).tolist()),
            "lateral_sigma_px": one_sigma(lateral[chosen].ravel().tolist()),
            "lateral_sigma_full_px": one_sigma((scale**exponent * lateral[chosen]).ravel().tolist()),
        }
    return rows


def summary(name: str, masks: str, found: dict[str, Any]) -> dict[str, Any]:
    """The row of one flight and masks: observations, σ and RMS of depth and lateral px, share beyond the gate,
    and the bias share of its views."""
    depth, lateral = found["depth_px"], found["lateral_px"]

    def rms(values: Sequence[float]) -> float | None:
        return float(math.sqrt(np.mean(np.square(values)))) if len(values) else None

    return {
        "flight": name,
        "masks": masks,
        "observations": len(depth),
        "disparity_sigma_px": one_sigma(depth),
        "disparity_rms_px": rms(depth),
        "lateral_sigma_px": one_sigma(lateral),
        "lateral_rms_px": rms(lateral),
        "beyond_gate_share": found["beyond"] / found["cut_points"] if found["cut_points"] else None,
        "bias_share": bias_share(found["by_cut"]),
        "by_disparity_scale": by_disparity_scale(found),
    }


def fmt(value: float | None, digits: int = 2) -> str:
    return "—" if value is None else f"{value:.{digits}f}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=2, help="scene seed of the flights (default 2; approach.py's is 1)")
    parser.add_argument("--speeds", default="0.5", help="approach speeds m/s, comma-separated (default 0.5)")
    parser.add_argument("--hover-s", type=float, default=3.0, help="hover seconds at 0.8 m (0: none; default 3)")
    parser.add_argument("--resolution", default="1280x720")
    parser.add_argument("--masks", choices=("truth", "builtin", "both"), default="both")
    parser.add_argument("--set", action="append", default=[], help="a section.key=value override of the deploy file")
    parser.add_argument("--json", type=Path, help="write the rows here")
    args = parser.parse_args(argv)
    width = int(args.resolution.split("x")[0])
    flights = [
        (f"{float(s):g} m/s", render_flight(args.resolution, float(s), 0.0, args.seed)) for s in args.speeds.split(",")
    ]
    if args.hover_s > 0:
        flights.append(("hover", render_flight(args.resolution, None, args.hover_s, args.seed)))
    rows = []
    exponent = daemon_config(flights[0][1], width, args.set).tracking.scale_exponent
    for masks in ("truth", "builtin") if args.masks == "both" else (args.masks,):
        pooled: dict[str, Any] = {
            "depth_px": [],
            "lateral_px": [],
            "scales": [],
            "exponent": exponent,
            "by_cut": {},
            "beyond": 0,
            "cut_points": 0,
        }
        for name, directory in flights:
            print(f"replaying {directory.name} with {masks} masks ...", file=sys.stderr)
            found = flight_observations(directory, masks, width, args.set)
            rows.append(summary(name, masks, found))
            pooled["depth_px"] += found["depth_px"]
            pooled["lateral_px"] += found["lateral_px"]
            pooled["scales"] += found["scales"]
            pooled["beyond"] += found["beyond"]
            pooled["cut_points"] += found["cut_points"]
            if name == "hover":  # views from one spot: what the bias share is about
                pooled["by_cut"] = found["by_cut"]
        rows.append(summary("all", masks, pooled))
    print(
        f"CPU: {cpu_name()}; {args.resolution}; seed {args.seed}; {DEPLOY_CONFIG.name}; overrides: {args.set or 'none'}"
    )
    print(
        f"{'flight':>8} {'masks':>7} {'obs':>5} {'disp σ px':>9} {'rms':>5} {'lat σ px':>8} {'rms':>5} "
        f"{'>gate':>5} {'bias':>5}"
    )
    for r in rows:
        print(
            f"{r['flight']:>8} {r['masks']:>7} {r['observations']:>5} {fmt(r['disparity_sigma_px']):>9} "
            f"{fmt(r['disparity_rms_px']):>5} {fmt(r['lateral_sigma_px']):>8} {fmt(r['lateral_rms_px']):>5} "
            f"{fmt(r['beyond_gate_share']):>5} {fmt(r['bias_share']):>5}"
        )
    print(f"\nby the region's disparity scale s, 1-σ px: as [tracking] states it (÷ s^{exponent:g}) / full resolution")
    print(f"{'masks':>7} {'s':>2} {'obs':>5} {'disp σ':>6} {'full':>5} {'lat σ':>6} {'full':>5}")
    for r in rows:
        if r["flight"] != "all":
            continue
        for scale, b in r["by_disparity_scale"].items():
            print(
                f"{r['masks']:>7} {scale:>2} {b['observations']:>5} {fmt(b['disparity_sigma_px']):>6} "
                f"{fmt(b['disparity_sigma_full_px']):>5} {fmt(b['lateral_sigma_px']):>6} "
                f"{fmt(b['lateral_sigma_full_px']):>5}"
            )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        payload = {
            "cpu": cpu_name(),
            "seed": args.seed,
            "resolution": args.resolution,
            "overrides": args.set,
            "scale_exponent": exponent,
            "rows": rows,
        }
        args.json.write_text(json.dumps(payload, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
