"""The pure helpers of `benchmarks/segmenter.py` and `benchmarks/machine.py`, on small hand-made inputs.

Why: the segmenter benchmark's figures (cut points on the real trees' branch / trunk / not-branch polygons,
where each annotated region's pixels went, recall by branch width, the reliability table, which segmenter a
name builds) decide which segmenter ships; a helper that miscounts would mislead silently, since the benchmark
itself is too slow to run in the tests. Each expected value below is worked out by hand from the input.
`benchmarks/` is not a package: its scripts import their siblings with their own folder on the path, so the
tests put it there first.
"""

from __future__ import annotations

import math
import os
import platform
import sys
from pathlib import Path

import numpy as np
import pytest
from result_factory import branch

from branchrange.core.masks import BranchMasks
from branchrange.core.segmentation.learned import SHIPPED_MODELS, LearnedSegmenter, LearnedSegmenterConfig
from branchrange.core.segmentation.network_input import CLASSES
from branchrange.core.segmentation.structure import StructureSegmenter

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))
import machine  # noqa: E402
import segmenter as segmenter_benchmark  # noqa: E402


def square(x0: float, y0: float, x1: float, y1: float) -> list[list[float]]:
    """The polygon of the axis-aligned rectangle with corners (x0, y0) and (x1, y1)."""
    return [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]


#: four regions 10 px square: a branch, a trunk, a not-branch and a second branch (for the cut candidates)
REAL_ANNOTATIONS = {
    "regions": [
        {"label": "branch", "kind": "branch", "polygon": square(0, 0, 10, 10)},
        {"label": "branch", "kind": "trunk", "polygon": square(20, 0, 30, 10)},
        {"label": "not_branch", "kind": "foliage", "polygon": square(0, 20, 10, 30)},
        {"label": "branch", "kind": "branch", "polygon": square(20, 20, 30, 30)},
    ],
    "cut_candidates": [{"xy": [5, 5], "region": 0}, {"xy": [6, 6], "region": 0}, {"xy": [25, 25], "region": 3}],
}


def test_polygon_at_inside_outside_on_the_edge_and_in_a_notch() -> None:
    """The region whose polygon holds the point (its edge included, as `region_pixels`' fill); None outside all."""
    ell = [[0, 0], [10, 0], [10, 4], [4, 4], [4, 10], [0, 10]]  # an L: its notch is outside
    annotations = {
        "regions": [
            {"label": "branch", "kind": "branch", "polygon": ell},
            {"label": "not_branch", "kind": "ground", "polygon": square(20, 0, 30, 10)},
        ]
    }
    assert segmenter_benchmark.polygon_at(annotations, (2.0, 7.0)) == 0
    assert segmenter_benchmark.polygon_at(annotations, (7.0, 2.0)) == 0
    assert segmenter_benchmark.polygon_at(annotations, (7.0, 7.0)) is None  # the notch
    assert segmenter_benchmark.polygon_at(annotations, (25.5, 9.5)) == 1
    assert segmenter_benchmark.polygon_at(annotations, (20.0, 5.0)) == 1  # on the edge
    assert segmenter_benchmark.polygon_at(annotations, (30.4, 5.0)) is None  # 0.4 px beyond it
    assert segmenter_benchmark.polygon_at(annotations, (15.0, 5.0)) is None


def test_polygon_at_overlapping_regions_gives_the_first_listed() -> None:
    """The annotations promise no overlap; where two regions do overlap, the first listed one holds the point."""
    annotations = {
        "regions": [
            {"label": "not_branch", "kind": "foliage", "polygon": square(0, 0, 10, 10)},
            {"label": "branch", "kind": "branch", "polygon": square(5, 5, 15, 15)},
        ]
    }
    assert segmenter_benchmark.polygon_at(annotations, (7.0, 7.0)) == 0
    assert segmenter_benchmark.polygon_hits(annotations, (7.0, 7.0)) == "not_branch"
    assert segmenter_benchmark.polygon_at(annotations, (12.0, 12.0)) == 1


def test_polygon_hits_names_the_label() -> None:
    """'branch' on a branch polygon (a trunk one too), 'not_branch' on a not-branch one, else 'unlabelled'."""
    assert segmenter_benchmark.polygon_hits(REAL_ANNOTATIONS, (5.0, 5.0)) == "branch"
    assert segmenter_benchmark.polygon_hits(REAL_ANNOTATIONS, (25.0, 5.0)) == "branch"
    assert segmenter_benchmark.polygon_hits(REAL_ANNOTATIONS, (5.0, 25.0)) == "not_branch"
    assert segmenter_benchmark.polygon_hits(REAL_ANNOTATIONS, (50.0, 50.0)) == "unlabelled"


