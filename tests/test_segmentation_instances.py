"""The learned segmenter's instance stage: which trunk regions are the tree's, and straight pieces."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from branchrange.core.geometry import StereoGeometry
from branchrange.core.segmentation.learned import LearnedSegmenter, LearnedSegmenterConfig, trunk_attachment
from branchrange.core.segmentation.pieces import straight_pieces_of
from branchrange.core.segmentation.trunk import in_front_of_trunk, tree_trunk

GEOMETRY = StereoGeometry.centred(400.0, 0.06, 200, 120)


def test_a_trunk_cut_in_two_by_a_branch_in_front_stays_one_trunk_and_a_far_tree_does_not_join():
    trunk = np.zeros((120, 200), dtype=bool)
    trunk[:, 40:70] = True  # the tree being pruned, 2 m away ...
    trunk[50:58, :] = False  # ... its silhouette cut by a branch in front of it
    trunk[:, 150:160] = True  # another tree's trunk, 6 m away
    depth = np.full(trunk.shape, 2.0)
    depth[:, 150:160] = 6.0
    depth[60:, 40:70] = 2.1  # the lower part leans slightly away: within the tolerance
    branches = np.zeros_like(trunk)
    kept = tree_trunk(trunk, branches, depth, GEOMETRY, 0.1)  # no branches: the largest region and its parts
    assert kept[:50, 40:70].all() and kept[58:, 40:70].all()
    assert not kept[:, 150:160].any()
    speck = np.zeros_like(trunk)
    speck[5:7, 100:102] = True  # a few pixels at the trunk's depth are not a trunk part
    assert not tree_trunk(trunk | speck, branches, depth, GEOMETRY, 0.1)[5:7, 100:102].any()
    assert not tree_trunk(np.zeros_like(trunk), branches, depth, GEOMETRY, 0.1).any()


def test_a_post_beside_the_trunk_at_its_depth_is_not_a_trunk_part_but_the_trunk_below_a_branch_is():
    trunk = np.zeros((120, 200), dtype=bool)
    trunk[:, 40:56] = True  # the tree, 2 m away ...
    trunk[50:58, 40:56] = False  # ... cut by a branch in front: its upper part continues the line
    trunk[:, 100:110] = True  # an orchard post at the same depth, 44 px beside it
    depth = np.full(trunk.shape, 2.0)
    branches = np.zeros_like(trunk)
    branches[30:34, 56:90] = True  # a branch growing from the upper part: that part is the tree's
    kept = tree_trunk(trunk, branches, depth, GEOMETRY, 0.1)
    assert kept[:50, 40:56].all() and kept[58:, 40:56].all()
    assert not kept[:, 100:110].any()
    leaning = np.zeros_like(trunk)  # a leaning trunk cut in two: its parts are beside each other in columns
    cv2.line(leaning.view(np.uint8), (20, 119), (140, 0), 1, thickness=12)
    leaning[55:63, :] = False
    kept = tree_trunk(leaning, np.zeros_like(trunk), depth, GEOMETRY, 0.1)
    assert kept[leaning].all()


def test_a_trunk_seen_from_below_stays_one_trunk_though_its_parts_lie_at_other_depths():
    """Looking up a trunk: its top is farther than its foot (inverse depth affine along it, as on any plane),
    and leaves in front cut it in three. Its parts at 1.3 and 1.75 m are the tree's, though the foot is at
    1.0 m; the same pixels at a depth that does not continue the foot's surface are not."""
    trunk = np.zeros((120, 200), dtype=bool)
    trunk[:, 60:90] = True
    trunk[38:44, :] = False
    trunk[78:84, :] = False
    rows = np.arange(120, dtype=np.float64)[:, None]
    depth = np.broadcast_to(1.0 / (1.0 - 0.005 * (119 - rows)), trunk.shape).copy()  # 1.0 m below, 2.5 m on top
    assert depth[100, 70] == pytest.approx(1.1, abs=0.01) and depth[60, 70] == pytest.approx(1.42, abs=0.02)
    foot = np.zeros_like(trunk)
    foot[95:99, 90:140] = True  # a branch grows from the foot: it is the anchor
    kept = tree_trunk(trunk, foot, depth, GEOMETRY, 0.1)
    assert kept[trunk].all()
    depth[:38] = 1.1  # the top part at the foot's own depth: not where the trunk's surface runs
    kept = tree_trunk(trunk, foot, depth, GEOMETRY, 0.1)
    assert kept[84:, 60:90].all() and kept[44:78, 60:90].all() and not kept[:38].any()


