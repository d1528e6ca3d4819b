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

Input: `(1, 3, H, W)` float32 RGB in [0, 1] (the Ultralytics convention), the frame letterboxed into
it as Ultralytics' predictor does (aspect kept, bilinear resize, grey 114 padding split evenly): a
fixed-shape model at its own input size; a dynamic-shape one at `input_size`, or the `imgsz` the
exporter wrote into the model's metadata, or 640 — never the frame's own size: a model trained at 640
finds a 1920×1080 frame's branches far less often there, in 4–5× the time — with the padding cut
to what makes each side a multiple of `stride` (Ultralytics' "rect" letterbox). Detections
are kept from `score_threshold` (0.25) and NMS suppresses above `nms_iou` (0.7): Ultralytics' predict
defaults `conf` and `iou`. Which class ids are branch and which trunk is configuration, not guessed.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import cv2
import numpy as np

from branchrange.core.geometry import StereoGeometry
from branchrange.core.masks import DEFAULT_TRUNK_ID, BranchMasks, split_binary
from branchrange.core.settings_check import Checks, Limit, Settings
from stereo.onnx_runtime import import_onnxruntime

#: Ultralytics' predict `imgsz`: the input side of a dynamic-shape model whose metadata gives none.
DEFAULT_INPUT_SIDE_PX = 640
#: The largest input side accepted from the settings or a model's metadata.
MAX_INPUT_SIDE_PX = 8192


class OnnxSegmenterError(ValueError):
    """A model file or setting the ONNX segmenter cannot use; the message says which and why."""


@dataclass(frozen=True)
class OnnxSegmenterConfig(Settings):
    """Settings of `OnnxSegmenter` (the `[segmenter]` keys besides `model`).

    - `branch_classes`, `trunk_classes`: the model's class ids that are branch / trunk (others are
      ignored); at least one branch class.
    - `score_threshold`: detections scoring lower are dropped (YOLO layouts); 0.25 is Ultralytics'
      predict default `conf`.
    - `mask_threshold`: probability above which a pixel belongs to a mask (0..1).
    - `nms_iou`: IoU above which the weaker of two same-class boxes is suppressed; 0.7 is Ultralytics'
      default `iou` (0.5 kept 3.2 of 5.3 branches an image where thin diagonal stems' boxes overlap).
    - `input_size`: a dynamic-shape model's input, px: the frame is letterboxed into this square
      (Ultralytics' `imgsz`); 0 = the `imgsz` in the model's metadata (its export size), else 640.
      A fixed-shape model runs at its own input size.
    - `min_area_px`: smaller instances are dropped (speckle).
    - `stride`: a dynamic-shape input's sides are padded to a multiple of this (the network's largest
      downsampling: 32 for YOLOv8/11/26-seg).
    - `threads`: onnxruntime intra-op threads (the pipeline shares 2 cores with stereo).
    - `trunk_id`: the id the trunk gets in the returned instances.
    """

    branch_classes: tuple[int, ...] = (0,)
    trunk_classes: tuple[int, ...] = ()
    score_threshold: float = 0.25
    mask_threshold: float = 0.5
    nms_iou: float = 0.7
    input_size: int = 0
    min_area_px: int = 20
    stride: int = 32
    threads: int = 2
    trunk_id: int = DEFAULT_TRUNK_ID

    section = "segmenter"
    error: ClassVar[type[ValueError]] = OnnxSegmenterError
    limits = {
        "branch_classes": Limit(minimum=0),
        "trunk_classes": Limit(minimum=0),
        "score_threshold": Limit(minimum=0, maximum=1, expected="a score in [0, 1]"),
        "mask_threshold": Limit(exclusive_minimum=0, exclusive_maximum=1, expected="a probability in (0, 1)"),
        "nms_iou": Limit(exclusive_minimum=0, maximum=1, expected="an IoU in (0, 1]"),
        "min_area_px": Limit(minimum=1, expected="≥ 1 pixel"),
        "stride": Limit(minimum=1, expected="≥ 1 pixel"),
        "threads": Limit(minimum=1, expected="≥ 1"),
        "trunk_id": Limit(minimum=1, maximum=65535),
    }

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
            "input_size": (
                self.input_size == 0 or self.stride <= self.input_size <= MAX_INPUT_SIDE_PX,
                f"0 (the model's export size) or {self.stride}..{MAX_INPUT_SIDE_PX} px",
            ),
            "trunk_id": (0 < self.trunk_id <= 65535, "an id in 1..65535"),
        }