def test_real_pair_scores_counts_each_kind_of_hit() -> None:
    """Six cut points: 3 on branch polygons (1 of them a trunk), 2 on not-branch, 1 on none; at ≥ 0.8 four."""
    branches = [
        branch(1, (0.0, 0.0, 1.0), pixel=(5.0, 5.0), confidence=0.9),  # branch, a candidate's region
        branch(2, (0.0, 0.0, 1.0), pixel=(25.0, 5.0), confidence=0.8),  # trunk, exactly at the threshold
        branch(3, (0.0, 0.0, 1.0), pixel=(5.0, 25.0), confidence=0.95),  # not-branch
        branch(4, (0.0, 0.0, 1.0), pixel=(50.0, 50.0), confidence=0.99),  # unlabelled
        branch(5, (0.0, 0.0, 1.0), pixel=(2.0, 2.0), confidence=0.3),  # branch, same region as the first
        branch(6, (0.0, 0.0, 1.0), pixel=(8.0, 25.0), confidence=0.5),  # not-branch
    ]
    assert segmenter_benchmark.real_pair_scores(REAL_ANNOTATIONS, branches, 0.8) == {
        "cut_points": 6,
        "on_branch": 3,
        "on_trunk": 1,
        "on_not_branch": 2,
        "unlabelled": 1,
        "precision": 0.6,
        "candidate_branches": 2,  # regions 0 and 3 (region 0 holds two candidates)
        "candidate_branches_reached": 1,  # only region 0 got a cut point
        "acted_on": {"branch": 2, "not_branch": 1, "unlabelled": 1},
    }


def test_real_pair_scores_without_labelled_cut_points_or_candidates() -> None:
    """No cut point in any polygon: precision None (not 0); no `cut_candidates` key: none to reach."""
    annotations = {"regions": REAL_ANNOTATIONS["regions"]}
    branches = [branch(1, (0.0, 0.0, 1.0), pixel=(15.0, 15.0), confidence=0.9)]
    assert segmenter_benchmark.real_pair_scores(annotations, branches, 0.95) == {
        "cut_points": 1,
        "on_branch": 0,
        "on_trunk": 0,
        "on_not_branch": 0,
        "unlabelled": 1,
        "precision": None,
        "candidate_branches": 0,
        "candidate_branches_reached": 0,
        "acted_on": {"branch": 0, "not_branch": 0, "unlabelled": 0},
    }


#: a 10×12 frame's regions; with their edges (pixel centres on them count) they hold 8, 18, 36 and 4 pixels
PIXEL_ANNOTATIONS = {
    "regions": [
        {"label": "branch", "kind": "branch", "polygon": square(1, 1, 4, 2)},  # columns 1–4, rows 1–2
        {"label": "branch", "kind": "trunk", "polygon": square(7, 0, 9, 5)},  # columns 7–9, rows 0–5
        {"label": "not_branch", "kind": "ground", "polygon": square(0, 7, 11, 9)},  # columns 0–11, rows 7–9
        {"label": "branch", "kind": "branch", "polygon": square(1, 4, 2, 5)},  # columns 1–2, rows 4–5
    ]
}
TRUNK_ID = 9


def pixel_labels() -> np.ndarray:
    """Instances over `PIXEL_ANNOTATIONS`: region 0 half branch (id 3) and one trunk pixel, region 1 half trunk and
    one branch pixel (id 5), region 2 nothing, region 3 all branch (id 3)."""
    labels = np.zeros((10, 12), np.int32)
    labels[1:3, 1:3] = 3
    labels[1, 4] = TRUNK_ID
    labels[0:3, 7:10] = TRUNK_ID
    labels[5, 9] = 5
    labels[4:6, 1:3] = 3
    return labels


def pixel_disparity() -> np.ndarray:
    """Region 0: 2, 4, …, 12 and two invalid pixels (median 7); region 1: its row + 1 (median 3.5); else none."""
    disparity = np.zeros((10, 12), np.float32)
    disparity[1, 1:5] = [0, 2, 4, 6]
    disparity[2, 1:5] = [8, 10, 12, -1]
    disparity[0:6, 7:10] = np.arange(1, 7, dtype=np.float32)[:, None]
    return disparity


