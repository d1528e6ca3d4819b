"""`LearnedSegmenter`: branch instances from the shipped `BranchNet` (ONNX, onnxruntime on CPU) plus geometry.

Steps (one frame):
1. `BranchNet` gives per-pixel background / trunk / branch probabilities from the left image and
   the disparity (its input: `network_input`; the network itself, for training only:
   `branchrange.learning.branchnet`), seen at `network_width` and brought back to the frame's size; the
   columns around the trunk it finds are seen once more at twice that size (`trunk_band_px`),
   where the thin stems a pruner cuts leave the trunk;
2. the trunk is the trunk region that branches grow from, with its other parts at its depth
   (`trunk.tree_trunk`: other trunks, posts and frames are background to the cut-point stage, and a
   branch in front of the trunk cuts its silhouette in two); trunk pixels nearer than the bark on both
   sides (`trunk.in_front_of_trunk`, `front_of_trunk_ratio`) are a stem before it and become branch
   pixels — the network alone calls a thin dark stem on dark bark trunk;
3. branch pixels are cut apart where the depth jumps (`depth_edge_ratio`, as in the built-in
   segmenters: a stem crossing in front of another becomes two), then each region is split into
   straight pieces (`pieces.straight_pieces_of`, each line as wide as the branch where it is drawn):
   branches that leave the trunk side by side or cross in the image at one depth are one region, and
   one axis through two branches gives a cut point on neither; pieces under `min_area_px` are dropped;
4. with a trunk found, only pieces within `max_trunk_gap_m` of it are kept: what a pruner cuts grows
   from the trunk (a loose piece is a twig, the far part of a branch, a leaf or background);
5. each instance's score is the mean branch probability over its pixels, lowered when the piece
   stops short of the trunk (`trunk_attachment`) — carried in
   `BranchMasks.scores` and multiplied into its cut point's confidence, so a doubtful instance
   never produces a confident cut point; that product goes through the model's measured
   calibration at the width and trunk band the network saw the frame with and in the frame's light
   (`branchrange.learning.calibration`, `branchrange.core.light_check`), so a reported confidence is the share of such
   cut points that lie within 5 cm of a true one (SGBM, held-out synthetic scenes); where that light's
   calibration found a higher least confidence for ≥ 90 % right targets, or none, the masks carry it
   (`BranchMasks.target_min_confidence`).

The weights file ships inside the package (`weights/branchnet.onnx`, under 1 MB) and is checked
against the SHA-256 recorded beside it (`weights/branchnet.json`, which also holds the training
config, seed and validation IoU); `model=` takes another file trained with `branchrange
train-segmenter`, checked against its own JSON when one sits beside it, or a model bundle folder (a
fine-tune on a user's labels, `bundle`), checked against its manifest.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from branchrange.core.confidence import ConfidenceCalibration
from branchrange.core.geometry import StereoGeometry, disparity_to_depth
from branchrange.core.light_check import LIGHTS, LightReading, measure_light
from branchrange.core.masks import DEFAULT_TRUNK_ID, BranchMasks
from branchrange.core.segmentation.bundle import bundle_model
from branchrange.core.segmentation.network_input import CLASSES, IN_CHANNELS, STRIDE, network_input
from branchrange.core.segmentation.onnx_model import EXECUTION_PROVIDERS, OnnxSegmenterError, onnx_session
from branchrange.core.segmentation.ood import (
    OodReading,
    OodReference,
    OodReferenceError,
    frame_statistic,
    reference_in,
)
from branchrange.core.segmentation.pieces import bridged_region_of, straight_pieces_of
from branchrange.core.segmentation.segmenter import foreground_depth_edges
from branchrange.core.segmentation.trunk import in_front_of_trunk, tree_trunk, trunk_gap_m
from branchrange.core.settings_check import Checks, Limit, Settings, one_of
from stereo.weights import sha256_of

log = logging.getLogger(__name__)

#: the shipped model and its metadata (SHA-256, training config, validation IoU)
SHIPPED_MODEL = Path(__file__).with_name("weights") / "branchnet.onnx"
#: the shipped model per `LearnedSegmenterConfig.precision` (int8: `branchrange.learning.quantize`, its own calibration)
SHIPPED_MODELS = {"fp32": SHIPPED_MODEL, "int8": SHIPPED_MODEL.with_name("branchnet_int8.onnx")}
_BACKGROUND, _TRUNK, _BRANCH = (CLASSES.index(name) for name in ("background", "trunk", "branch"))
#: the range of `LearnedSegmenterConfig.network_width` (px)
MIN_NETWORK_WIDTH, MAX_NETWORK_WIDTH = 160, 4096
#: class probabilities are floored at this before their log is taken: a class ruled out keeps a finite logit
PROBABILITY_FLOOR = 1e-6
#: the largest `LearnedSegmenterConfig.trunk_band_px` (px)
MAX_TRUNK_BAND_PX = 1024
#: a frame column holds the trunk when the first look labels at least this many of its pixels trunk
TRUNK_COLUMN_MIN_PX = 5
#: the trunk band is looked at with this many times the first look's pixels per frame pixel, per side
TRUNK_BAND_ZOOM = 2
#: the width (px) of the synthetic scenes the model is trained and calibrated on: a model JSON written
#: before calibrations recorded their width holds one "confidence_calibration", measured at it
SCENE_WIDTH = 640


@dataclass(frozen=True)
class LearnedSegmenterConfig(Settings):
    """Settings of `LearnedSegmenter`.

    - `model`: an ONNX `BranchNet` file, or a model bundle folder (`branchrange train-segmenter --coco`: checked
      against its manifest, `bundle`); empty = the shipped one of `precision`.
    - `precision`: "fp32" or "int8" (a statically quantized copy: its network ~1.4×, the whole segmenter
      ~1.2× faster on CPU, same recall; `branchrange.learning.quantize`): of the shipped model with `model` empty, or of
      a bundle folder made with `--int8`; a `model` .onnx file is run as it is (fp32 only).
    - `device`: where the network runs: "cpu" (the default), "cuda" (onnxruntime's CUDA provider) or "tensorrt"
      (its TensorRT provider, which also runs the int8 copy), both from onnxruntime-gpu on a CUDA companion
      (`onnx_model.EXECUTION_PROVIDERS`); a device whose provider the installed onnxruntime lacks is refused when
      the segmenter is built, never run on the CPU instead. The int8 copy is a CPU or TensorRT model: with
      "cuda", use `precision = "fp32"`.
    - `network_width`: the width (px) the network sees a frame at — the frame is resized to it, aspect
      kept, and the class probabilities back to the frame's size; 0 (the default) = the frame's own
      width: the roi mode's 640×360 coarse frame as it is, what the onboard loop affords (8 fresh Hz on
      2 cores; 2.9 Hz and a p95 latency over 0.5 s at 1280). Stems 1–3 px wide in a 640×360 frame are
      what the network misses most; at 1280 they are 2–6 px, inside the 0.5–1.6× scales it was trained
      at: on 30 held-out 640×360 scenes recall within 5 cm is 67 against 58 % with SGBM and 86 against
      76 % with exact disparity, for 3.5× the time (211 against 61 ms on one thread) and fewer cut points
      confident enough to be a target (24 against 29 % of the branches) — the choice off the vehicle
      (`deploy/serve.toml`).
    - `branch_threshold`: branch probability a pixel needs (0..1); the trunk is the arg-max class.
    - `min_area_px`: smaller branch instances are dropped (speckle, twig tips).
    - `depth_edge_ratio`: neighbours whose depths differ by more than this fraction are cut apart.
    - `front_of_trunk_ratio`: trunk pixels whose disparity exceeds the bark's on both sides by this share
      (and 0.3 px) are a stem in front of the trunk, a branch candidate (`trunk.in_front_of_trunk`; 0 = off).
      At 0.03, recall within 5 cm with exact disparity +4.3 points on calibration scenes 2861–2940 and
      +5.0 held out, where 12 % of the branches had been called trunk; with SGBM +0.5 and 0 (on bark SGBM
      rarely shows a 2 px stem nearer) for ~0.5 more false cut points a frame, all low-confidence — so
      the deploy files, whose segmenter sees SGBM (the roi mode's coarse pass), set 0.
    - `trunk_band_px`: the network looks a second time at the columns within this many px of those the
      first look calls trunk, at `TRUNK_BAND_ZOOM` times the first look's size, and there the two looks'
      class probabilities are averaged (`log_mean_probability`; 0 = one look). What a pruner cuts grows
      from the trunk, and the stems 1–3 px wide the first look misses most are there. At 40, with SGBM:
      recall within 5 cm on calibration scenes 2861–2980 60.4 → 62.9 % and false cut points 6.40 → 5.78
      a frame, held out 59.4 → 67.2 % and 5.17 → 4.57 (on 60 held-out scenes 59.8 → 64.1 % and 5.68 →
      5.22) — about the recall of the whole frame seen at 1280 (66.3 % on the 60), with fewer false cut
      points, for ~60 % of its time: the band is on average a third of the frame's width, and the second
      look costs ~70 ms on one thread (134–140 against 65–68 ms a 640×360 frame; 88
      against 50 ms on two). The onboard deploy files set 0: the real-time loop cannot spare it (5.6
      against 8.1 fresh Hz on the synthetic HD720 flight).
    - `max_trunk_gap_m`: with a trunk found, instances farther from it than this are dropped (0 = keep all).
    - `attachment_scale_m`: a kept piece that stops short of the trunk by more than `TOUCHING_TRUNK_M`
      has its score multiplied by exp(−(gap − `TOUCHING_TRUNK_M`) / this) (`trunk_attachment`; 0 = off).
    - `visible_length_scale_m`: a cut point's confidence is also multiplied by L / (L + this) of its branch's
      visible length L (base to tip, m; `confidence.visible_length_factor`, 0 = off) before the calibration,
      which is measured with it: short pieces are more often fragments (bark ridges, twig ends, leaf edges).
      Chosen on calibration scenes 2861–2980 (0.05 / 0.1 / 0.2 alike, 0.1 best at few false cut points);
      held out (240 scenes, SGBM, ranked by the product), the branches found at ≤ 0.3 / 0.5 / 1 false cut
      points a frame rose 35.4 → 39.3 / 42.5 → 45.2 / 51.2 → 52.9 % with the trunk band and 31.9 → 32.4 /
      38.3 → 41.1 / 46.5 → 48.9 % with one look.
    - `split_straight`: split each branch region into straight pieces (`pieces.straight_pieces_of`), so
      branches that touch or cross in the image become separate instances; else 8-connected regions.
    - `bridge_px`: branch pixels up to 2× this many px apart belong to one region (`pieces.bridged_regions`), for
      the trunk-gap filter and the straight pieces, whose runs may skip as much: a stem seen through leaves
      shows as fragments, each under `min_area_px`, that only together make a piece. At 3 against 0, on 60
      held-out scenes: with the trunk band recall within 5 cm 63.0 → 64.4 % with SGBM and 83.2 → 85.1 % with
      exact disparity, false cut points 4.53 → 4.30 and 2.98 → 2.78 a frame; seen at 1280 65.8 → 70.1 %; on
      the real Jadeplant pair 1 → 4 cut points on branches, none on not-branch. With one look no change
      (58.7 → 58.2 %), and in the real-time loop on the synthetic HD720 approach flight (one look) the frames
      with a target fell from 0.52 to 0.25: so it applies only where the network sees the stems enlarged (a
      second look at the trunk band, or `network_width` above the frame's; `LearnedSegmenter.bridge_px`),
      the setting where the fragments it finds are real stems, and never with one look at the frame's width
      (the onboard deploy files).
    - `piece_disparity_ratio`: a straight piece's pixels must also follow its line in depth: within this share
      of the line's disparity (at least `pieces.PIECE_MIN_DISPARITY_PX`) of the disparity affine along the
      line between its two sample pixels (`pieces.straight_pieces`; 0, the default, = the image alone). A thin
      stem crossing a thicker branch in the image, or leaving the trunk beside it at a shallow angle, lies at
      another depth; without the test the thicker one's line takes the stem's base. Off by default because it
      finds more branches but not more that a robot may act on. At 0.04 (the best of 0.02–0.15 with floors of
      0.2–2 px on calibration scenes 2861–2980), held out on 240 scenes: recall within 5 cm with exact
      disparity 82.0 → 84.0 % (surely; at 1280 84.7 → 87.2 %), with SGBM 65.3 → 65.9 % (within noise) for
      0.8 more false cut points a frame; yet after recalibration the cut points at confidence ≥ 0.8 that are
      right fell from 449 to 390 with SGBM, the onboard one-look threshold rose from 0.72 to 0.80, and with
      exact disparity the targets within 5 cm fell from 94 to 89 % (benchmarks/RESULTS.md). Worth trying with
      a stereo better than SGBM's, after recalibrating the model with it on.
    - `calibrated`: report cut-point confidences through the model's measured calibration at the width
      the network sees the frame at and its trunk band (its JSON's "confidence_calibrations"; the nearest
      width measured, by ratio, then the nearest band), so that a confidence is the share of such cut
      points that are right.
    - `light_calibration`: measure each frame's light (`light_check.measure_light`: dark, bright, noisy or
      normal) and read its confidences through the calibration measured in that light, with that light's
      least target confidence (a table where none was ≥ 90 % right gives no target in that light; since the
      depth's precision entered the confidence every shipped table has one). Held out, calibration error at
      dusk 0.108 → 0.056 and at high gain 0.096 → 0.019 against the normal-light table (benchmarks/RESULTS.md);
      off = every frame through the normal-light calibration, as before lights were measured.
    - `ood`: read each frame's out-of-distribution signal (`ood`: how far the network's class probabilities on
      the frame lie from those on its training domain, against the reference in the model's JSON under "ood")
      into the result (`segmenter_ood`) and warn when the model does not look like it knows the scene; off, or a
      model whose JSON has no reference, = no signal. ~1–2 ms a 640×360 frame.
    - `threads`: onnxruntime intra-op threads. 1 by default: onboard the segmenter runs in the stereo
      thread while the geometry thread works on the other core (roi-sgbm on the synthetic flight:
      9.9–10.7 fresh Hz with 1 thread, 8.5–9.2 with 2); alone it costs 62 / 53 ms (1 / 2 threads) on a
      640×360 frame at `network_width` 640, 209 / 153 ms at 1280.
    - `trunk_id`: the id the trunk gets in the returned instances.
    """

    section = "segmenter.learned"
    error = OnnxSegmenterError
    limits = {
        "precision": Limit(enum=tuple(SHIPPED_MODELS)),
        "device": Limit(enum=tuple(EXECUTION_PROVIDERS)),
        "network_width": Limit(minimum=0, maximum=MAX_NETWORK_WIDTH),  # 0, or from MIN_NETWORK_WIDTH: checks()
        "branch_threshold": Limit(exclusive_minimum=0, exclusive_maximum=1, expected="a probability in (0, 1)"),
        "min_area_px": Limit(minimum=1, expected="≥ 1 pixel"),
        "depth_edge_ratio": Limit(exclusive_minimum=0, expected="> 0 (relative depth jump)"),
        "front_of_trunk_ratio": Limit(
            minimum=0, maximum=1, expected="0..1 (share of the bark's disparity; 0 = stems before the trunk stay trunk)"
        ),
        "trunk_band_px": Limit(
            minimum=0, maximum=MAX_TRUNK_BAND_PX, expected=f"0..{MAX_TRUNK_BAND_PX} px (0 = the network looks once)"
        ),
        "bridge_px": Limit(minimum=0, maximum=20, expected="0..20 px (0 = regions as 8-connected)"),
        "piece_disparity_ratio": Limit(
            minimum=0, maximum=1, expected="0..1 (share of a line's disparity; 0 = pieces follow the image alone)"
        ),
        "max_trunk_gap_m": Limit(minimum=0, maximum=10, expected="0..10 m (0 = keep instances away from the trunk)"),
        "attachment_scale_m": Limit(
            minimum=0, maximum=1, expected="0..1 m (0 = a piece's gap to the trunk is not scored)"
        ),
        "visible_length_scale_m": Limit(
            minimum=0, maximum=10, expected="0..10 m (0 = how long a branch is seen is not scored)"
        ),
        "threads": Limit(minimum=1, maximum=64, expected="1..64 threads"),
        "trunk_id": Limit(minimum=1, maximum=65535),
    }

    model: str = ""
    precision: str = "fp32"
    device: str = "cpu"
    network_width: int = 0
    branch_threshold: float = 0.5
    min_area_px: int = 12
    depth_edge_ratio: float = 0.06
    front_of_trunk_ratio: float = 0.03
    trunk_band_px: int = 40
    max_trunk_gap_m: float = 0.1
    attachment_scale_m: float = 0.02
    visible_length_scale_m: float = 0.1
    split_straight: bool = True
    bridge_px: int = 3
    piece_disparity_ratio: float = 0.0
    calibrated: bool = True
    light_calibration: bool = True
    ood: bool = True
    threads: int = 1
    trunk_id: int = DEFAULT_TRUNK_ID

    def checks(self) -> Checks:
        """Range checks of the settings (`Settings`)."""
        return {
            "precision": (
                self.precision in SHIPPED_MODELS
                and (self.precision == "fp32" or not self.model.lower().endswith(".onnx")),
                "'fp32' or 'int8' (the shipped models, or a bundle folder's int8 copy; a model file of your own "
                "(.onnx) is used as it is: leave precision 'fp32')",
            ),
            "device": (
                self.device in EXECUTION_PROVIDERS and not (self.device == "cuda" and self.precision == "int8"),
                f"{one_of(EXECUTION_PROVIDERS)}; the int8 copy runs on 'cpu' or 'tensorrt', not 'cuda'",
            ),
            "network_width": (
                self.network_width == 0 or MIN_NETWORK_WIDTH <= self.network_width <= MAX_NETWORK_WIDTH,
                f"0 (the frame's own width) or {MIN_NETWORK_WIDTH}..{MAX_NETWORK_WIDTH} px",
            ),
            "trunk_id": (0 < self.trunk_id <= 65535, "an id in 1..65535"),
        }


def verified_metadata(path: Path) -> dict[str, Any]:
    """The metadata JSON beside the model `path` ({} when there is none), after checking that the SHA-256
    it records matches the file; `OnnxSegmenterError` naming both hashes when not, or a missing file."""
    meta_path = path.with_suffix(".json")
    if not path.is_file():
        raise OnnxSegmenterError(f"learned segmenter: no model file {path}")
    if not meta_path.is_file():
        return {}
    try:
        meta = dict(json.loads(meta_path.read_text(encoding="utf-8")))
    except (OSError, ValueError, TypeError) as exc:
        raise OnnxSegmenterError(f"learned segmenter: {meta_path} is not a readable JSON object ({exc})") from None
    expected = meta.get("onnx_sha256")
    found = sha256_of(path)
    if expected and expected != found:
        raise OnnxSegmenterError(
            f"learned segmenter: {path} has SHA-256 {found}, but {meta_path.name} "
            f"records {expected}: the file is damaged or not the one trained"
        )
    return meta


#: how a confidence calibration was measured: (network width px, trunk band px, class of light in `LIGHTS`)
Setting = tuple[int, int, str]


@dataclass(frozen=True)
class MeasuredCalibration:
    """One table of a model JSON's "confidence_calibrations": the map of raw to calibrated confidence, the
    light it was measured in (`LIGHTS`) and the least calibrated confidence at which ≥ 90 % of its cut points
    were right (`math.inf` when none was: JSON null; 0 when the table does not say)."""

    calibration: ConfidenceCalibration
    light: str
    target_min_confidence: float


def calibrations_by_setting(meta: dict[str, Any]) -> dict[Setting, MeasuredCalibration]:
    """A model JSON's confidence calibrations keyed by how the network saw the calibration scenes: (width
    px, `trunk_band_px`, light) ("confidence_calibrations": [{..., "network_width": W, "trunk_band_px": B,
    "light": L}]; B absent = 0, one look; L absent = "normal"; an older single "confidence_calibration"
    counts as (`SCENE_WIDTH`, 0, "normal")); ValueError naming what is wrong."""
    tables = meta.get("confidence_calibrations")
    if tables is None:
        old = meta.get("confidence_calibration")
        tables = [] if old is None else [{**old, "network_width": SCENE_WIDTH}]
    if not isinstance(tables, list):
        raise ValueError("'confidence_calibrations' must be a list of tables, each with its 'network_width'")
    calibrations = {}
    for table in tables:
        if not isinstance(table, dict) or not isinstance(table.get("network_width"), int):
            raise ValueError("every confidence calibration needs an integer 'network_width' (px)")
        if not isinstance(table.get("trunk_band_px", 0), int):
            raise ValueError("a confidence calibration's 'trunk_band_px' must be an integer (px)")
        light = table.get("light", "normal")
        if light not in LIGHTS:
            raise ValueError(f"a confidence calibration's 'light' must be one of {', '.join(LIGHTS)}, not {light!r}")
        minimum = table.get("target_min_confidence", 0.0)
        if minimum is not None and not (isinstance(minimum, (int, float)) and 0 <= minimum <= 1):
            raise ValueError("a confidence calibration's 'target_min_confidence' must be null or a number in [0, 1]")
        calibrations[(table["network_width"], table.get("trunk_band_px", 0), light)] = MeasuredCalibration(
            ConfidenceCalibration.from_json_dict(table), light, math.inf if minimum is None else float(minimum)
        )
    return calibrations


class LearnedSegmenter:
    """`Segmenter` over `BranchNet` (see the module docstring)."""

    name = "learned"

    def __init__(self, config: LearnedSegmenterConfig = LearnedSegmenterConfig()) -> None:
        self.config = config
        self.model_path = Path(config.model) if config.model else SHIPPED_MODELS[config.precision]
        if self.model_path.is_dir():  # a model bundle (`bundle`): its manifest and files checked first
            self.model_path = bundle_model(self.model_path, config.precision)
        meta = verified_metadata(self.model_path)
        try:
            self.calibrations = calibrations_by_setting(meta) if config.calibrated else {}
            self.ood_reference: OodReference | None = reference_in(meta) if config.ood else None
        except (ValueError, OodReferenceError) as exc:
            raise OnnxSegmenterError(f"learned segmenter: {self.model_path.with_suffix('.json')}: {exc}") from None
        if config.calibrated and not self.calibrations:
            log.warning(
                "learned segmenter: %s carries no confidence calibration: its cut points are reported with raw "
                "confidences and are never targets (calibrate it, or fine-tune with more held-out frames)",
                self.model_path,
            )
        # the int8 copy (metadata "quantization") gains from onnxruntime's blocked layout, fp32 loses (see there)
        self.session = onnx_session(
            self.model_path, config.threads, blocked_layout="quantization" in meta, device=config.device
        )
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        if len(inputs) != 1 or inputs[0].shape[1:2] != [IN_CHANNELS] or outputs[0].shape[1:2] != [len(CLASSES)]:
            raise OnnxSegmenterError(
                f"learned segmenter: {self.model_path} is not a BranchNet (expected one input (1, {IN_CHANNELS}, H, W) "
                f"and logits (1, {len(CLASSES)}, H, W); found inputs {[(i.name, i.shape) for i in inputs]}, "
                f"outputs {[(o.name, o.shape) for o in outputs]})"
            )
        self._input = inputs[0].name

    def _target_minimum(self, measured: MeasuredCalibration | None) -> float:
        """The least confidence a target needs beyond the settings' own by the calibration `measured` for a frame:
        none in normal light (the settings' minimum stands: its default is that table's), its light's where it
        asks more, and `math.inf` (never a target) for a model with no calibration at all — a raw confidence
        says nothing measured, and the settings' minimum was chosen for a calibrated one."""
        if measured is None:
            return math.inf if self.config.calibrated and not self.calibrations else 0.0
        return 0.0 if measured.light == "normal" else measured.target_min_confidence

    def calibration_at(self, seen_width: int, light: str = "normal") -> MeasuredCalibration | None:
        """The calibration measured at the width nearest (by ratio) `seen_width` px — with the trunk band nearest
        this segmenter's `trunk_band_px` where several were measured there — in `light`, or in normal light
        when none was measured in it; None without any."""
        if not self.calibrations:
            return None
        band = self.config.trunk_band_px
        width, band = min(
            {s[:2] for s in self.calibrations}, key=lambda s: (abs(math.log(s[0] / seen_width)), abs(s[1] - band))
        )
        in_light = {s[2]: c for s, c in self.calibrations.items() if s[:2] == (width, band)}
        return in_light.get(light) or in_light.get("normal") or next(iter(in_light.values()))

    def bridge_px(self, frame_width: int) -> int:
        """`bridge_px` when the network looks at the stems enlarged — a second look at the trunk band, or the
        frame seen wider than it is — else 0 (see `LearnedSegmenterConfig.bridge_px`)."""
        enlarged = self.config.trunk_band_px > 0 or self.seen_width(frame_width) > frame_width
        return self.config.bridge_px if enlarged else 0

    def seen_width(self, frame_width: int) -> int:
        """The width (px) the network sees a frame `frame_width` px wide at (`network_width`)."""
        return self.config.network_width or frame_width

    def logits(self, left: np.ndarray, disparity: np.ndarray) -> np.ndarray:
        """`float32 (3, H, W)` background / trunk / branch logits of a frame (`CLASSES` order), `H×W` the
        frame's size. The network sees it resized to `network_width` (the disparity's values need no
        scaling: the network divides them by their 95th percentile); its class probabilities are then
        resampled to the frame's pixels — a frame pixel's share of stem, averaged over the ones the
        network saw — and returned as log-probabilities (logits of the same softmax). In the `trunk_band`
        the network looks once more at `TRUNK_BAND_ZOOM` times that size, and there the log of the two
        looks' mean probabilities is returned."""
        return self.looked(left, disparity)[0]

    def looked(self, left: np.ndarray, disparity: np.ndarray) -> tuple[np.ndarray, OodReading | None]:
        """`logits` of a frame and its out-of-distribution reading (`ood`), taken on the first look's logits —
        what the reference was measured on whatever the trunk band — or None without a reference."""
        seen = self.seen_width(disparity.shape[1])
        logits = self.first_look(left, disparity)
        ood = None if self.ood_reference is None else self.ood_reference.reading(frame_statistic(logits))
        band = self.trunk_band(logits)
        if band is not None:  # the columns around the trunk once more, larger: both looks' probabilities averaged
            first, last = band
            zoomed = band_seen_width(last - first, seen / disparity.shape[1])
            second = self._logits_seen_at(left[:, first:last], disparity[:, first:last], zoomed)
            logits[:, :, first:last] = log_mean_probability(logits[:, :, first:last], second)
        return logits, ood

    def first_look(self, left: np.ndarray, disparity: np.ndarray) -> np.ndarray:
        """`float32 (3, H, W)` logits of the network's first look at a frame, at `network_width` and brought back
        to the frame's size (`logits` without the trunk band's second look): what the out-of-distribution
        statistics are taken on, at run time and when a model's reference is measured
        (`branchrange.learning.ood_reference`)."""
        return self._logits_seen_at(left, disparity, self.seen_width(disparity.shape[1]))

    def trunk_band(self, logits: np.ndarray) -> tuple[int, int] | None:
        """Columns [first, last) within `trunk_band_px` of the columns the `(3, H, W)` logits call trunk
        (≥ `TRUNK_COLUMN_MIN_PX` of their pixels), widened to multiples of `STRIDE` (the network's grid; on
        the held-out scenes, with the second look replacing the first, 71.1 % recall against 67.2 % for the
        band as it fell); None when the setting is 0 or no column holds the trunk."""
        if not self.config.trunk_band_px:
            return None
        trunk = (logits[_TRUNK] > logits[_BACKGROUND]) & (logits[_TRUNK] > logits[_BRANCH])
        columns = np.flatnonzero(np.count_nonzero(trunk, axis=0) >= TRUNK_COLUMN_MIN_PX)
        if columns.size == 0:
            return None
        band = self.config.trunk_band_px
        first, last = max(0, int(columns[0]) - band), min(trunk.shape[1], int(columns[-1]) + band + 1)
        return first // STRIDE * STRIDE, min(trunk.shape[1], -(-last // STRIDE) * STRIDE)

    def _logits_seen_at(self, left: np.ndarray, disparity: np.ndarray, seen: int) -> np.ndarray:
        """`logits` of a frame (or a band of columns of it) that the network sees `seen` px wide."""
        height, width = disparity.shape
        if seen != width:
            size = (seen, max(1, round(height * seen / width)))
            larger = seen > width
            left = cv2.resize(left, size, interpolation=cv2.INTER_LINEAR if larger else cv2.INTER_AREA)
            disparity = cv2.resize(np.asarray(disparity, dtype=np.float32), size, interpolation=cv2.INTER_NEAREST)
        rows, cols = disparity.shape
        features = network_input(left, disparity, stride=STRIDE)
        logits = np.asarray(self.session.run(None, {self._input: features[None]})[0][0, :, :rows, :cols])
        return resampled_logits(logits, (width, height))

    def segment(
        self, left: np.ndarray, disparity: np.ndarray, geometry: StereoGeometry, confidence: np.ndarray | None = None
    ) -> BranchMasks:
        """Branch instances (1..K, each scored) and the trunk (`trunk_id`) of one rectified frame."""
        disparity = np.asarray(disparity, dtype=np.float32)
        if left.shape[:2] != disparity.shape:
            raise ValueError(f"left image {left.shape[:2]} and disparity {disparity.shape} differ in size")
        logits, ood = self.looked(left, disparity)
        return self.instances(logits, left, disparity, geometry, ood=ood)

    def instances(
        self,
        logits: np.ndarray,
        left: np.ndarray,
        disparity: np.ndarray,
        geometry: StereoGeometry,
        light: LightReading | None = None,
        ood: OodReading | None = None,
    ) -> BranchMasks:
        """`segment` given the network's class logits (`float32 (3, h, w)`, as `logits` returns them) of the frame
        `left` (`uint8 H×W×3`) with `disparity` (`float32 H×W` px) — or of that frame shrunk s = W / w times:
        the roi mode's coarse look, whose instances are found again at full resolution on the fine disparity
        (`RoiConfig.full_resolution_instances`). The class probabilities are then resampled to the frame's
        pixels, `min_area_px` and the bridged gap grow s times (a thin stem's area grows with its length),
        and the light and the confidences are read as at the width the network saw (its tables' classes of
        light were measured there: shrinking a frame averages its noise down). `light`: that frame's light
        when already measured (the coarse step's), else it is measured here; `ood`: the frame's
        out-of-distribution reading (`looked`), carried in the masks."""
        cfg = self.config
        size = (logits.shape[2], logits.shape[1])  # the frame's, or the coarse look's (W, H)
        width, scale = size[0], disparity.shape[1] / size[0]
        trunk_p, branch_p = trunk_and_branch_probabilities(logits, (disparity.shape[1], disparity.shape[0]))
        labels = np.zeros(disparity.shape, dtype=np.int32)
        depth = disparity_to_depth(disparity, geometry)  # inf where invalid
        trunk_px = (trunk_p > 1.0 - trunk_p - branch_p) & (trunk_p > branch_p)  # the arg-max class
        branch = (branch_p >= cfg.branch_threshold) & ~trunk_px
        branch &= ~foreground_depth_edges(branch, depth, cfg.depth_edge_ratio)
        trunk = tree_trunk(trunk_px, branch, depth, geometry, cfg.max_trunk_gap_m)
        bridge_px = round(self.bridge_px(width) * scale)
        min_area_px = round(cfg.min_area_px * scale)
        if cfg.front_of_trunk_ratio > 0:
            before_trunk = in_front_of_trunk(trunk, disparity, cfg.front_of_trunk_ratio, min_area_px)
            trunk &= ~before_trunk
            branch |= before_trunk
        labels[trunk] = cfg.trunk_id
        near_trunk = trunk.any() and cfg.max_trunk_gap_m > 0
        pixels = np.flatnonzero(branch)  # the branch pixels as flat indices: a few % of the frame
        if near_trunk:  # drop whole regions far from the trunk before the (costlier) splitting
            gap_m = trunk_gap_m(trunk, depth, geometry, pixels)
            region, region_count = bridged_region_of(branch, bridge_px, pixels)
            near = _nearest(region, gap_m, region_count)[region] <= cfg.max_trunk_gap_m
            branch.flat[pixels[~near]] = False
            pixels, gap_m = pixels[near], gap_m[near]
        instances = np.zeros(disparity.shape, dtype=np.int32)
        if cfg.split_straight:
            for piece_id, (pu, pv) in enumerate(
                straight_pieces_of(
                    branch,
                    min_area_px,
                    np.random.default_rng(0),
                    bridge_px,
                    disparity=disparity,
                    disparity_ratio=cfg.piece_disparity_ratio,
                ),
                1,
            ):
                instances[pv, pu] = piece_id
        else:
            instances = cv2.connectedComponents(branch.astype(np.uint8), connectivity=8)[1]
        instance = instances.ravel()[pixels]  # every instance pixel is a branch pixel
        count = int(instance.max(initial=0)) + 1
        sizes = np.bincount(instance, minlength=count)
        keep = np.flatnonzero(sizes[1:] >= min_area_px) + 1
        attachment = np.ones(count)
        if near_trunk:  # a piece of a region that touches the trunk may itself lie far from it
            gaps = _nearest(instance, gap_m, count)
            keep = keep[gaps[keep] <= cfg.max_trunk_gap_m]
            attachment[keep] = trunk_attachment(gaps[keep], cfg.attachment_scale_m)
        sums = np.bincount(instance, weights=branch_p.ravel()[pixels], minlength=count)
        scores = {i: float(sums[k] / sizes[k] * attachment[k]) for i, k in enumerate(keep.tolist(), 1)}
        renumber = np.zeros(count, dtype=np.int32)
        renumber[keep] = np.arange(1, len(keep) + 1)
        instance = renumber[instance]  # 0: dropped
        kept = instance > 0
        labels.ravel()[pixels[kept]] = instance[kept]
        if not cfg.light_calibration:
            light = None
        elif light is None:  # on the frame the network saw, where the tables' classes of light were measured
            light = measure_light(left if scale == 1 else cv2.resize(left, size, interpolation=cv2.INTER_AREA))
        measured = self.calibration_at(self.seen_width(width), "normal" if light is None else light.light)
        return BranchMasks(
            labels,
            cfg.trunk_id,
            self.name,
            scores=scores,
            calibration=None if measured is None else measured.calibration,
            light=light,
            target_min_confidence=self._target_minimum(measured),
            visible_length_scale_m=cfg.visible_length_scale_m,
            ood=ood,
        )


#: a piece whose pixels come this close to the trunk (m) touches it: SGBM fattens edges by a pixel or two
TOUCHING_TRUNK_M = 0.01


def band_seen_width(band_px: int, first_scale: float) -> int:
    """The width (px) the second look sees a band `band_px` frame px wide at: `TRUNK_BAND_ZOOM` times the
    first look's scale (`first_scale` = its seen width / the frame's), at most `MAX_NETWORK_WIDTH` — a
    2208 px ZED frame whose trunk spans it would otherwise ask for a 4416 px look, seconds and gigabytes."""
    return max(1, min(round(TRUNK_BAND_ZOOM * band_px * first_scale), MAX_NETWORK_WIDTH))


def log_mean_probability(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """`float32 (C, H, W)` log of the mean of two looks' class probabilities, each given as logits `(C, H, W)`.

    Why the mean and not the second look alone: on calibration scenes 2861–2980 (SGBM, trunk band 40 px)
    the second look alone put 14 % more cut points right (564 against 533) but made the confident ones
    less reliable, so the ≥ 90 %-right threshold rose to 0.88 and held out only 18 cut points reached it
    (55 with one look); the mean keeps what both looks agree on: 232 right at its threshold 0.78 on the
    calibration scenes (213 with one look), held out 63 (55) and 144 right in all (119)."""
    mean = 0.5 * (class_probabilities(first) + class_probabilities(second))
    return np.asarray(np.log(np.maximum(mean, PROBABILITY_FLOOR)), dtype=np.float32)


def class_probabilities(logits: np.ndarray) -> np.ndarray:
    """`(C, H, W)` softmax over the class axis of logits `(C, H, W)`."""
    exp = np.exp(logits - logits.max(axis=0))
    return np.asarray(exp / exp.sum(axis=0))


def resampled_logits(logits: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """`float32 (C, H, W)` log class probabilities of logits `(C, h, w)` resampled to `size` = (W, H) (the
    same array type when the size is theirs already; see `resampled_probability`)."""
    if (logits.shape[2], logits.shape[1]) == size:
        return np.asarray(logits, dtype=np.float32)
    probability = [resampled_probability(p, size) for p in class_probabilities(logits)]
    return np.asarray(np.log(np.maximum(np.stack(probability), PROBABILITY_FLOOR)), dtype=np.float32)


def resampled_probability(probability: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """`float32 H×W`: one class's probabilities `h×w` resampled to `size` = (W, H). Probabilities, not logits,
    are resampled: a 1 px stem seen 2 px wide then keeps its share of each frame pixel (held out, recall at
    confidence ≥ 0.8 28 against 24 % with logits); shrinking averages them (area), enlarging interpolates them
    (bilinear). Both weigh the pixels by shares that sum to 1, so resampled classes still sum to 1."""
    probability = np.asarray(probability, dtype=np.float32)
    if (probability.shape[1], probability.shape[0]) == size:
        return probability
    interpolation = cv2.INTER_AREA if size[0] < probability.shape[1] else cv2.INTER_LINEAR
    return np.asarray(cv2.resize(probability, size, interpolation=interpolation))


def trunk_and_branch_probabilities(logits: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """`float32 H×W` each: the trunk and the branch class probabilities of logits `(3, h, w)`, resampled to
    `size` = (W, H) when that is not their own (`resampled_probability`); the background's is 1 − both.

    Why not `resampled_logits`: the instance step needs only these two, and in the roi mode it runs at full
    resolution (1280×720) — the background channel's resize and the log taken then undone cost ~5 ms there."""
    probability = class_probabilities(logits)
    return resampled_probability(probability[_TRUNK], size), resampled_probability(probability[_BRANCH], size)


def trunk_attachment(gaps_m: np.ndarray, scale_m: float) -> np.ndarray:
    """Factor in (0, 1] per piece from how close (m, `(K,)`) it comes to the trunk: 1 when it touches
    (≤ `TOUCHING_TRUNK_M`), exp(−(gap − `TOUCHING_TRUNK_M`) / `scale_m`) beyond; all 1 for `scale_m` 0.

    Why: a branch grows from the trunk, so a piece that stops short of it is often the far part of a
    branch whose base another piece took, or a twig or leaf edge — on the calibration scenes the
    confident wrong cut points stopped a median 9 mm short (p90 6 cm), the right ones 5 mm (p90 8 mm).
    Folded into the score it ranks them lower, and the calibration then reports it."""
    if scale_m == 0:
        return np.ones(len(gaps_m))
    return np.asarray(np.exp(-np.maximum(0.0, gaps_m - TOUCHING_TRUNK_M) / scale_m), dtype=np.float64)


def _nearest(labels: np.ndarray, gap_m: np.ndarray, count: int) -> np.ndarray:
    """`(count,)`: the smallest `gap_m` `(N,)` (m) over the pixels of each label, given the pixels' labels
    `(N,)` in 0..count − 1 (inf for absent labels and 0)."""
    nearest = np.full(count, np.inf)
    np.minimum.at(nearest, labels, gap_m)
    nearest[0] = np.inf
    return nearest