def test_a_region_where_the_trunks_surface_runs_off_to_infinity_does_not_join():
    """The anchor's depth rises steeply down it (1 → 8 m over 50 rows: a bad fit, as SGBM's on a textureless
    trunk can give), so its surface carried to the region below lies beyond infinity: that region says
    nothing about the trunk, whatever its depth, and stays out."""
    trunk = np.zeros((120, 200), dtype=bool)
    trunk[:50, 40:60] = True
    trunk[100:, 40:60] = True  # on the anchor's line, 2 m away
    rows = np.arange(120, dtype=np.float64)[:, None]
    inverse = np.broadcast_to(1.0 - 0.0175 * rows, trunk.shape)
    depth = np.where(inverse > 0.1, 1.0 / np.maximum(inverse, 0.1), 2.0)
    assert depth[0, 50] == 1.0 and depth[49, 50] == pytest.approx(7.0, rel=0.05) and depth[110, 50] == 2.0
    kept = tree_trunk(trunk, np.zeros_like(trunk), depth, GEOMETRY, 0.1)
    assert kept[:50, 40:60].all() and not kept[100:, 40:60].any()
    depth[100:] = np.inf  # nor without any depth
    assert not tree_trunk(trunk, np.zeros_like(trunk), depth, GEOMETRY, 0.1)[100:, 40:60].any()


def test_the_tree_is_the_trunk_region_that_branches_grow_from_not_the_largest():
    trunk = np.zeros((120, 200), dtype=bool)
    trunk[:, 10:60] = True  # a wide post, 2 m away, nothing growing from it
    trunk[:, 140:150] = True  # the tree's trunk, 1.5 m away
    depth = np.full(trunk.shape, 1.5)
    depth[:, 10:60] = 2.0
    branches = np.zeros_like(trunk)
    branches[40:44, 150:190] = True  # a branch leaving the trunk at its depth
    kept = tree_trunk(trunk, branches, depth, GEOMETRY, 0.1)
    assert kept[:, 140:150].all() and not kept[:, 10:60].any()
    depth[40:44, 150:190] = 3.0  # the same pixels far behind the trunk: they do not grow from it
    kept = tree_trunk(trunk, branches, depth, GEOMETRY, 0.1)
    assert kept[:, 10:60].all() and not kept[:, 140:150].any()


def test_a_stem_seen_through_leaves_is_one_piece_when_its_fragments_are_bridged():
    """A 3 px stem behind leaves: eight fragments of 9 px, 4 px apart, each under the 12 px a piece needs.
    8-connected they are nothing; bridged (gaps up to 6 px) they are one piece along the stem, and a second
    stem 14 px beside it stays a piece of its own."""
    mask = np.zeros((60, 160), dtype=bool)
    for start in range(10, 110, 13):
        mask[20:23, start : start + 3] = True  # 3 × 3 px visible, then a leaf in front for 10 px ... too far
    assert not list(straight_pieces_of(mask, 12, np.random.default_rng(0)))
    assert not list(straight_pieces_of(mask, 12, np.random.default_rng(0), bridge_px=3))  # 10 px gaps: apart
    mask[:] = False
    for start in range(10, 110, 7):
        mask[20:23, start : start + 3] = True  # leaves 4 px wide in front: the fragments 4 px apart
    mask[34:37, 10:110] = True  # another stem, 11 px below
    assert [len(u) for u, _ in straight_pieces_of(mask, 12, np.random.default_rng(0))] == [300]
    pieces = sorted(
        (sorted(set(v.tolist())), len(u))
        for u, v in straight_pieces_of(mask, 12, np.random.default_rng(0), bridge_px=3)
    )
    assert pieces == [([20, 21, 22], int(mask[20:23].sum())), ([34, 35, 36], 300)]


def test_fragments_are_bridged_only_where_the_network_sees_the_stems_enlarged():
    def bridge(**settings: int) -> int:
        return LearnedSegmenter(LearnedSegmenterConfig(**settings)).bridge_px(640)

    assert bridge() == 3  # the default looks twice
    assert bridge(trunk_band_px=0) == 0  # one look at the frame's own width: the onboard files
    assert bridge(trunk_band_px=0, network_width=1280) == 3 and bridge(trunk_band_px=0, network_width=640) == 0
    assert bridge(bridge_px=5) == 5 and bridge(bridge_px=0) == 0


