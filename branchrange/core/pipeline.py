"""The per-frame pipeline: stereo pair (+ optional mask) → cut points, a `FrameResult` (`branchrange/v1`).

Stages, each timed in `timing_ms`: rectify (when a raw calibration is given) → stereo backend →
masks (given, or the segmenter) → cut points → tracking (stable ids) → target. One `Pipeline` is
built once per camera and reused for every frame; it holds the backend, the rectification maps
and the tracker's state. `process_disparity` runs the stages after stereo on a given disparity
(ground truth in evaluation, a disparity computed elsewhere).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np

from branchrange.core.branch_disparity import refine_branch_disparity
from branchrange.core.branch_propagation import propagate_labels, verify_support
from branchrange.core.cutpoints import (
    DEFAULT_TARGET_POLICY,
    CutPointConfig,
    CutPointResult,
    DroppedBranch,
    TargetPolicy,
    TrunkModel,
    estimate_cut_points,
    select_target,
)
from branchrange.core.frame_result import (
    Branch,
    CameraInfo,
    DroppedInstance,
    Frame,
    FrameResult,
    LightInfo,
    MasksInfo,
    PairCheckInfo,
    RoiInfo,
    RoiRegion,
    SegmenterOod,
    StereoInfo,
)
from branchrange.core.geometry import StereoGeometry, offset_disparity, valid_disparity
from branchrange.core.keyframe_worker import Keyframe, KeyframeWorker, global_shift
from branchrange.core.keyframes import CarriedFrame, KeyframeSchedule, Origin, grey_of
from branchrange.core.masks import (
    BranchMasks,
    MaskConfig,
    MaskKind,
    check_instance_count,
    masks_from_array,
    read_mask,
    validate_masks,
)
from branchrange.core.pair_check import PairCheck, check_rectification
from branchrange.core.region_budget import branch_scales
from branchrange.core.roi import CoarseToFine, CoarseToFineResult, CoarseTrunk, Region, RoiConfig, branch_gates
from branchrange.core.segmentation.choose import SegmenterConfig
from branchrange.core.segmentation.ood import OodWarnings
from branchrange.core.segmentation.segmenter import Segmenter
from branchrange.core.settings_check import Checks, ConfigError, Limit, Settings, one_of
from branchrange.core.timing import lap_ms
from branchrange.core.tracking import BranchTracker, TrackerConfig
from stereo.backends import (
    BACKEND_NAMES,
    MAX_DISP_EXPECTED,
    PRECISIONS,
    WEIGHTED_BACKENDS,
    StereoBackend,
    is_valid_max_disp,
)
from stereo.backends.base import MAX_DISP_LIMIT, MAX_DISP_STEP, validate_image, validate_pair

#: `stereo.mode`: 'full' matches the whole frame at full resolution; 'roi' coarse-to-fine (`branchrange.core.roi`).
STEREO_MODES: tuple[str, ...] = ("full", "roi")
#: The most stereo worker processes `stereo.workers` may ask for (each holds its own pipeline, models included).
MAX_STEREO_WORKERS = 64


@dataclass(frozen=True)
class StereoConfig(Settings):
    """Which stereo backend computes disparity (`stereo.backends.make_backend` arguments), and how.

    `backend`: one of `stereo.backends.BACKEND_NAMES`. `emcstereo` and `onnx` need `weights` (a
    checkpoint; the exported .onnx file): a network without them gives meaningless disparities,
    which the daemon would send to the flight controller as cut points. `max_disp`: the disparity
    search range in px at full resolution (`stereo.backends.check_max_disp`'s rule). `precision`:
    one of `stereo.backends.PRECISIONS` (fp16/bf16 need a CUDA `device` and emcstereo). `device`: the torch
    device a network backend runs on ('cpu', 'cuda', 'cuda:1'). `mode`:
    'roi' matches the frame at low resolution and each branch at full resolution in its box and
    disparity window (`[roi]`, `branchrange.core.roi`) — the real-time onboard default; 'full' matches
    the whole frame. `verify_weights`: check a registered release's weights against its SHA-256 on load.
    `refine_branches`: once the masks are known, match each branch on its own pixels for a sub-pixel
    disparity free of the background's pull (`branchrange.core.branch_disparity`; ~1 ms per branch).
    `workers`: how many processes of the onboard daemon run the stereo stage, each on the next frame
    while the others work, their results published in capture order (`branchrange.onboard.stereo_workers`);
    1 runs it in the daemon's own thread, 0 starts one per CPU core the daemon may use; with keyframes
    (`roi.keyframe_interval_s` > 0) always 1.
    """

    section = "stereo"
    error = ConfigError
    limits = {
        "backend": Limit(enum=BACKEND_NAMES, expected=one_of(BACKEND_NAMES)),
        "max_disp": Limit(minimum=MAX_DISP_STEP, maximum=MAX_DISP_LIMIT, multiple_of=MAX_DISP_STEP),
        "precision": Limit(enum=PRECISIONS, expected=one_of(PRECISIONS)),
        "mode": Limit(
            enum=STEREO_MODES,
            expected="'roi' (coarse pass + full-resolution regions per branch, see [roi]) or 'full' (whole frame)",
        ),
        "workers": Limit(minimum=0, maximum=MAX_STEREO_WORKERS, expected=f"0 (one per core) to {MAX_STEREO_WORKERS}"),
    }

    backend: str = "sgbm"
    weights: str = ""
    max_disp: int = 192
    device: str = "cpu"
    precision: str = "fp32"
    mode: str = "roi"
    verify_weights: bool = True
    refine_branches: bool = True
    workers: int = 1

    def checks(self) -> Checks:
        """The backend, its weights, search range and precision, and the mode."""
        return {
            "weights": (
                self.backend not in WEIGHTED_BACKENDS or bool(self.weights.strip()),
                f"a checkpoint path when stereo.backend = {self.backend!r}",
            ),
            "max_disp": (is_valid_max_disp(self.max_disp), MAX_DISP_EXPECTED),
        }

    def build_backend(self) -> StereoBackend:
        """The `stereo.backends` backend these settings name (`make_backend`); weights whose file name is a
        registered release are checked against its SHA-256 unless `verify_weights` is false (a local file
        that kept a release's name)."""
        from stereo.backends import make_backend

        return make_backend(
            self.backend,
            weights=self.weights_path,
            max_disp=self.max_disp,
            device=self.device,
            precision=self.precision,
            verify_sha256=self.verify_weights,
        )

    @property
    def weights_path(self) -> str | None:
        """`weights` as `make_backend` takes it (None when empty)."""
        return self.weights or None


MaskInput = BranchMasks | np.ndarray | str | Path | None


class PipelineInputError(ValueError):
    """A frame, mask or camera description the pipeline cannot work with; the message says which."""


@dataclass(frozen=True)
class PipelineConfig:
    """Settings of the whole per-frame chain: the pipeline's TOML sections themselves
    (`branchrange.config.loader.pipeline_config` hands them over from a file), and `check_pair`.

    - `stereo` (`[stereo]`): the backend (`stereo.backends.make_backend` arguments) and `mode`:
      'full' matches the whole frame at full resolution, 'roi' (`branchrange.core.roi`) the whole frame
      at low resolution and each branch at full resolution in its own box and disparity window —
      several times faster at HD720. Whole-frame here, the library's default; the onboard config
      file's default is roi.
    - `roi` (`[roi]`): the coarse-to-fine settings.
    - `cutpoints` (`[cutpoints]`): cut-point estimation, the target policy, tracking on or off.
    - `tracker` (`[branch_tracking]`): how branch ids are kept across frames.
    - `masks` (`[masks]`): how mask files and arrays are read.
    - `segmenter` (`[segmenter]`): the segmenter used when no mask is given, and its settings.
    - `check_pair`: measure the rectified pair's row misalignment (`branchrange.core.pair_check`, ~25 ms)
      on every frame: result field `pair_check`, and a refusal above the hard limit.
    """

    stereo: StereoConfig = field(default_factory=lambda: StereoConfig(mode="full"))
    roi: RoiConfig = field(default_factory=RoiConfig)
    cutpoints: CutPointConfig = field(default_factory=CutPointConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    masks: MaskConfig = field(default_factory=MaskConfig)
    segmenter: SegmenterConfig = field(default_factory=SegmenterConfig)
    check_pair: bool = False


def untracked_whole_frame(max_disp: int = 192, target_policy: str = DEFAULT_TARGET_POLICY) -> PipelineConfig:
    """The settings of evaluations and benchmarks, which score frames one by one: no tracking,
    whole-frame sgbm stereo searching `max_disp` px, targets chosen by `target_policy`."""
    return PipelineConfig(
        stereo=StereoConfig(mode="full", max_disp=max_disp),
        cutpoints=CutPointConfig(tracking=False, target_policy=target_policy),
    )


def with_exact_disparity(config: PipelineConfig) -> PipelineConfig:
    """`config` for a disparity known exactly (a renderer's): the cut points' confidence then leaves out a
    disparity error (`CutPointConfig.cut_disparity_noise_px` 0), which is a matcher's."""
    return replace(config, cutpoints=replace(config.cutpoints, cut_disparity_noise_px=0.0))


@dataclass(frozen=True)
class FrameArtifacts:
    """What the last frame left behind, for overlays and debugging: the rectified left image
    (`uint8 H×W×3`), disparity (`float32 H×W` px, 0 invalid), confidence (`H×W`) and the masks used."""

    left: np.ndarray
    disparity: np.ndarray
    confidence: np.ndarray
    masks: BranchMasks | None


@dataclass(frozen=True, eq=False)
class StereoStage:
    """What the stereo half of a frame hands to the geometry half.

    `left`: rectified `uint8 H×W×3`; `disparity`: `float32 H×W` px (0 invalid); `confidence`: `H×W`
    in [0, 1]; `masks`: the frame's instances, or None when the segmenter is to find them;
    `timing_ms`: the stages so far (ms); `compute_ms`: this half's compute time (ms); `regions`: the
    fine passes of `mode = "roi"` (None in whole-frame mode); `pair_check`: the rectification check
    when asked for; `coarse_trunk`: the trunk as the roi mode's coarse pass saw it (its cylinder is
    fitted from it in the geometry half); `right`: the rectified right image, for the branches' own
    disparity refinement (`branchrange.core.branch_disparity`; None: no refinement); `working_scale`:
    the scale each pixel's disparity was matched at (`uint8 H×W`, the roi mode's region budget; None: all
    at full resolution); `origin`, `keyframe_age_s`, `keyframe_ns`: with keyframes on, whether the segmenter
    ran on this frame or its instances were tracked, and the age (s) and capture time (ns) of the keyframe
    they come from.
    """

    left: np.ndarray
    disparity: np.ndarray
    confidence: np.ndarray
    masks: BranchMasks | None
    geometry: StereoGeometry
    index: int
    timestamp_ns: int
    backend: str
    max_disparity: int
    timing_ms: dict[str, float]
    compute_ms: float
    regions: tuple[Region, ...] | None = None
    pair_check: PairCheck | None = None
    coarse_trunk: CoarseTrunk | None = None
    right: np.ndarray | None = None
    origin: Origin | None = None
    keyframe_age_s: float | None = None
    working_scale: np.ndarray | None = None
    keyframe_ns: int | None = None


@dataclass(frozen=True, eq=False)
class CutPointStage:
    """What `Pipeline.cut_point_stage` hands to `Pipeline.finish_frame`.

    `stage`: the frame's `StereoStage` as the geometry half leaves it: its disparity checked (0 where invalid)
    and refined on the branches, its confidence likewise, its masks found; no right image or working scale
    (not needed any more: less to send between processes). `cut`: the cut points, or None when there was
    nothing to estimate them from, `reason` then saying why; `valid_share`: the share of valid disparity pixels
    in the frame; `timing_ms`: the stages so far (ms); `compute_ms`: both halves' compute time so far (ms).
    """

    stage: StereoStage
    cut: CutPointResult | None
    reason: str | None
    valid_share: float
    timing_ms: dict[str, float]
    compute_ms: float


class Pipeline:
    """Cut points of one stereo frame after another.

    Camera: either `calibration` (a `camera.StereoCalibration`; raw pairs are rectified unless
    `rectified=True` or the calibration says so) or `focal_px` + `baseline_m` (+ `principal_point`,
    default the image centre) of an already rectified pair. `doffs_px`: the pair's disparity offset
    (Z = f·B/(d + doffs)); a rectified calibration's default is its right minus left principal
    column (Middlebury 2014 `calib.txt`). `backend` and `segmenter` may be
    passed in ready-made (tests, a learned segmenter); otherwise they are built from `config`,
    the backend lazily on the first frame.
    """

    def __init__(
        self,
        config: PipelineConfig | None = None,
        *,
        calibration: Any = None,
        focal_px: float | None = None,
        baseline_m: float | None = None,
        principal_point: tuple[float, float] | None = None,
        rectified: bool = False,
        backend: Any = None,
        segmenter: Segmenter | None = None,
        doffs_px: float | None = None,
    ) -> None:
        self.config = config or PipelineConfig()
        self.rectifier = None
        self._size: tuple[int, int] | None = None  # (width, height) the camera description fits
        if calibration is not None:
            if focal_px is not None or baseline_m is not None:
                raise PipelineInputError("give either a calibration or focal_px + baseline_m, not both")
            width, height = calibration.image_size
            self._size = (int(width), int(height))
            if rectified or calibration.is_rectified:
                focal_px, baseline_m = float(calibration.K1[0, 0]), float(calibration.baseline_m)
                principal_point = (float(calibration.K1[0, 2]), float(calibration.K1[1, 2]))
                if doffs_px is None:  # a rectified calibration's right principal point may sit doffs px right
                    doffs_px = float(calibration.K2[0, 2] - calibration.K1[0, 2])
            else:
                from camera import Rectifier

                self.rectifier = Rectifier(calibration)
                focal_px, baseline_m = self.rectifier.focal_px, self.rectifier.baseline_m
                principal_point = self.rectifier.principal_point
        if focal_px is None or baseline_m is None:
            raise PipelineInputError("the pipeline needs a calibration, or focal_px and baseline_m of a rectified pair")
        # validated now (GeometryError names the value) rather than at the first frame
        StereoGeometry(float(focal_px), float(baseline_m), 0.0, 0.0)
        self.focal_px, self.baseline_m = float(focal_px), float(baseline_m)
        self.doffs_px = 0.0 if doffs_px is None else float(doffs_px)
        offset_disparity(np.zeros(1), self.doffs_px)  # a non-finite doffs fails here, not at the first frame
        self.principal_point = principal_point
        self._backend = backend
        self.segmenter: Segmenter = segmenter or self.config.segmenter.build()
        self.tracker = BranchTracker(self.config.tracker)
        self.ood_warnings = OodWarnings()
        self.keyframes = KeyframeSchedule()
        self.keyframe_worker = KeyframeWorker(self._keyframe)  # its thread starts with the first keyframe handed over
        self._worker_coarse_to_fine: CoarseToFine | None = None  # the worker's own matchers, built on first use
        self._worker_shed_level = 0
        # keyframe mode: each carried branch's last trusted cut point (3,) m, by mask id (the geometry half's)
        self._trusted_cuts: dict[int, np.ndarray] = {}
        self._trusted_keyframe_ns: int | None = None  # the keyframe those ids belong to
        self.last: FrameArtifacts | None = None
        self._coarse_to_fine: CoarseToFine | None = None

    @property
    def backend(self) -> Any:
        """The stereo backend, built from the config on first use."""
        if self._backend is None:
            self._backend = self.config.stereo.build_backend()
        return self._backend

    @property
    def coarse_to_fine(self) -> CoarseToFine:
        """The coarse-to-fine matcher of `mode = "roi"` around the (fine) backend, built on first use."""
        if self._coarse_to_fine is None:
            self._coarse_to_fine = CoarseToFine(
                self.config.roi, self.backend, self.segmenter, self.config.stereo.max_disp
            )
        return self._coarse_to_fine

    def geometry_for(self, width: int, height: int) -> StereoGeometry:
        """The rectified camera model for frames of `width × height` px."""
        if self._size is not None and self._size != (width, height):
            raise PipelineInputError(
                f"the calibration is for {self._size[0]}×{self._size[1]} px images but the frames are "
                f"{width}×{height} px; use the calibration of this resolution (e.g. --resolution)"
            )
        if self.principal_point is None:
            return StereoGeometry.centred(self.focal_px, self.baseline_m, width, height)
        return StereoGeometry(self.focal_px, self.baseline_m, *self.principal_point)

    def reset(self) -> None:
        """Forget tracked branches and carried instances (a new sequence or after the camera was lost)."""
        self.tracker.reset()
        self.keyframes.reset()
        self.keyframe_worker.forget()
        self._trusted_cuts = {}

    def _masks(self, mask: MaskInput, shape: tuple[int, int]) -> BranchMasks | None:
        """The frame's `BranchMasks` from a path, array or ready instance (None when not given)."""
        if mask is None:
            return None
        cfg = self.config.masks
        if isinstance(mask, (str, Path)):
            masks = read_mask(mask, trunk_id=cfg.trunk_id, kind=cast(MaskKind, cfg.kind), ignored_ids=cfg.ignored_ids)
        elif isinstance(mask, BranchMasks):
            masks = mask
        else:
            masks = masks_from_array(
                mask, trunk_id=cfg.trunk_id, kind=cast(MaskKind, cfg.kind), ignored_ids=cfg.ignored_ids
            )
        check_instance_count(masks, self.config.cutpoints.max_instances)  # before any other work on such a mask
        if self.rectifier is not None and not self.rectifier.calibration.is_rectified:
            validate_masks(masks, shape)
            masks = replace(masks, labels=self.rectifier.rectify_labels(masks.labels))
        validate_masks(masks, shape)
        return masks

    def process(
        self, left: np.ndarray, right: np.ndarray, mask: MaskInput = None, index: int = 0, timestamp_ns: int = 0
    ) -> FrameResult:
        """One frame: RGB `uint8 H×W×3` pair (raw when a raw calibration was given) → its `FrameResult`.

        `mask`: an instance-id / binary mask (array, path or `BranchMasks`) in the left image's
        pixels, or None for the segmenter. The same as `geometry_stage(stereo_stage(...))`.
        """
        return self.geometry_stage(self.stereo_stage(left, right, mask, index, timestamp_ns))

    def stereo_stage(
        self,
        left: np.ndarray,
        right: np.ndarray,
        mask: MaskInput = None,
        index: int = 0,
        timestamp_ns: int = 0,
        shed_level: int = 0,
    ) -> StereoStage:
        """The first half of a frame: checks, rectification, masks read, disparity.

        In `mode = "roi"` this is the coarse pass, the segmenter (when no mask is given) and the
        full-resolution regions of interest; in `"full"` the whole-frame backend. The onboard
        daemon runs it on its stereo thread and `geometry_stage` on another. `shed_level`
        (`branchrange.onboard.load_shedding`): 1 skips the roi mode's full-resolution instance step,
        2 also the branches' own disparity refinement in the geometry half.
        """
        start = time.perf_counter()
        timing: dict[str, float] = {}
        validate_pair(left, right, PipelineInputError)
        geometry = self.geometry_for(left.shape[1], left.shape[0])
        masks = self._masks(mask, left.shape[:2])
        if self.rectifier is not None:
            left, right = self.rectifier.rectify(left, right)
        pair_check = check_rectification(left, right) if self.config.check_pair else None
        if pair_check is not None:
            pair_check.raise_if_refused()
        t = lap_ms(timing, "rectify", start)
        if self.config.stereo.mode == "roi":
            fine, origin, keyframe_ns = self._roi_stereo(left, right, masks, geometry, timestamp_ns, shed_level, timing)
            timing.update(fine.timing_ms)
            disparity, confidence, masks, regions = fine.disparity, fine.confidence, fine.masks, tuple(fine.regions)
            coarse_trunk, working_scale = fine.trunk, fine.working_scale
            backend, max_disparity = f"{self.backend.name}-roi", self.config.stereo.max_disp
        else:
            regions, coarse_trunk, origin, keyframe_ns, working_scale = None, None, None, None, None
            stereo = self.backend.compute(left, right)
            disparity, confidence = stereo.disparity, stereo.confidence
            backend, max_disparity = stereo.backend or self.backend.name, int(stereo.max_disparity)
        lap_ms(timing, "stereo", t)
        return StereoStage(
            left,
            disparity,
            confidence,
            masks,
            geometry,
            int(index),
            int(timestamp_ns),
            backend,
            max_disparity,
            timing,
            (time.perf_counter() - start) * 1000.0,
            regions,
            pair_check,
            coarse_trunk=coarse_trunk,
            right=right if shed_level < 2 else None,
            origin=origin,
            keyframe_age_s=None if keyframe_ns is None else round((timestamp_ns - keyframe_ns) / 1e9, 3),
            keyframe_ns=keyframe_ns,
            working_scale=working_scale,
        )

    def _roi_stereo(
        self,
        left: np.ndarray,
        right: np.ndarray,
        masks: BranchMasks | None,
        geometry: StereoGeometry,
        timestamp_ns: int,
        shed_level: int,
        timing: dict[str, float],
    ) -> tuple[CoarseToFineResult, Origin | None, int | None]:
        """The roi mode's stereo half: a keyframe (the segmenter runs), or a tracked frame (the last frame's
        instances carried over, `branchrange.core.keyframes`); with masks given, those. Its origin and the
        capture time (ns) of the keyframe its instances descend from are None unless keyframes are on."""
        schedule, roi = self.keyframes, self.config.roi
        if masks is not None or roi.keyframe_interval_s <= 0:
            fine = self.coarse_to_fine.compute(left, right, masks, geometry, full_resolution_instances=shed_level < 1)
            return fine, None, None
        t = time.perf_counter()
        grey = grey_of(left)
        if roi.keyframe_worker:
            carried = self._from_worker(left, right, grey, timestamp_ns, shed_level)
        else:
            carried = schedule.carry_from(timestamp_ns, roi.keyframe_interval_s)
        moved = None
        if carried is not None:
            moved = propagate_labels(
                carried.grey,
                carried.masks,
                grey,
                search_px=roi.track_search_px,
                min_ncc=roi.track_min_ncc,
                offsets=carried.offsets,
            )
            lap_ms(timing, "propagate", t)
        if moved is None or not moved.shifts:
            fine = self.coarse_to_fine.compute(left, right, None, geometry, full_resolution_instances=shed_level < 1)
            found = fine.masks
            gates = {} if found is None else branch_gates(found, fine.disparity, roi.track_gate_px)
            schedule.done(grey, found, gates, timestamp_ns, "keyframe", lost=False)
            return fine, "keyframe", timestamp_ns
        assert carried is not None
        fine = self.coarse_to_fine.compute(
            left, right, replace(carried.masks, labels=moved.labels), geometry, carried=True, gates=carried.gates
        )
        assert fine.masks is not None, "carried masks are given masks"
        labels, failed = verify_support(moved.labels, fine.masks.labels, list(moved.shifts), roi.track_min_support)
        kept = replace(fine.masks, labels=labels)
        fine = replace(fine, masks=kept)
        gates = branch_gates(kept, fine.disparity, roi.track_gate_px)
        # the next frame is matched on the keyframe again (its image, its masks, less the branches lost since),
        # from where this frame found each branch
        gone = set(moved.lost) | set(failed)
        anchor = carried.masks.labels
        anchor = np.where(np.isin(anchor, list(gone)), 0, anchor) if gone else anchor
        offsets = {k: v for k, v in moved.offsets.items() if k not in gone}
        schedule.done(
            carried.grey,
            replace(carried.masks, labels=anchor),
            gates,
            timestamp_ns,
            "tracked",
            lost=bool(gone),
            offsets=offsets,
        )
        return fine, "tracked", carried.keyframe_ns

    def _from_worker(
        self, left: np.ndarray, right: np.ndarray, grey: np.ndarray, timestamp_ns: int, shed_level: int
    ) -> CarriedFrame | None:
        """With `roi.keyframe_worker`: what this frame tracks from — the worker's newest keyframe when one is
        done (carried to this frame from where the whole image moved since), else the last anchor while it
        is younger than `roi.track_max_age_s` — and the frame handed to the worker when a keyframe is due.
        The stereo thread waits only when it has nothing to track and a keyframe is in flight; with nothing
        at all (the first frame, every branch lost) the frame is a keyframe itself (None)."""
        schedule, roi, worker = self.keyframes, self.config.roi, self.keyframe_worker
        fresh = worker.take()
        anchor = schedule.anchor(timestamp_ns, roi.track_max_age_s)
        if fresh is None and anchor is None and worker.busy:
            fresh = worker.take(wait_s=roi.track_max_age_s)
        if fresh is not None and fresh.masks is not None:
            schedule.adopt(fresh.grey, fresh.masks, fresh.gates, fresh.timestamp_ns, global_shift(fresh.grey, grey))
            anchor = schedule.anchor(timestamp_ns, roi.track_max_age_s)
        if anchor is not None and schedule.due(timestamp_ns, roi.keyframe_interval_s):
            self._worker_shed_level = shed_level
            if worker.submit(left, right, timestamp_ns):
                schedule.submitted()
        return anchor

    def _keyframe(self, left: np.ndarray, right: np.ndarray, timestamp_ns: int) -> Keyframe:
        """The keyframe worker's job: the segmenter's instances of a rectified pair, on its own matchers."""
        if self._worker_coarse_to_fine is None:
            self._worker_coarse_to_fine = CoarseToFine(
                self.config.roi, self.config.stereo.build_backend(), self.segmenter, self.config.stereo.max_disp
            )
        geometry = self.geometry_for(left.shape[1], left.shape[0])
        fine = self._worker_coarse_to_fine.compute(
            left, right, None, geometry, full_resolution_instances=self._worker_shed_level < 1
        )
        found = fine.masks
        gates = {} if found is None else branch_gates(found, fine.disparity, self.config.roi.track_gate_px)
        return Keyframe(grey_of(left), found, gates, timestamp_ns)

    def _without_jumps(self, cut: CutPointResult, origin: Origin, keyframe_ns: int | None) -> CutPointResult:
        """Keyframe mode: on a tracked frame, drop each cut point that is more than `roi.track_max_jump_m`
        from its branch's last trusted one (or has none) and ask for a keyframe; remember the trusted ones
        (a keyframe's are all trusted: the segmenter measured them; so are those of the first frame carried
        from a keyframe the worker finished, `keyframe_ns` new: its ids are new)."""
        if origin == "keyframe" or keyframe_ns != self._trusted_keyframe_ns:
            self._trusted_cuts = {b.mask_id: b.cut_point_m for b in cut.branches}
            self._trusted_keyframe_ns = keyframe_ns
            return cut
        kept, dropped = [], list(cut.dropped)
        limit = self.config.roi.track_max_jump_m
        for branch in cut.branches:
            last = self._trusted_cuts.get(branch.mask_id)
            jump = math.inf if last is None else float(np.linalg.norm(branch.cut_point_m - last))
            if jump > limit:
                dropped.append(
                    DroppedBranch(
                        branch.mask_id,
                        "carried over from the last frame, its cut point is "
                        + ("new" if last is None else f"{100 * jump:.0f} cm from that frame's")
                        + f" (more than roi.track_max_jump_m = {limit} m): not trusted until the next keyframe",
                    )
                )
                continue
            kept.append(branch)
        if len(kept) < len(cut.branches):
            self.keyframes.request()
        self._trusted_cuts.update((b.mask_id, b.cut_point_m) for b in kept)
        return CutPointResult(kept, dropped)

    def process_disparity(
        self,
        left: np.ndarray,
        disparity: np.ndarray,
        confidence: np.ndarray | None = None,
        mask: MaskInput = None,
        index: int = 0,
        timestamp_ns: int = 0,
        backend: str = "given",
        right: np.ndarray | None = None,
    ) -> FrameResult:
        """The stages after stereo on a rectified left image and its `float32 H×W` disparity (px).

        `confidence` (`H×W` in [0, 1]) defaults to 1 wherever the disparity is valid. `right`: the
        rectified right image, when given each branch's disparity is refined on its own pixels
        (`[stereo] refine_branches`).
        """
        start = time.perf_counter()
        left = validate_image(left, "left", PipelineInputError)
        disparity = np.asarray(disparity, dtype=np.float32)
        if disparity.shape != left.shape[:2]:
            raise PipelineInputError(
                f"disparity is {disparity.shape[1]}×{disparity.shape[0]} px but the left "
                f"image is {left.shape[1]}×{left.shape[0]} px"
            )
        if confidence is None:
            confidence = valid_disparity(disparity).astype(np.float32)
        elif np.shape(confidence) != disparity.shape:
            raise PipelineInputError(f"confidence has shape {np.shape(confidence)}, expected {disparity.shape}")
        if self.rectifier is not None and not self.rectifier.calibration.is_rectified:
            raise PipelineInputError("process_disparity needs a rectified frame; this pipeline rectifies raw pairs")
        if right is not None:
            right = validate_image(right, "right", PipelineInputError)
            if right.shape[:2] != left.shape[:2]:
                raise PipelineInputError(
                    f"right image is {right.shape[1]}×{right.shape[0]} px but the left "
                    f"image is {left.shape[1]}×{left.shape[0]} px"
                )
        geometry = self.geometry_for(left.shape[1], left.shape[0])
        masks = self._masks(mask, left.shape[:2])
        finite_max = (
            np.nanmax(np.where(np.isfinite(disparity), disparity, np.nan)) if np.isfinite(disparity).any() else 0.0
        )
        stage = StereoStage(
            left,
            disparity,
            np.asarray(confidence),
            masks,
            geometry,
            int(index),
            int(timestamp_ns),
            backend,
            max(1, int(np.ceil(finite_max)) + 1),
            {"rectify": 0.0, "stereo": 0.0},
            (time.perf_counter() - start) * 1000.0,
            right=right,
        )
        return self.geometry_stage(stage)

    def geometry_stage(self, stage: StereoStage) -> FrameResult:
        """The second half of a frame: masks (the segmenter when none) → cut points → tracking → target → result.
        The same as `finish_frame(cut_point_stage(stage))`.

        `timing_ms.total` is the compute time of both halves (ms), not including any wait between them.
        """
        return self.finish_frame(self.cut_point_stage(stage))

    def cut_point_stage(self, stage: StereoStage) -> CutPointStage:
        """The part of the geometry half that keeps nothing from one frame to the next: the disparity checked,
        masks (the segmenter when none), the branches' own disparity, the trunk, the cut points. The stereo
        worker processes (`branchrange.onboard.stereo_workers`) run it beside the stereo half; `finish_frame`,
        which carries the state across frames (tracking, keyframes), runs in the daemon."""
        start = t = time.perf_counter()
        timing = dict(stage.timing_ms)
        left, geometry, masks, max_disparity = stage.left, stage.geometry, stage.masks, stage.max_disparity
        valid = valid_disparity(stage.disparity, max_disparity)
        # non-finite values are no evidence: keep them out of every later stage
        disparity = np.where(valid, stage.disparity, 0.0).astype(np.float32)
        if self.doffs_px:  # from here on, Z = f·B/d (Middlebury's doffs folded into d)
            disparity = offset_disparity(disparity, self.doffs_px)
        confidence = np.where(valid, np.nan_to_num(stage.confidence, nan=0.0), 0.0).astype(np.float32)
        reason = None
        cut: CutPointResult | None = None
        if masks is None:
            masks = self.segmenter.segment(left, disparity, geometry, confidence) if valid.any() else None
        t = lap_ms(timing, "masks", t)
        working_scales = {} if masks is None else branch_scales(masks, stage.working_scale)
        if masks is not None and stage.right is not None and self.config.stereo.refine_branches:
            disparity = refine_branch_disparity(  # rewrites `confidence` (this frame's own) on refined branches
                left,
                stage.right,
                disparity,
                masks,
                confidence,
                doffs_px=self.doffs_px,
                max_disparity=max_disparity,
                working_scales=working_scales,
            ).disparity
            t = lap_ms(timing, "branch_disparity", t)
        if masks is None or not valid.any():  # no masks only when nothing was valid to segment
            reason = "no valid disparity in the frame (textureless, overexposed or out of the stereo range)"
        elif not masks.branch_ids():
            reason = (
                f"the mask ({masks.source}) holds no branch instance"
                if masks.source != self.segmenter.name
                else f"the {masks.source} segmenter found no branch"
            )
        else:
            trunk_model: TrunkModel | None | Literal["fit"] = "fit"  # whole-frame mode: from the mask
            if stage.regions is not None:  # roi mode: the trunk's cylinder from the coarse pass
                roi = self.config.roi
                trunk_points = roi.budget_trunk_points if roi.budget else 0
                trunk_model = (
                    None if stage.coarse_trunk is None else stage.coarse_trunk.fit(self.config.cutpoints, trunk_points)
                )
                t = lap_ms(timing, "trunk", t)
            cut = estimate_cut_points(
                masks,
                disparity,
                geometry,
                self.config.cutpoints,
                confidence=confidence,
                max_disparity=max_disparity,
                trunk_model=trunk_model,
                working_scales=working_scales,
            )
        lap_ms(timing, "cutpoints", t)
        done = replace(stage, disparity=disparity, confidence=confidence, masks=masks, right=None, working_scale=None)
        compute_ms = stage.compute_ms + (time.perf_counter() - start) * 1000.0
        return CutPointStage(done, cut, reason, round(float(valid.mean()), 4), timing, compute_ms)

    def finish_frame(self, cut_stage: CutPointStage) -> FrameResult:
        """The end of a frame, in frame order: keyframe trust, tracking, the target, the `FrameResult`; the frame's
        images become `last`."""
        start = time.perf_counter()
        stage, reason, timing = cut_stage.stage, cut_stage.reason, dict(cut_stage.timing_ms)
        left, geometry, masks, disparity = stage.left, stage.geometry, stage.masks, stage.disparity
        cut = CutPointResult() if cut_stage.cut is None else cut_stage.cut
        if cut_stage.cut is not None:
            if stage.origin is not None:
                cut = self._without_jumps(cut, stage.origin, stage.keyframe_ns)
            if not cut.branches:
                reason = f"all {len(cut.dropped)} branch instances were dropped: " + "; ".join(
                    f"{d.mask_id}: {d.reason}" for d in cut.dropped[:5]
                )
        self.last = FrameArtifacts(left, disparity, stage.confidence, masks)
        t = time.perf_counter()
        if self.config.cutpoints.tracking:
            self.tracker.update(cut.branches)
        t = lap_ms(timing, "tracking", t)
        needed = self.config.cutpoints.target_min_confidence
        target = select_target(  # the policy name was checked where the settings entered
            cut.branches, cast(TargetPolicy, self.config.cutpoints.target_policy), target_minimum(needed, masks)
        )
        if target is None and cut.branches:
            reason = no_target_reason(needed, masks)
        timing["total"] = round(cut_stage.compute_ms + (time.perf_counter() - start) * 1000.0, 3)
        ood = None if masks is None else masks.ood
        self.ood_warnings.note(ood)
        return FrameResult(
            frame=Frame(stage.index, stage.timestamp_ns, int(left.shape[1]), int(left.shape[0])),
            camera=CameraInfo(geometry.focal_px, geometry.baseline_m, geometry.cx, geometry.cy),
            stereo=StereoInfo(stage.backend, int(stage.max_disparity), cut_stage.valid_share),
            timing_ms=timing,
            masks=MasksInfo("none", 0, False)
            if masks is None
            else MasksInfo(
                masks.source,
                len(masks.branch_ids()),
                masks.trunk() is not None,
                None if masks.light is None else LightInfo.from_reading(masks.light),
            ),
            branches=tuple(
                _refused_in_light(Branch.from_estimate(b), needed, masks)
                for b in sorted(cut.branches, key=lambda b: b.id)
            ),
            dropped=tuple(DroppedInstance.from_dropped(d) for d in cut.dropped),
            target_id=None if target is None else int(target.id),
            reason=reason,
            roi=None if stage.regions is None else RoiInfo(tuple(RoiRegion.from_region(r) for r in stage.regions)),
            pair_check=None if stage.pair_check is None else PairCheckInfo.from_check(stage.pair_check),
            origin=stage.origin,
            keyframe_age_s=stage.keyframe_age_s,
            segmenter_ood=None if ood is None else SegmenterOod.from_reading(ood),
        )


def _refused_in_light(branch: Branch, needed: float, masks: BranchMasks | None) -> Branch:
    """`branch` marked `light_refuses_target` when the frame's light asks more of a target than the settings'
    minimum `needed` and more than its confidence: the MAVLink relay's fused tracks read it, so the light's
    rule holds for the target it sends too."""
    light_needs = target_minimum(needed, masks)
    if light_needs > needed and branch.confidence < light_needs:
        return replace(branch, light_refuses_target=True)
    return branch


def target_minimum(needed: float, masks: BranchMasks | None) -> float:
    """The confidence a cut point needs to be the target: the settings' minimum `needed`, or more where the
    frame's light asks more (`BranchMasks.target_min_confidence`; `math.inf`: no target in that light)."""
    return max(needed, 0.0 if masks is None else masks.target_min_confidence)


def no_target_reason(needed: float, masks: BranchMasks | None) -> str:
    """Why no cut point became the target: none reached the settings' minimum `needed`, or none what the
    frame's light asks (`BranchMasks.target_min_confidence`, from the calibration measured in that light)."""
    light_needs = target_minimum(needed, masks)
    if masks is not None and masks.calibration is None and math.isinf(light_needs):
        return "the segmenter's model carries no confidence calibration: its cut points are never targets"
    if masks is None or masks.light is None or light_needs <= needed:
        return f"no branch reaches the target confidence {needed}"
    light = masks.light
    if math.isinf(light_needs):
        return (
            f"no target in {light.light} light ({light.measured}): when the segmenter was calibrated, no confidence "
            "in that light was ≥ 90 % right"
        )
    return f"no branch reaches the target confidence {light_needs} that {light.light} light needs ({light.measured})"
