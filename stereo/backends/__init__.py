"""Stereo backends behind one interface: `make_backend("sgbm" | "emcstereo", ...)` → `StereoBackend`."""

from __future__ import annotations

import os
import warnings

from stereo.backends.base import (
    MAX_DISP_EXPECTED,
    PRECISIONS,
    BackendConfigError,
    StereoBackend,
    StereoInputError,
    StereoResult,
    check_max_disp,
    is_valid_max_disp,
    validate_pair,
)
from stereo.backends.sgbm import SGBMBackend

#: Every backend `make_backend` builds: the one list the config, the command line and the API offer.
BACKEND_NAMES: tuple[str, ...] = ("sgbm", "emcstereo", "onnx")
#: The backends that need `weights` (a checkpoint; an exported .onnx file for onnx).
WEIGHTED_BACKENDS: tuple[str, ...] = ("emcstereo", "onnx")


class UntrainedModelWarning(UserWarning):
    """The emcstereo backend was built without weights: its disparities are those of random parameters."""


def make_backend(
    name: str,
    *,
    weights: str | os.PathLike[str] | None = None,
    max_disp: int = 192,
    device: str = "cpu",
    precision: str = "fp32",
    verify_sha256: bool = True,
) -> StereoBackend:
    """Build a backend by name.

    `sgbm`: CPU only, no weights, fp32; `max_disp` a multiple of 16. `emcstereo`: loads `weights`
    with `stereo.checkpoints.load_model` (any supported layout); without weights it builds a
    randomly initialised full model and warns (UntrainedModelWarning). `max_disp` is the inference
    search range (multiple of 16, at most the model's trained range); fp16/bf16 need CUDA.
    `verify_sha256=False` loads emcstereo weights named as a registered release without checking them.
    """
    if name == "sgbm":
        for option, value, default in (
            ("weights", weights, None),
            ("device", device, "cpu"),
            ("precision", precision, "fp32"),
        ):
            if value != default:
                raise BackendConfigError(f"the sgbm backend takes no {option} other than {default!r}, got {value!r}")
        return SGBMBackend(max_disp)
    if name == "emcstereo":
        from stereo.backends.emcstereo import EMCStereoBackend, resolve_device
        from stereo.checkpoints import load_model
        from stereo.model import EMCStereo

        if weights is None:
            warnings.warn(
                "emcstereo backend built without weights: a randomly initialised model gives meaningless "
                "disparities (pass weights=PATH)",
                UntrainedModelWarning,
                stacklevel=2,
            )
            model = EMCStereo()
        else:
            model = load_model(weights, device=resolve_device(device), verify_sha256=verify_sha256)
        return EMCStereoBackend(model, max_disp=max_disp, device=device, precision=precision)
    if name == "onnx":  # an exported EMCStereo graph under ONNX Runtime (stereo/backends/onnx.py)
        from stereo.backends.onnx import make_onnx_backend

        return make_onnx_backend(weights, max_disp, device, precision)
    raise BackendConfigError(f"unknown stereo backend {name!r}; choose one of {BACKEND_NAMES}")


__all__ = [
    "BACKEND_NAMES",
    "MAX_DISP_EXPECTED",
    "PRECISIONS",
    "WEIGHTED_BACKENDS",
    "BackendConfigError",
    "SGBMBackend",
    "StereoBackend",
    "StereoInputError",
    "StereoResult",
    "UntrainedModelWarning",
    "check_max_disp",
    "is_valid_max_disp",
    "make_backend",
    "validate_pair",
]
