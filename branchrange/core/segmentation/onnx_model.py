"""Bring your own model: branch instances from an ONNX segmentation network run by onnxruntime on CPU.

Two output layouts are understood, recognised from the model's outputs:

- **YOLOv8-seg** (two outputs): detections `(1, 4 + nc + nm, N)` — box centre/size `cx, cy, w, h`
  in input pixels, `nc` class scores, `nm` mask coefficients — and prototypes `(1, nm, h, w)`;
  or the end-to-end form `(1, N, 6 + nm)` — `x1, y1, x2, y2, score, class`, coefficients — that
  an export with NMS gives. A detection's mask is `sigmoid(coefficients · prototypes)` cropped to
  its box; raw detections go through per-class NMS first.
- **Per-pixel logits** (one output `(1, C, h, w)`): semantic classes, arg-max per pixel (one
  channel: sigmoid > `mask_threshold`); branch pixels are split into instances by 8-connectivity,
  trunk pixels form the trunk.

Input: `(1, 3, H, W)` float32 RGB in [0, 1] (the Ultralytics convention). A fixed input size is
letterboxed (aspect kept, grey 114 padding); a dynamic one gets the image padded to a multiple of
`stride`. Which class ids are branch and which trunk is configuration, not guessed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import cv2
import numpy as np

from branchrange.core.geometry import StereoGeometry
from branchrange.core.masks import DEFAULT_TRUNK_ID, BranchMasks, split_binary
from branchrange.core.settings_check import Checks, Settings
from stereo.onnx_runtime import import_onnxruntime


class OnnxSegmenterError(ValueError):
    """A model file or setting the ONNX segmenter cannot use; the message says which and why."""


@dataclass(frozen=True)
class OnnxSegmenterConfig(Settings):
    """Settings of `OnnxSegmenter` (the `[segmenter]` keys besides `model`).

    - `branch_classes`, `trunk_classes`: the model's class ids that are branch / trunk (others are
      ignored); at least one branch class.
    - `score_threshold`: detections scoring lower are dropped (YOLO layouts).
    - `mask_threshold`: probability above which a pixel belongs to a mask (0..1).
    - `nms_iou`: IoU above which the weaker of two same-class boxes is suppressed.
    - `min_area_px`: smaller instances are dropped (speckle).
    - `stride`: dynamic input sizes are padded to a multiple of this.
    - `threads`: onnxruntime intra-op threads (the pipeline shares 2 cores with stereo).
    """

    branch_classes: tuple[int, ...] = (0,)
    trunk_classes: tuple[int, ...] = ()
    score_threshold: float = 0.25
    mask_threshold: float = 0.5
    nms_iou: float = 0.5
    min_area_px: int = 20
    stride: int = 32
    threads: int = 2
    trunk_id: int = DEFAULT_TRUNK_ID

    section = "segmenter"
    error: ClassVar[type[ValueError]] = OnnxSegmenterError

    def checks(self) -> Checks:
        """The range of every setting; a class id is branch or trunk, not both."""
        overlap = set(self.branch_classes) & set(self.trunk_classes)
        return {
            "branch_classes": (
                len(self.branch_classes) > 0 and min(self.branch_classes) >= 0,
                "at least one class id ≥ 0",
            ),
            "trunk_classes": (
                not overlap and all(c >= 0 for c in self.trunk_classes),
                f"class ids ≥ 0 that are not also branch classes (both: {sorted(overlap)})",
            ),
            "score_threshold": (0 <= self.score_threshold <= 1, "a score in [0, 1]"),
            "mask_threshold": (0 < self.mask_threshold < 1, "a probability in (0, 1)"),
            "nms_iou": (0 < self.nms_iou <= 1, "an IoU in (0, 1]"),
            "min_area_px": (self.min_area_px >= 1, "≥ 1 pixel"),
            "stride": (self.stride >= 1, "≥ 1 pixel"),
            "threads": (self.threads >= 1, "≥ 1"),
            "trunk_id": (0 < self.trunk_id <= 65535, "an id in 1..65535"),
        }


@dataclass(frozen=True)
class _Letterbox:
    """How an image was placed into the network input: scale, then (left, top) padding in px."""

    scale: float
    pad_x: int
    pad_y: int
    input_w: int
    input_h: int

    def to_image(self, plane: np.ndarray, width: int, height: int, interpolation: int) -> np.ndarray:
        """A `h×w` map over the network input (any resolution) → the original `height×width` image."""
        full = cv2.resize(plane, (self.input_w, self.input_h), interpolation=interpolation)
        x0, y0 = self.pad_x, self.pad_y
        x1 = x0 + int(round(width * self.scale))
        y1 = y0 + int(round(height * self.scale))
        return cv2.resize(full[y0:y1, x0:x1], (width, height), interpolation=interpolation)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.clip(x, -50.0, 50.0)))


def onnx_session(path: Path, threads: int, blocked_layout: bool = True) -> onnxruntime.InferenceSession:  # noqa: F821 - optional import
    """An onnxruntime CPU session of the model file `path` with `threads` intra-op threads;
    `OnnxSegmenterError` naming the file when it is missing or unreadable, or onnxruntime is absent.

    `blocked_layout` False stops one graph optimisation: the NCHWc layout (channels in blocks of 8 or 16
    for the AVX2 / AVX-512 convolution kernels). A network of few channels at full resolution pays more
    for reordering its tensors between the blocked convolutions and the resizes and concatenations
    around them than the kernels save: BranchNet in fp32 segments 7 % faster without it, with identical
    labels (`benchmarks/segmenter.py` frames, 1 and 2 threads), while its int8 copy is 15 % slower."""
    if not path.is_file():
        raise OnnxSegmenterError(f"onnx:{path}: no such model file (expected an .onnx file)")
    try:
        ort = import_onnxruntime()
    except ImportError:
        raise OnnxSegmenterError(
            "onnx segmenters need onnxruntime (a dependency of branchrange): pip install onnxruntime"
        ) from None
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    if not blocked_layout:
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED
    try:
        return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # noqa: BLE001 - onnxruntime raises its own types for any unreadable model
        raise OnnxSegmenterError(f"onnx:{path}: not a model onnxruntime can load ({exc})") from None


class OnnxSegmenter:
    """`Segmenter` over an ONNX model (YOLOv8-seg or per-pixel logits), onnxruntime on CPU."""

    def __init__(self, path: str | Path, config: OnnxSegmenterConfig = OnnxSegmenterConfig()) -> None:
        path = Path(path)
        self.session = onnx_session(path, config.threads)
        self.config = config
        self.name = f"onnx:{path.name}"
        inputs = self.session.get_inputs()
        if len(inputs) != 1 or len(inputs[0].shape) != 4:
            raise OnnxSegmenterError(
                f"onnx:{path}: expected one image input (1, 3, H, W), got {[(i.name, i.shape) for i in inputs]}"
            )
        self._input = inputs[0].name
        h, w = inputs[0].shape[2:]
        self._fixed_size = (w, h) if isinstance(w, int) and isinstance(h, int) else None
        outputs = self.session.get_outputs()
        self.layout = self._layout(path, [o.shape for o in outputs])

    @staticmethod
    def _layout(path: Path, shapes: list[list]) -> str:
        """'yolo' for detections + prototypes, 'logits' for one `(1, C, h, w)` map; else an error."""
        ranks = [len(s) for s in shapes]
        if ranks == [4]:
            return "logits"
        if sorted(ranks) == [3, 4]:
            return "yolo"
        raise OnnxSegmenterError(
            f"onnx:{path}: outputs of shapes {shapes} are neither YOLOv8-seg "
            "(detections (1, 4+nc+nm, N) and prototypes (1, nm, h, w)) nor "
            "per-pixel logits (one output (1, C, h, w))"
        )

    def _prepare(self, left: np.ndarray) -> tuple[np.ndarray, _Letterbox]:
        """The `(1, 3, H, W)` float32 input and where the image sits in it."""
        height, width = left.shape[:2]
        if self._fixed_size is not None:
            in_w, in_h = self._fixed_size
            scale = min(in_w / width, in_h / height)
        else:
            s = self.config.stride
            scale = 1.0
            in_w, in_h = -(-width // s) * s, -(-height // s) * s
        new_w, new_h = int(round(width * scale)), int(round(height * scale))
        canvas = np.full((in_h, in_w, 3), 114, dtype=np.uint8)
        pad_x, pad_y = (in_w - new_w) // 2, (in_h - new_h) // 2
        resized = (
            left
            if (new_w, new_h) == (width, height)
            else cv2.resize(left, (new_w, new_h), interpolation=cv2.INTER_AREA)
        )
        canvas[pad_y : pad_y + new_h, pad_x : pad_x + new_w] = resized
        tensor = canvas.astype(np.float32).transpose(2, 0, 1)[None] / 255.0
        return np.ascontiguousarray(tensor), _Letterbox(scale, pad_x, pad_y, in_w, in_h)

    def segment(
        self, left: np.ndarray, disparity: np.ndarray, geometry: StereoGeometry, confidence: np.ndarray | None = None
    ) -> BranchMasks:
        """Instances for `left` (`uint8 H×W×3` RGB); disparity and geometry are not used by the model."""
        tensor, box = self._prepare(left)
        outputs = self.session.run(None, {self._input: tensor})
        height, width = left.shape[:2]
        if self.layout == "logits":
            labels = self._from_logits(outputs[0][0], box, width, height)
        else:
            detections, prototypes = sorted(outputs, key=lambda o: o.ndim)
            labels = self._from_yolo(detections[0], prototypes[0], box, width, height)
        return BranchMasks(labels, self.config.trunk_id, self.name)

    def _from_logits(self, logits: np.ndarray, box: _Letterbox, width: int, height: int) -> np.ndarray:
        """Instance labels from a `(C, h, w)` logit map: branch components 1..K, trunk = `trunk_id`."""
        cfg = self.config
        if logits.shape[0] == 1:
            prob = box.to_image(_sigmoid(logits[0]).astype(np.float32), width, height, cv2.INTER_LINEAR)
            classes = np.where(prob > cfg.mask_threshold, 0, -1)
        else:
            planes = np.stack([box.to_image(p.astype(np.float32), width, height, cv2.INTER_LINEAR) for p in logits])
            classes = np.argmax(planes, axis=0)
        labels = split_binary(np.isin(classes, cfg.branch_classes), cfg.min_area_px)
        if cfg.trunk_classes:
            labels[np.isin(classes, cfg.trunk_classes) & (labels == 0)] = cfg.trunk_id
        return labels.astype(np.int32)

    def _detections(self, raw: np.ndarray, n_coeffs: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(boxes `(K, 4)` x1 y1 x2 y2 input px, scores `(K,)`, classes `(K,)`, coefficients `(K, nm)`)."""
        cfg = self.config
        rows, cols = raw.shape
        if cols == 6 + n_coeffs:  # end-to-end export, NMS done (raw exports have thousands of columns)
            boxes, scores, classes, coeffs = raw[:, :4], raw[:, 4], raw[:, 5].astype(int), raw[:, 6:]
            keep = scores >= cfg.score_threshold
            return boxes[keep], scores[keep], classes[keep], coeffs[keep]
        if rows <= 4 + n_coeffs:
            raise OnnxSegmenterError(
                f"{self.name}: detections of shape {raw.shape} do not hold 4 box values, "
                f"class scores and {n_coeffs} mask coefficients per column"
            )
        table = raw.T  # (N, 4 + nc + nm)
        class_scores = table[:, 4 : rows - n_coeffs]
        classes = np.argmax(class_scores, axis=1)
        scores = class_scores[np.arange(len(table)), classes]
        keep = scores >= cfg.score_threshold
        table, classes, scores = table[keep], classes[keep], scores[keep]
        cx, cy, w, h = table[:, 0], table[:, 1], table[:, 2], table[:, 3]
        boxes = np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], axis=1)
        chosen: list[int] = []
        for cls in np.unique(classes):
            idx = np.flatnonzero(classes == cls)
            xywh = [[float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])] for b in boxes[idx]]
            kept = cv2.dnn.NMSBoxes(xywh, scores[idx].astype(float).tolist(), cfg.score_threshold, cfg.nms_iou)
            chosen.extend(int(idx[k]) for k in np.asarray(kept).reshape(-1))
        chosen.sort()
        return boxes[chosen], scores[chosen], classes[chosen], table[chosen, rows - n_coeffs :]

    def _from_yolo(
        self, raw: np.ndarray, prototypes: np.ndarray, box: _Letterbox, width: int, height: int
    ) -> np.ndarray:
        """Instance labels from YOLOv8-seg outputs; higher-scoring instances win overlapping pixels."""
        cfg = self.config
        n_coeffs, proto_h, proto_w = prototypes.shape
        boxes, scores, classes, coeffs = self._detections(raw, n_coeffs)
        labels = np.zeros((height, width), dtype=np.int32)
        wanted = np.isin(classes, cfg.branch_classes + cfg.trunk_classes)
        order = np.argsort(-scores[wanted])
        boxes, classes, coeffs = boxes[wanted][order], classes[wanted][order], coeffs[wanted][order]
        flat = prototypes.reshape(n_coeffs, -1)
        gx = (np.arange(proto_w) + 0.5) * box.input_w / proto_w
        gy = (np.arange(proto_h) + 0.5) * box.input_h / proto_h
        next_id = 1
        for (x1, y1, x2, y2), cls, c in zip(boxes, classes, coeffs):
            prob = _sigmoid(c @ flat).reshape(proto_h, proto_w).astype(np.float32)
            prob *= ((gx >= x1) & (gx <= x2))[None, :] & ((gy >= y1) & (gy <= y2))[:, None]
            mask = (box.to_image(prob, width, height, cv2.INTER_LINEAR) > cfg.mask_threshold) & (labels == 0)
            if mask.sum() < cfg.min_area_px:
                continue
            if cls in cfg.trunk_classes:
                labels[mask] = cfg.trunk_id
            else:
                labels[mask] = next_id
                next_id += 1
        return labels