def test_two_thin_stems_of_a_fork_beside_a_thick_limb_become_two_pieces():
    # one region: a limb 17 px thick, and a fork of two 3 px stems leaving it 6° apart. A band as wide as
    # the limb would take both stems on one line (one axis between them: a cut point on neither).
    limb, stems = np.zeros((170, 240), np.uint8), [np.zeros((170, 240), np.uint8) for _ in range(2)]
    cv2.line(limb, (10, 40), (230, 40), 1, thickness=17)
    cv2.line(stems[0], (40, 48), (220, 120), 1, thickness=3)
    cv2.line(stems[1], (40, 48), (220, 145), 1, thickness=3)
    mask = (limb | stems[0] | stems[1]) > 0
    owners = np.zeros(mask.shape, dtype=int)
    for k, (u, v) in enumerate(straight_pieces_of(mask, 12, np.random.default_rng(0)), 1):
        owners[v, u] = k
    far = np.zeros(mask.shape, dtype=bool)
    far[:, 120:] = True  # past the fork, where the stems are 12-30 px apart
    owner = [np.bincount(owners[(s > 0) & far & (limb == 0)]).argmax() for s in stems]
    assert 0 not in owner and owner[0] != owner[1]
    for s, k in zip(stems, owner):
        assert np.mean(owners[(s > 0) & far] == k) > 0.8


