"""The scoring functions of `benchmarks/approach.py`, on small hand-made inputs with known answers.

Why: the approach benchmark decides whether the daemon meets issue 37's flight targets (target switches,
σ calibration, latency per range band, setpoints held by the speed cap); a helper that miscounts would
pass or fail them silently, and the benchmark itself renders and flies for minutes, too slow for the
tests. `benchmarks/` is not a package: the tests put it on the path as its scripts do.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))
import approach  # noqa: E402


def test_switches_count_only_targets_more_than_10_cm_apart() -> None:
    a = np.array([1.0, 2.0, -2.0])
    b = a + np.array([0.2, 0.0, 0.0])
    sent = [a, a + [0.03, 0, 0], None, a + [0.05, 0, 0], b, b + [0, 0.02, 0], None, a]
    # a→a+3 cm, gap, →a+5 cm: the same branch; →b (15 cm): one; b→b+2 cm: none; gap, →a (≈ 20 cm): two
    assert approach.switch_indices(sent) == [4, 7]


def test_a_target_exactly_10_cm_away_is_no_switch() -> None:
    a = np.zeros(3)
    assert approach.switch_indices([a, a + [0.10, 0, 0]]) == []
    assert approach.switch_indices([a, a + [0.1001, 0, 0]]) == [1]
    assert approach.switch_indices([None, None]) == []


def test_sigma_coverage_by_axis_and_radius() -> None:
    covariance = np.diag([1e-4, 1e-4, 4e-4])  # σ = 2 cm along z, the largest axis
    errors = np.array([[0, 0, 0.01], [0, 0, 0.03], [0.05, 0, 0.01], [0, 0, -0.019]])
    result = approach.sigma_coverage(errors, np.repeat(covariance[None], 4, axis=0))
    # along z within 2 cm: 1st, 3rd, 4th; whole error within 2 cm: 1st, 4th
    assert result["axis"] == 0.75
    assert result["radius"] == 0.5
    assert result["sends"] == 4


def test_sigma_radius_expected_is_the_gaussian_share() -> None:
    isotropic = np.repeat((1e-4 * np.eye(3))[None], 3, axis=0)
    # |x| ≤ σ for an isotropic 3-D Gaussian: P(χ²₃ ≤ 1) = 0.199
    assert approach.sigma_coverage(np.zeros((3, 3)), isotropic)["radius_expected"] == pytest.approx(0.199, abs=0.02)
    flat = np.repeat(np.diag([1e-12, 1e-12, 1e-4])[None], 3, axis=0)
    # one dominant axis: the 1-D 68.3 %
    assert approach.sigma_coverage(np.zeros((3, 3)), flat)["radius_expected"] == pytest.approx(0.683, abs=0.02)


def test_errors_drawn_from_the_reported_covariance_are_68_percent_covered() -> None:
    covariance = np.array([[4e-4, 1e-4, 0.0], [1e-4, 1e-4, 0.0], [0.0, 0.0, 2e-5]])
    errors = np.random.default_rng(3).multivariate_normal(np.zeros(3), covariance, 2000)
    covariances = np.repeat(covariance[None], 2000, axis=0)
    result = approach.sigma_coverage(errors, covariances)
    assert result["axis"] == pytest.approx(0.683, abs=0.03)
    # the largest axis's σ is 20.7 mm, and the median |error| along it is 0.674 σ for a normal error
    assert result["sigma_mm"] == pytest.approx(20.7, abs=0.1)
    assert result["axis_error_mm"] == pytest.approx(0.674 * result["sigma_mm"], rel=0.08)
    # twice the error: the covariance is overconfident and the coverage says so
    assert approach.sigma_coverage(2 * errors, covariances)["axis"] == pytest.approx(0.383, abs=0.03)


def test_sigma_coverage_without_sends() -> None:
    assert approach.sigma_coverage(np.zeros((0, 3)), np.zeros((0, 3, 3)))["axis"] is None


@pytest.mark.parametrize(
    ("range_m", "band"), [(3.05, 0), (3.0, 0), (2.5, 0), (2.49, 1), (1.5, 2), (1.0, 3), (0.99, 4), (0.8, 4), (0.5, 4)]
)
def test_range_bands_are_half_metres_from_3_m_the_outer_ones_open(range_m: float, band: int) -> None:
    assert approach.band_of(range_m) == band


def test_band_labels() -> None:
    assert approach.band_label(0) == "3.0–2.5"
    assert approach.band_label(4) == "1.0–0.8"


def test_latency_bands_count_released_sent_and_late_frames() -> None:
    samples = [(2.9, 0.1), (2.8, 0.3), (2.7, None), (0.9, 0.6)]
    bands = approach.latency_bands(samples, max_age_s=0.5)
    assert bands[0] == {"band_m": "3.0–2.5", "released": 3, "sent": 2, "late": 0, "p50_ms": 200.0, "p95_ms": 290.0}
    assert bands[4] == {"band_m": "1.0–0.8", "released": 1, "sent": 1, "late": 1, "p50_ms": 600.0, "p95_ms": 600.0}
    assert bands[2]["released"] == 0 and bands[2]["p95_ms"] is None


def test_speed_cap_is_a_step_of_exactly_speed_times_dt() -> None:
    steps = [(0.25, 0.125), (0.25, 0.1), (0.251, 0.125), (0.25, 0.124), (0.1, 0.05)]
    # 0.5 m/s: 12.5 cm in 250 ms is the cap; 10 cm is free; 251 ms is within the ms rounding; 12.4 cm is free
    assert approach.speed_capped(steps, 0.5) == [True, False, True, False, True]


def test_a_point_stands_for_the_nearest_cut_point_within_10_cm() -> None:
    cuts = {1: np.zeros(3), 2: np.array([0.18, 0.0, 0.0])}
    assert approach.is_of(np.array([0.02, 0.0, 0.0]), 1, cuts)
    assert not approach.is_of(np.array([0.095, 0.0, 0.0]), 1, cuts)  # within 10 cm of 1, but 2 is nearer
    assert not approach.is_of(np.array([0.0, 0.11, 0.0]), 1, cuts)  # nearest, but 11 cm off


def test_confident_runs_and_when_each_became_eligible() -> None:
    samples = [(0.0, False, False), (0.1, True, False), (0.2, True, False), (0.3, True, True), (0.4, False, False)]
    samples += [(1.0, True, False), (1.5, True, False)]
    runs = approach.confident_runs(samples, end_s=2.5)
    assert runs == [
        {"start_s": 0.1, "end_s": 0.4, "eligible_after_s": 0.2},
        {"start_s": 1.0, "end_s": 2.5, "eligible_after_s": None},
    ]


def test_ready_in_time_fails_a_run_confident_for_a_second_without_eligibility() -> None:
    eligible_soon = {"start_s": 0.1, "end_s": 0.4, "eligible_after_s": 0.2}
    too_short_to_tell = {"start_s": 2.0, "end_s": 2.9, "eligible_after_s": None}
    never = {"start_s": 1.0, "end_s": 2.5, "eligible_after_s": None}
    late = {"start_s": 1.0, "end_s": 3.0, "eligible_after_s": 1.2}
    assert approach.ready_in_time([eligible_soon, too_short_to_tell])
    assert not approach.ready_in_time([eligible_soon, never])
    assert not approach.ready_in_time([late])


def test_border_pixels_within_2_percent_of_the_width() -> None:
    assert approach.is_border((10.0, 300.0), 1280, 720)
    assert approach.is_border((1260.0, 300.0), 1280, 720)
    assert approach.is_border((640.0, 700.0), 1280, 720)
    assert not approach.is_border((640.0, 360.0), 1280, 720)


def test_stats_in_millimetres() -> None:
    values = [0.001 * v for v in range(1, 11)]
    assert approach.stats_mm(values) == {"median": 5.5, "p90": 9.1, "max": 10.0}
    assert approach.stats_mm([]) == {"median": None, "p90": None, "max": None}


def test_preloaded_replay_releases_the_recordings_frames_at_their_times(tmp_path: Path) -> None:
    from synth_recording import write_tree_recording

    from camera.sources import PreloadedReplay, ReplaySource

    period_ns = 50_000_000
    directory = write_tree_recording(tmp_path / "rec", 4, period_ns)
    expected = list(ReplaySource(directory, pace="fast"))
    released: list[float] = []
    replay = PreloadedReplay(directory, pace="recorded")
    frames = []
    for frame in replay:
        released.append(time.monotonic())
        frames.append(frame)
    assert [f.index for f in frames] == [f.index for f in expected]
    assert [f.timestamp_ns for f in frames] == [f.timestamp_ns for f in expected]
    assert all(np.array_equal(a.left, b.left) and np.array_equal(a.mask, b.mask) for a, b in zip(frames, expected))
    # paced by the recording: frame k no earlier than k periods after the first
    assert all(t - released[0] >= k * period_ns / 1e9 - 1e-3 for k, t in enumerate(released))


def test_truth_mask_flights_take_the_noise_measured_for_truth_masks(tmp_path: Path) -> None:
    report = tmp_path / "noise.json"
    rows = [
        {"flight": "all", "masks": "builtin", "disparity_sigma_px": 0.3, "lateral_sigma_px": 4.5, "bias_share": 0.24},
        {"flight": "hover", "masks": "truth", "disparity_sigma_px": 0.2, "lateral_sigma_px": 1.0, "bias_share": 0.1},
        {
            "flight": "all",
            "masks": "truth",
            "disparity_sigma_px": 0.1012,
            "lateral_sigma_px": 1.641,
            "bias_share": 0.61,
        },
    ]
    report.write_text(json.dumps({"rows": rows}))
    assert approach.truth_mask_noise(report) == [
        "tracking.disparity_sigma_px=0.101",
        "tracking.lateral_sigma_px=1.64",
        "tracking.bias_share=0.61",
    ]
    # each is a valid override of the deploy file
    approach.daemon_config(tmp_path, 1280, approach.truth_mask_noise(report))
    assert approach.truth_mask_noise(tmp_path / "missing.json") == []
    assert approach.truth_mask_noise(None) == []


def _row(masks: str, axis: float | None, sends: int) -> dict:
    return {"masks": masks, "sigma": {"axis": axis, "sends": sends}}


def test_coverage_is_pooled_over_the_sends_of_every_flight_per_mask_source() -> None:
    rows = [_row("truth", 1.0, 30), _row("truth", 0.25, 10), _row("builtin", 0.5, 4), _row("builtin", None, 0)]
    # one track's error persists from send to send: a flight alone is nearly all or nothing
    assert approach.pooled_coverage(rows) == {"truth": pytest.approx((30 + 2.5) / 40, abs=1e-3), "builtin": 0.5}


def test_reports_of_other_seeds_pool_into_one_verdict(tmp_path: Path) -> None:
    def flight(axis: float) -> dict:
        return {
            "speed_m_s": 0.5,
            "masks": "truth",
            "off_5cm": 0,
            "border_targets": 0,
            "switches": 0,
            "nearest": {"ready": True},
            "sigma": {"axis": axis, "sends": 10},
            "latency_ms": [{"released": 5, "p95_ms": 100.0}],
        }

    paths = []
    for seed, axis in ((1, 1.0), (2, 0.4)):
        paths.append(tmp_path / f"seed{seed}.json")
        paths[-1].write_text(json.dumps({"load": f"{seed}.0", "flights": [flight(axis)], "targets": {}}))
    alone = approach.pool_reports(paths[:1])
    assert not alone["targets"]["1-σ covers 68 ± 10 % (pooled per masks)"]  # 100 %: too wide
    both = approach.pool_reports(paths)
    assert len(both["flights"]) == 2 and both["load"] == "1.0 | 2.0"
    assert both["targets"]["1-σ covers 68 ± 10 % (pooled per masks)"]  # 70 % over the two