def network_classes() -> np.ndarray:
    """Arg-max classes: region 0 all branch, region 1 12 px trunk and 3 px branch, one branch pixel in region 2."""
    classes = np.full((10, 12), CLASSES.index("background"), np.int64)
    classes[1:3, 1:5] = CLASSES.index("branch")
    classes[0:4, 7:10] = CLASSES.index("trunk")
    classes[5, 7:10] = CLASSES.index("branch")
    classes[8, 0] = CLASSES.index("branch")
    return classes


def test_region_pixels_with_network_classes() -> None:
    """Each region's pixels, median valid disparity and shares in the final masks and the network's classes."""
    masks = BranchMasks(pixel_labels(), trunk_id=TRUNK_ID)
    rows = segmenter_benchmark.region_pixels(PIXEL_ANNOTATIONS, masks, pixel_disparity(), network_classes())
    assert rows == [
        {
            "region": 0,
            "label": "branch",
            "kind": "branch",
            "pixels": 8,
            "median_disparity_px": 7.0,
            "as_branch": 4 / 8,
            "as_trunk": 1 / 8,
            "network_branch": 8 / 8,
            "network_trunk": 0.0,
        },
        {
            "region": 1,
            "label": "branch",
            "kind": "trunk",
            "pixels": 18,
            "median_disparity_px": 3.5,
            "as_branch": 1 / 18,
            "as_trunk": 9 / 18,
            "network_branch": 3 / 18,
            "network_trunk": 12 / 18,
        },
        {
            "region": 2,
            "label": "not_branch",
            "kind": "ground",
            "pixels": 36,
            "median_disparity_px": None,
            "as_branch": 0.0,
            "as_trunk": 0.0,
            "network_branch": 1 / 36,
            "network_trunk": 0.0,
        },
        {
            "region": 3,
            "label": "branch",
            "kind": "branch",
            "pixels": 4,
            "median_disparity_px": None,
            "as_branch": 4 / 4,
            "as_trunk": 0.0,
            "network_branch": 0.0,
            "network_trunk": 0.0,
        },
    ]


def test_region_pixels_without_network_classes_or_trunk() -> None:
    """No network classes: no network shares; no trunk id: every instance pixel (id 9 too) is a branch's."""
    masks = BranchMasks(pixel_labels())
    rows = segmenter_benchmark.region_pixels(PIXEL_ANNOTATIONS, masks, pixel_disparity(), None)
    assert [set(row) for row in rows] == [
        {"region", "label", "kind", "pixels", "median_disparity_px", "as_branch", "as_trunk"}
    ] * 4
    assert [row["as_branch"] for row in rows] == [5 / 8, 10 / 18, 0.0, 4 / 4]
    assert [row["as_trunk"] for row in rows] == [0.0, 0.0, 0.0, 0.0]


def test_region_pixels_ignored_ids_are_neither_branch_nor_trunk() -> None:
    """An instance id in `BranchMasks.ignored_ids` (here region 3's id 3, and region 0's half) counts as nothing."""
    masks = BranchMasks(pixel_labels(), trunk_id=TRUNK_ID, ignored_ids=(3,))
    rows = segmenter_benchmark.region_pixels(PIXEL_ANNOTATIONS, masks, pixel_disparity(), None)
    assert [row["as_branch"] for row in rows] == [0.0, 1 / 18, 0.0, 0.0]
    assert [row["as_trunk"] for row in rows] == [1 / 8, 9 / 18, 0.0, 0.0]


def test_shares_by_kind_weights_each_region_by_its_pixels() -> None:
    """The two 'branch' regions (8 and 4 px) pool into one row; shares rounded to 1e-3."""
    masks = BranchMasks(pixel_labels(), trunk_id=TRUNK_ID)
    rows = segmenter_benchmark.region_pixels(PIXEL_ANNOTATIONS, masks, pixel_disparity(), network_classes())
    assert segmenter_benchmark.shares_by_kind(rows) == {
        # (4 + 4) / 12, 1 / 12, 8 / 12, 0
        "branch": {"pixels": 12, "as_branch": 0.667, "as_trunk": 0.083, "network_branch": 0.667, "network_trunk": 0.0},
        # 1 / 18, 9 / 18, 3 / 18, 12 / 18
        "trunk": {"pixels": 18, "as_branch": 0.056, "as_trunk": 0.5, "network_branch": 0.167, "network_trunk": 0.667},
        # 0, 0, 1 / 36, 0
        "ground": {"pixels": 36, "as_branch": 0.0, "as_trunk": 0.0, "network_branch": 0.028, "network_trunk": 0.0},
    }