def _crossing_stem_before_a_limb() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(mask, disparity px, limb pixels, stem pixels) `H×W`: a limb 11 px thick at 20 px disparity and a
    3 px stem leaving the same trunk edge (column 10) 4° off it, nearer (24 px) and in front where they
    overlap — one region in the image, two lines in depth."""
    limb, stem = np.zeros((120, 260), np.uint8), np.zeros((120, 260), np.uint8)
    cv2.line(limb, (10, 60), (250, 60), 1, thickness=11)
    cv2.line(stem, (10, 62), (250, 45), 1, thickness=3)
    disparity = np.zeros(limb.shape, np.float32)
    disparity[limb > 0] = 20.0
    disparity[stem > 0] = 24.0  # drawn last: in front
    return (limb | stem) > 0, disparity, (limb > 0) & (stem == 0), stem > 0


def _owners(mask: np.ndarray, disparity: np.ndarray | None = None, disparity_ratio: float = 0.0) -> np.ndarray:
    """`H×W` piece number (1..) of each pixel of `mask` (0 outside every piece)."""
    owners = np.zeros(mask.shape, dtype=int)
    pieces = straight_pieces_of(
        mask, 12, np.random.default_rng(0), disparity=disparity, disparity_ratio=disparity_ratio
    )
    for k, (u, v) in enumerate(pieces, 1):
        owners[v, u] = k
    return owners


def test_a_stem_crossing_a_limb_at_another_depth_keeps_its_base_when_pieces_follow_the_disparity():
    mask, disparity, limb, stem = _crossing_stem_before_a_limb()
    base = stem.copy()
    base[:, 60:] = False  # the stem's first 50 px from the trunk, inside the limb's band
    image_only = _owners(mask)
    # the image alone: the limb's line takes the stem's base, so no piece holds the stem from the trunk
    assert np.mean(image_only[base] == np.bincount(image_only[limb]).argmax()) > 0.5
    followed = _owners(mask, disparity=disparity, disparity_ratio=0.04)
    stem_piece = np.bincount(followed[stem]).argmax()
    assert stem_piece > 0 and np.mean(followed[stem] == stem_piece) > 0.9
    assert np.mean(followed[base] == stem_piece) > 0.9  # from the trunk on
    assert np.mean(followed[limb] == stem_piece) < 0.02  # and the limb's piece is the limb
    # unknown disparity (0, NaN or inf) follows any line: the image alone decides, as without a disparity
    for missing in (0.0, np.nan, np.inf):
        unknown = np.where(stem, missing, disparity).astype(np.float32)
        assert np.array_equal(_owners(mask, disparity=unknown, disparity_ratio=0.04), image_only)
    assert np.array_equal(_owners(mask, disparity=disparity, disparity_ratio=0.0), image_only)


class _ClassMapSegmenter(LearnedSegmenter):
    """The learned segmenter's instance stage over a given class map (logits ±10), not the network's (both looks,
    and no out-of-distribution reading: `looked` is where `segment` gets them)."""

    classes: np.ndarray

    def looked(self, left: np.ndarray, disparity: np.ndarray) -> tuple[np.ndarray, None]:
        return np.stack([np.where(self.classes == k, 10.0, -10.0) for k in range(3)]).astype(np.float32), None


def test_a_piece_that_stops_short_of_the_trunk_scores_lower_than_one_that_touches_it():
    assert trunk_attachment(np.array([0.0, 0.01, 0.03]), 0.02) == pytest.approx([1.0, 1.0, np.exp(-1.0)])
    assert (trunk_attachment(np.array([0.05]), 0.0) == 1).all()
    classes = np.zeros((120, 200), np.uint8)
    classes[:, 90:110] = 1  # trunk
    classes[30:34, 110:190] = 2  # a branch leaving it
    classes[80:84, 118:190] = 2  # a piece stopping 9 px (4.5 cm at 2 m, f 400 px) short of it
    segmenter = _ClassMapSegmenter(LearnedSegmenterConfig())
    segmenter.classes = classes
    disparity = np.full(classes.shape, 400.0 * 0.06 / 2.0, np.float32)  # everything 2 m away
    masks = segmenter.segment(np.zeros((120, 200, 3), np.uint8), disparity, GEOMETRY)
    touching, short = (int(np.bincount(masks.labels[rows, 150]).argmax()) for rows in (slice(30, 34), slice(80, 84)))
    assert masks.scores[touching] == pytest.approx(1.0, abs=1e-6)
    assert masks.scores[short] == pytest.approx(np.exp(-(0.045 - 0.01) / 0.02), rel=0.15)
    plain = _ClassMapSegmenter(LearnedSegmenterConfig(attachment_scale_m=0))
    plain.classes = classes
    assert plain.segment(np.zeros((120, 200, 3), np.uint8), disparity, GEOMETRY).scores[short] == pytest.approx(1.0)


def _bark_with_stems_before_it() -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """(trunk-class mask, disparity px, {name: boolean mask}) of a trunk 0.2 m in radius 2 m away (80 px wide at
    f 400 px, its bulge 0.2 m nearer in the middle) with SGBM-like noise, a vertical and a horizontal 3 px stem
    and a round leaf 1.6 m away in front of it — all called trunk, as the network calls a stem on bark."""
    f, b, radius = GEOMETRY.focal_px, GEOMETRY.baseline_m, 0.2
    columns = np.arange(200) - 100.0
    across = np.clip(columns * 2.0 / f, -radius, radius)
    bark_depth = 2.0 - np.sqrt(radius**2 - across**2)  # m, nearest at the trunk's middle
    disparity = np.broadcast_to(f * b / bark_depth, (120, 200)).astype(np.float32).copy()
    disparity += np.random.default_rng(3).normal(0.0, 0.1, disparity.shape).astype(np.float32)
    trunk = np.zeros((120, 200), dtype=bool)
    trunk[:, 62:139] = True
    shapes = {name: np.zeros_like(trunk) for name in ("vertical", "horizontal", "leaf")}
    shapes["vertical"][10:110, 90:93] = True
    shapes["horizontal"][70:73, 64:137] = True
    cv2.circle(shapes["leaf"].view(np.uint8), (120, 30), 5, 1, thickness=-1)
    for shape in shapes.values():
        disparity[shape] = f * b / 1.6
    return trunk, disparity, shapes


def test_a_stem_before_the_bark_is_told_from_it_by_depth_and_the_trunks_own_bulge_is_not():
    trunk, disparity, shapes = _bark_with_stems_before_it()
    front = in_front_of_trunk(trunk, disparity, 0.03, 12)
    for name in ("vertical", "horizontal"):
        inner = shapes[name].copy()
        inner[:, :66] = inner[:, 135:] = False  # at the silhouette's edge one side of bark is missing
        assert np.mean(front[inner]) > 0.9, name
    assert not front[shapes["leaf"]].any()  # round: a leaf, not a stem
    bark = trunk & ~shapes["vertical"] & ~shapes["horizontal"] & ~shapes["leaf"]
    assert not front[bark].any()  # 10 % nearer in the middle than at the edges, but smoothly
    assert not in_front_of_trunk(trunk, disparity, 0.5, 12).any()  # the stems are 25 % nearer, not 50
    assert not in_front_of_trunk(trunk, np.zeros_like(disparity), 0.03, 12).any()  # no depth, no evidence


def test_the_learned_instance_stage_makes_a_stem_called_trunk_a_branch_when_it_is_before_the_bark():
    trunk, disparity, shapes = _bark_with_stems_before_it()
    segmenter = _ClassMapSegmenter(LearnedSegmenterConfig())
    segmenter.classes = np.where(trunk, 1, 0).astype(np.uint8)
    masks = segmenter.segment(np.zeros((120, 200, 3), np.uint8), disparity, GEOMETRY)
    stem = masks.labels[20:60, 90:93]
    assert (stem > 0).all() and (stem != masks.trunk_id).all() and len(np.unique(stem)) == 1
    assert np.mean(masks.labels[:, 100:130] == masks.trunk_id) > 0.9  # the bark stays the trunk
    off = _ClassMapSegmenter(LearnedSegmenterConfig(front_of_trunk_ratio=0))
    off.classes = segmenter.classes
    assert (
        off.segment(np.zeros((120, 200, 3), np.uint8), disparity, GEOMETRY).labels[20:60, 90:93] == masks.trunk_id
    ).all()
