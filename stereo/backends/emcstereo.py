"""EMCStereo inference backend: numpy RGB pair → normalised, padded tensors → network → un-padded maps.

Precision: fp16/bf16 run under CUDA autocast only; asking for them on the CPU raises
BackendConfigError (CPU autocast would change numerics without a speed-up we have measured).
"""

from __future__ import annotations

import time
from contextlib import nullcontext

import numpy as np
import torch

from stereo.backends.base import (
    MAX_DISP_STEP,
    PRECISIONS,
    BackendConfigError,
    StereoResult,
    is_valid_max_disp,
    sanitize_dense_output,
    stage_timings_ms,
    validate_pair,
)
from stereo.backends.roi import crop_replicate, validate_window
from stereo.model import EMCStereo
from stereo.padding import compute_padding, pad_image, unpad

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
NETWORK_RANGE_STEP = 16  # compute_roi's search ranges: what the hourglass accepts at any size
_AUTOCAST_DTYPES = {"fp16": torch.float16, "bf16": torch.bfloat16}


def resolve_device(device: str | torch.device) -> torch.device:
    """The torch device for a name like "cpu", "cuda" or "cuda:1"; BackendConfigError when unusable here."""
    try:
        resolved = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise BackendConfigError(f"device {device!r} is not a torch device name (try 'cpu' or 'cuda')") from exc
    if resolved.type == "cuda" and not torch.cuda.is_available():
        raise BackendConfigError(f"device {device!r} requested but CUDA is not available on this machine; use 'cpu'")
    if resolved.type not in ("cpu", "cuda"):
        raise BackendConfigError(f"device {device!r} is not supported; use 'cpu' or 'cuda[:N]'")
    return resolved


def normalize_images(images: np.ndarray, device: torch.device) -> torch.Tensor:
    """RGB uint8 `(N, H, W, 3)` → ImageNet-normalised float32 `(N, 3, H, W)` on `device`."""
    tensor = torch.from_numpy(np.ascontiguousarray(images)).to(device).permute(0, 3, 1, 2).float().div_(255.0)
    mean = torch.tensor(IMAGENET_MEAN, device=device).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD, device=device).view(1, 3, 1, 1)
    return (tensor - mean) / std


class EMCStereoBackend:
    """Runs an EMCStereo model on rectified RGB pairs of any size (≥ 1×1); confidence from the soft-argmin."""

    name = "emcstereo"

    def __init__(
        self,
        model: EMCStereo,
        *,
        max_disp: int | None = None,
        device: str | torch.device = "cpu",
        precision: str = "fp32",
    ) -> None:
        max_disp = model.max_disp if max_disp is None else max_disp
        if not is_valid_max_disp(max_disp) or max_disp > model.max_disp:
            raise BackendConfigError(
                f"emcstereo max_disp must be a multiple of {MAX_DISP_STEP} in (0, {model.max_disp}] "
                f"(the model's trained range), got {max_disp!r}"
            )
        if precision not in PRECISIONS:
            raise BackendConfigError(f"precision {precision!r} is not one of {PRECISIONS}")
        self.device = resolve_device(device)
        if precision != "fp32" and self.device.type != "cuda":
            raise BackendConfigError(
                f"precision {precision!r} needs a CUDA device (autocast is CUDA-only here); "
                f"use precision='fp32' on {self.device}"
            )
        self.max_disparity = max_disp
        self.precision = precision
        self.model = model.to(self.device).eval()

    def _autocast(self) -> torch.autocast | nullcontext[None]:
        """Mixed-precision context for fp16/bf16 on CUDA, nothing for fp32."""
        if self.precision == "fp32":
            return nullcontext()
        return torch.autocast(device_type="cuda", dtype=_AUTOCAST_DTYPES[self.precision])

    def _now(self) -> float:
        """perf_counter after the device's queued work has finished (so stage timings are real)."""
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        return time.perf_counter()

    def compute(self, left: np.ndarray, right: np.ndarray) -> StereoResult:
        """Disparity (float32 px, dense; non-finite outputs become 0) and confidence in [0, 1] of a rectified pair."""
        validate_pair(left, right)
        disparity, confidence, timing = self._run(left, right, self.max_disparity)
        return StereoResult(disparity, confidence, timing, self.name, self.max_disparity)

    def compute_roi(
        self, left: np.ndarray, right: np.ndarray, roi: tuple[int, int, int, int], d_min: int, d_range: int
    ) -> StereoResult:
        """Disparity of the left-image box `roi = (x0, y0, x1, y1)` searched over `[d_min, d_min + d_range)`.

        The network searches S = 16·⌈d_range/16⌉ disparities (its hourglass halves the ¼-resolution
        disparity axis twice, so other multiples of 4 fail inside it; S ≤ the model's range). It sees
        the left box extended S columns to the left (so the box's pixels have their whole search
        inside the input) and the right image's same rows and columns shifted left by `d_min` (so
        its disparity 0 is absolute `d_min`); out-of-frame columns replicate the border. `d_min` is
        added back, estimates at or beyond `d_min + d_range` are invalid (outside the window asked
        for), and the extension is dropped. Returns `(y1 − y0)×(x1 − x0)` maps, absolute px, 0 (and
        confidence 0) where invalid, `max_disparity = d_min + d_range`.
        """
        (x0, y0, x1, y1), d_min, d_range = validate_window(left, right, roi, d_min, d_range)
        search = -(-d_range // NETWORK_RANGE_STEP) * NETWORK_RANGE_STEP
        if search > self.model.max_disp:
            raise BackendConfigError(
                f"emcstereo d_range {d_range} needs a {search}-disparity search (steps of {NETWORK_RANGE_STEP}), "
                f"beyond the model's trained range (0, {self.model.max_disp}]"
            )
        rows = (y0, y1)
        left_crop = crop_replicate(left, rows, (x0 - search, x1))
        right_crop = crop_replicate(right, rows, (x0 - search - d_min, x1 - d_min))
        disparity, confidence, timing = self._run(left_crop, right_crop, search)
        disparity, confidence = disparity[:, search:], confidence[:, search:]
        valid = (confidence > 0) & (disparity < d_range)
        disparity = np.where(valid, disparity + np.float32(d_min), np.float32(0.0))
        confidence = np.where(valid, confidence, np.float32(0.0))
        return StereoResult(disparity, confidence, timing, self.name, d_min + d_range)

    def _run(
        self, left: np.ndarray, right: np.ndarray, max_disp: int
    ) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
        """The network on one validated pair: (disparity, confidence) float32 `H×W` and stage timings in ms."""
        height, width = left.shape[:2]
        padding = compute_padding(height, width)
        start = self._now()
        with torch.inference_mode():
            images = pad_image(normalize_images(np.stack([left, right]), self.device), padding)
            prepared = self._now()
            with self._autocast():
                disparity, confidence = self.model.infer(images[:1], images[1:], max_disp=max_disp)
            inferred = self._now()
            disparity = unpad(disparity[0].float(), padding).cpu().numpy()
            confidence = unpad(confidence[0].float(), padding).cpu().numpy()
        disparity, confidence = sanitize_dense_output(disparity, confidence)
        end = self._now()
        return (
            disparity,
            confidence,
            stage_timings_ms(start, [("preprocess", prepared), ("network", inferred), ("postprocess", end)]),
        )