def test_shares_by_kind_without_network_classes() -> None:
    """Rows without network shares pool into rows without them."""
    rows = segmenter_benchmark.region_pixels(PIXEL_ANNOTATIONS, BranchMasks(pixel_labels()), pixel_disparity(), None)
    assert segmenter_benchmark.shares_by_kind(rows) == {
        "branch": {"pixels": 12, "as_branch": 0.75, "as_trunk": 0.0},  # (5 + 4) / 12
        "trunk": {"pixels": 18, "as_branch": 0.556, "as_trunk": 0.0},  # 10 / 18
        "ground": {"pixels": 36, "as_branch": 0.0, "as_trunk": 0.0},
    }


def stems() -> np.ndarray:
    """Four horizontal stems 60 px long, 2, 4, 6 and 10 px wide (ids 1–4), with background all round."""
    mask = np.zeros((34, 80), np.int32)
    for branch_id, (top, width) in enumerate([(2, 2), (6, 4), (12, 6), (20, 10)], start=1):
        mask[top : top + width, 10:70] = branch_id
    return mask


def test_width_class_of_stems_of_known_width() -> None:
    """A stem w px wide (w even) measures 2 × (w / 2) × 0.955 px (OpenCV's 3×3 L2 distance steps 0.955 a pixel):
    1.91, 3.82, 5.73 and 9.55 px — one stem in each class of `WIDTH_BINS_PX`."""
    mask = stems()
    assert [segmenter_benchmark.width_class(mask, branch_id) for branch_id in (1, 2, 3, 4)] == [
        "0–3 px",
        "3–5 px",
        "5–8 px",
        "≥8 px",
    ]


def test_width_class_scales_to_640_wide_and_hides_absent_branches() -> None:
    """`px_scale` multiplies the width (3.82 × 2 = 7.64, 9.55 × 0.5 = 4.78 px); a branch with no pixel is hidden."""
    mask = stems()
    assert segmenter_benchmark.width_class(mask, 1, px_scale=2.0) == "3–5 px"
    assert segmenter_benchmark.width_class(mask, 2, px_scale=2.0) == "5–8 px"
    assert segmenter_benchmark.width_class(mask, 4, px_scale=0.5) == "3–5 px"
    assert segmenter_benchmark.width_class(mask, 7) == "hidden"


#: (confidence, within 5 cm): bins' lower edges included, 1.0 in the top bin
PAIRS = [
    (0.1, False),
    (0.2, True),
    (0.35, False),
    (0.8, False),
    (0.85, True),
    (0.85, True),
    (0.88, False),
    (0.9, True),
    (1.0, True),
]


def test_reliability_counts_share_and_mean_per_bin() -> None:
    """Per bin of `BINS`: cut points, share correct and mean confidence; NaN for an empty bin."""
    rows = segmenter_benchmark.reliability(PAIRS)
    assert [(label, count) for label, count, _, _ in rows] == [
        ("0.0–0.2", 1),
        ("0.2–0.4", 2),
        ("0.4–0.6", 0),
        ("0.6–0.8", 0),
        ("0.8–0.9", 4),
        ("0.9–1.0", 2),
    ]
    nan = math.nan
    assert [share for _, _, share, _ in rows] == pytest.approx([0.0, 0.5, nan, nan, 0.5, 1.0], nan_ok=True)
    assert [mean for _, _, _, mean in rows] == pytest.approx([0.1, 0.275, nan, nan, 0.845, 0.95], nan_ok=True)


def test_reliability_of_no_cut_points() -> None:
    """No pairs: every bin empty."""
    assert [count for _, count, _, _ in segmenter_benchmark.reliability([])] == [0] * 6


def test_mean_confidence_above() -> None:
    """The mean of the confidences at or above the threshold; NaN when there are none."""
    assert segmenter_benchmark.mean_confidence_above(PAIRS, 0.8) == pytest.approx(5.28 / 6)
    assert segmenter_benchmark.mean_confidence_above(PAIRS, 0.9) == pytest.approx(0.95)
    assert math.isnan(segmenter_benchmark.mean_confidence_above(PAIRS, 1.01))
    assert math.isnan(segmenter_benchmark.mean_confidence_above([], 0.0))