@dataclass(frozen=True)
class _Letterbox:
    """How an image was placed into the network input: scaled by `scale` to `inner_w×inner_h` px,
    at (`pad_x`, `pad_y`) px in the `input_w×input_h` input."""

    scale: float
    pad_x: int
    pad_y: int
    inner_w: int
    inner_h: int
    input_w: int
    input_h: int

    @classmethod
    def fit(cls, width: int, height: int, target: tuple[int, int], stride: int | None) -> _Letterbox:
        """Place a `width×height` image into `target` (w, h) px, aspect kept, centred.

        `stride` None: the input is `target` itself (a fixed-shape model). Otherwise `target` is first
        rounded up to multiples of `stride` (Ultralytics' `check_imgsz`) and the input keeps of the
        padding only what makes each side a multiple of `stride` (its letterbox with `auto=True`, what
        its predictor uses for a dynamic-shape model): a 1920×1080 frame at 640 becomes 640×360 in a
        640×384 input."""
        if stride is not None:
            target = (-(-target[0] // stride) * stride, -(-target[1] // stride) * stride)
        scale = min(target[0] / width, target[1] / height)
        inner_w, inner_h = int(round(width * scale)), int(round(height * scale))
        in_w, in_h = target
        if stride is not None:
            in_w, in_h = inner_w + (in_w - inner_w) % stride, inner_h + (in_h - inner_h) % stride
        return cls(scale, (in_w - inner_w) // 2, (in_h - inner_h) // 2, inner_w, inner_h, in_w, in_h)

    def to_input(self, image: np.ndarray) -> np.ndarray:
        """The `uint8 H×W×3` image placed into the `input_h×input_w×3` input, grey 114 around it;
        resized bilinearly, as Ultralytics' `LetterBox` does."""
        canvas = np.full((self.input_h, self.input_w, 3), 114, dtype=np.uint8)
        inner = (self.inner_w, self.inner_h)
        resized = image if inner == image.shape[1::-1] else cv2.resize(image, inner, interpolation=cv2.INTER_LINEAR)
        canvas[self.pad_y : self.pad_y + self.inner_h, self.pad_x : self.pad_x + self.inner_w] = resized
        return canvas

    def to_image(self, plane: np.ndarray, width: int, height: int, interpolation: int) -> np.ndarray:
        """A `h×w` map over the network input (any resolution) → the original `height×width` image."""
        full = cv2.resize(plane, (self.input_w, self.input_h), interpolation=interpolation)
        inner = full[self.pad_y : self.pad_y + self.inner_h, self.pad_x : self.pad_x + self.inner_w]
        return cv2.resize(inner, (width, height), interpolation=interpolation)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.clip(x, -50.0, 50.0)))


def _export_size(text: str) -> tuple[int, int] | None:
    """(w, h) px of a metadata `imgsz` ('640', '[640, 640]' or '[384, 640]': Ultralytics writes [h, w]);
    None when it is not one or two whole numbers in 1..`MAX_INPUT_SIDE_PX`."""
    try:
        value: Any = json.loads(text)  # str() of an int or a list of ints is JSON
    except ValueError:
        return None
    sides = [value] if isinstance(value, int) else list(value) if isinstance(value, (list, tuple)) else []
    if not 1 <= len(sides) <= 2 or not all(type(v) is int and 1 <= v <= MAX_INPUT_SIDE_PX for v in sides):
        return None
    return sides[-1], sides[0]


#: A segmenter's `device` → the onnxruntime execution providers it asks for, best first; the CPU's last takes the
#: nodes a GPU provider leaves. TensorRT (NVIDIA's, in the Jetson builds of onnxruntime-gpu) also runs an int8 copy.
EXECUTION_PROVIDERS: dict[str, tuple[str, ...]] = {
    "cpu": ("CPUExecutionProvider",),
    "cuda": ("CUDAExecutionProvider", "CPUExecutionProvider"),
    "tensorrt": ("TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"),
}


def execution_providers(device: str, available: list[str]) -> list[str]:
    """The providers of `device` (`EXECUTION_PROVIDERS`) that onnxruntime has (`available`); `OnnxSegmenterError`
    when it lacks the device's own: a model asked to run on the GPU never runs on the CPU unnoticed."""
    wanted = EXECUTION_PROVIDERS[device]
    if wanted[0] not in available:
        raise OnnxSegmenterError(
            f"segmenter device {device!r} needs onnxruntime's {wanted[0]}, and the installed onnxruntime has "
            f"{', '.join(available) or 'none'}: install onnxruntime-gpu (on a Jetson, NVIDIA's JetPack build), "
            'or set [segmenter.learned] device = "cpu"'
        )
    return [provider for provider in wanted if provider in available]


def onnx_session(
    path: Path, threads: int, blocked_layout: bool = True, device: str = "cpu"
) -> onnxruntime.InferenceSession:  # noqa: F821 - optional import
    """An onnxruntime session of the model file `path` on `device` (`EXECUTION_PROVIDERS`) with `threads`
    intra-op threads; `OnnxSegmenterError` naming the file when it is missing or unreadable, onnxruntime is
    absent or lacks the device's provider.

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
    providers = execution_providers(device, list(ort.get_available_providers()))
    try:
        return ort.InferenceSession(str(path), options, providers=providers)
    except Exception as exc:  # noqa: BLE001 - onnxruntime raises its own types for any unreadable model
        raise OnnxSegmenterError(f"onnx:{path}: not a model onnxruntime can load ({exc})") from None


class OnnxSegmenter:
    """`Segmenter` over an ONNX model (YOLOv8-seg or per-pixel logits), onnxruntime on the CPU."""

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
        self.fixed_shape = isinstance(w, int) and isinstance(h, int)
        #: (w, h) px the frame is letterboxed into: a fixed-shape model's input, else `input_size` or the export size
        self.input_size: tuple[int, int] = (w, h) if self.fixed_shape else self._dynamic_size(path, config)
        outputs = self.session.get_outputs()
        self.layout = self._layout(path, [o.shape for o in outputs])

    def _dynamic_size(self, path: Path, config: OnnxSegmenterConfig) -> tuple[int, int]:
        """(w, h) px a dynamic-shape model runs at: `input_size` when set, else the `imgsz` the
        Ultralytics exporter writes into the model's metadata ('640' or '[h, w]'), else 640."""
        if config.input_size:
            return config.input_size, config.input_size
        text = self.session.get_modelmeta().custom_metadata_map.get("imgsz")
        if text is None:
            return DEFAULT_INPUT_SIDE_PX, DEFAULT_INPUT_SIDE_PX
        size = _export_size(text)
        if size is None:
            raise OnnxSegmenterError(
                f"onnx:{path}: metadata imgsz = {text!r} is not an input size (expected 640 or [h, w] px up to "
                f"{MAX_INPUT_SIDE_PX}); set segmenter.input_size"
            )
        return size

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
        box = _Letterbox.fit(width, height, self.input_size, None if self.fixed_shape else self.config.stride)
        tensor = box.to_input(left).astype(np.float32).transpose(2, 0, 1)[None] / 255.0
        return np.ascontiguousarray(tensor), box

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