DEFAULT_BAND = LearnedSegmenterConfig().trunk_band_px
DEPTH = segmenter_benchmark.DEPTH_PIECES_RATIO


@pytest.mark.parametrize(
    ("name", "expected"),
    [
        ("learned", LearnedSegmenterConfig()),
        ("learned/0", LearnedSegmenterConfig(trunk_band_px=0)),
        ("learned@1280", LearnedSegmenterConfig(network_width=1280, trunk_band_px=0)),
        ("learned@1280/40", LearnedSegmenterConfig(network_width=1280, trunk_band_px=40)),
        ("learned-int8", LearnedSegmenterConfig(precision="int8", trunk_band_px=DEFAULT_BAND)),
        ("learned-int8/0", LearnedSegmenterConfig(precision="int8", trunk_band_px=0)),
        ("learned/0+depth", LearnedSegmenterConfig(trunk_band_px=0, piece_disparity_ratio=DEPTH)),
        ("learned+depth~normal", LearnedSegmenterConfig(piece_disparity_ratio=DEPTH, light_calibration=False)),
        ("learned~normal", LearnedSegmenterConfig(light_calibration=False)),
    ],
)
def test_benchmark_segmenter_name_grammar(name: str, expected: LearnedSegmenterConfig) -> None:
    """'-int8', '@width', '/band', '+depth' and '~normal' set the learned segmenter's settings, the rest default."""
    built = segmenter_benchmark.benchmark_segmenter(name)
    assert isinstance(built, LearnedSegmenter)
    assert built.config == expected
    assert built.model_path == SHIPPED_MODELS[expected.precision]


@pytest.mark.parametrize("name", ["learned+depth/0", "learned~normal+depth", "learned/0+depthX", "learned@wide"])
def test_benchmark_segmenter_refuses_a_misplaced_part(name: str) -> None:
    """A learned variant out of the grammar's order is refused, not built with the misplaced part dropped."""
    with pytest.raises(ValueError, match="expected learned"):
        segmenter_benchmark.benchmark_segmenter(name)


def test_benchmark_segmenter_other_names() -> None:
    """A name outside the learned grammar is `make_segmenter`'s."""
    assert type(segmenter_benchmark.benchmark_segmenter("structure")) is StructureSegmenter


CPUINFO = """processor\t: 0
model name\t: AMD EPYC 9B14
flags\t\t: fpu sse2 avx avx2 avx512f avx512bw

processor\t: 1
model name\t: Another CPU
flags\t\t: fpu sse2
"""


@pytest.fixture
def fixed_machine(monkeypatch: pytest.MonkeyPatch) -> None:
    """Three usable cores, a load average of 0.456, and no model name from `platform`."""
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2})
    monkeypatch.setattr(os, "getloadavg", lambda: (0.456, 1.0, 1.0))
    monkeypatch.setattr(platform, "processor", lambda: "")


@pytest.mark.usefixtures("fixed_machine")
def test_cpu_description_reads_the_first_processor(tmp_path: Path) -> None:
    """The first "model name" and "flags" lines count: AVX2 and AVX-512 (avx512f) present."""
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text(CPUINFO)
    assert machine.cpu_description(cpuinfo) == {
        "model": "AMD EPYC 9B14",
        "cores": 3,
        "avx2": True,
        "avx512": True,
        "load_average_1min": 0.46,
    }
    assert machine.cpu_name(cpuinfo) == "AMD EPYC 9B14; AVX2 yes, AVX-512 yes; 3 cores"


@pytest.mark.usefixtures("fixed_machine")
def test_cpu_name_without_avx512(tmp_path: Path) -> None:
    """avx512bw without avx512f is no AVX-512."""
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("model name\t: Intel Xeon\nflags\t\t: fpu avx avx2 avx512bw\n")
    assert machine.cpu_description(cpuinfo)["avx512"] is False
    assert machine.cpu_name(cpuinfo) == "Intel Xeon; AVX2 yes, AVX-512 no; 3 cores"


@pytest.mark.usefixtures("fixed_machine")
def test_cpu_name_without_cpuinfo(tmp_path: Path) -> None:
    """No file: the extensions are unknown (None), not absent, and the model falls back to 'unknown CPU'."""
    missing = tmp_path / "absent"
    description = machine.cpu_description(missing)
    assert (description["model"], description["avx2"], description["avx512"]) == ("unknown CPU", None, None)
    assert machine.cpu_name(missing) == "unknown CPU; AVX2 unknown, AVX-512 unknown; 3 cores"
