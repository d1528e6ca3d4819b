"""An int8 copy of a trained `BranchNet` ONNX file, for companion computers where every millisecond counts.

Static quantization with onnxruntime's own tool (`onnxruntime.quantization.quantize_static`): weights
int8 per output channel, activations uint8 with ranges measured on `QUANTIZATION_SEEDS` frames (the
validation scenes: never trained on, and apart from the confidence calibration's), QDQ format so the
file stays a plain ONNX graph. On 2 AVX-512 cores one 640×360 frame takes 22 ms instead of 30, with the
same recall on the calibration scenes (sgbm 52.7 % against 53.5 %, exact disparity 72.1 % against 71.9 %).
The int8 model's confidence calibration is its own (`branchrange.learning.calibration.calibrate_model`): a
different model, measured again. Needs the `onnx` package (the training extra), not at run time.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from branchrange.core.segmentation.learned import verified_metadata
from branchrange.core.segmentation.network_input import network_input, padded_to_stride
from branchrange.learning.samples import cached_sample
from stereo.onnx_runtime import import_onnxruntime
from stereo.weights import sha256_of

#: scenes whose frames set the activation ranges (the validation seeds of the training config)
QUANTIZATION_SEEDS = (2801, 2821)


def int8_path(model: Path) -> Path:
    """Where the int8 copy of `model` goes: beside it, "_int8" before the suffix."""
    return model.with_name(f"{model.stem}_int8{model.suffix}")


def quantize_branchnet(
    model: Path,
    data_dir: Path,
    seeds: tuple[int, int] = QUANTIZATION_SEEDS,
    samples: Sequence[dict[str, np.ndarray]] = (),
    samples_from: str = "",
) -> dict[str, Any]:
    """Write the int8 copy of the fp32 ONNX `model` to `int8_path(model)` and its metadata JSON beside it
    (the source's model, width and classes, its SHA-256, what set the ranges, the new file's SHA-256); returns
    that metadata. The activation ranges come from the frames of scenes `seeds` [first, last) (from, or rendered
    into, `data_dir`) — or, when given, from `samples` (each with "left" and "disparity": a fine-tune's own
    labelled frames, the domain it will see), described by `samples_from`."""
    import_onnxruntime()  # its telemetry off before onnxruntime.quantization loads the library
    import onnxruntime.quantization as quantization
    from onnxruntime.quantization.shape_inference import quant_pre_process

    source_meta = verified_metadata(model)  # the file quantized is the one its JSON describes
    out = int8_path(model)
    frames = samples or [cached_sample(data_dir, seed) for seed in range(*seeds)]
    inputs = [padded_to_stride(network_input(s["left"], s["disparity"]))[0][None] for s in frames]

    class Frames(quantization.CalibrationDataReader):  # type: ignore[misc]
        """The frames, one `{"image": (1, 5, H, W)}` feed at a time."""

        def __init__(self) -> None:
            self.feeds: Iterator[np.ndarray] = iter(inputs)

        def get_next(self) -> dict[str, np.ndarray] | None:
            feed = next(self.feeds, None)
            return None if feed is None else {"image": feed}

    prepared = out.with_name(f"{out.stem}.prepared.onnx")
    try:
        quant_pre_process(str(model), str(prepared))
        quantization.quantize_static(
            str(prepared),
            str(out),
            Frames(),
            quant_format=quantization.QuantFormat.QDQ,
            activation_type=quantization.QuantType.QUInt8,
            weight_type=quantization.QuantType.QInt8,
            per_channel=True,
        )
    finally:
        prepared.unlink(missing_ok=True)
    meta: dict[str, Any] = {
        **{k: source_meta[k] for k in ("model", "width", "classes") if k in source_meta},
        "onnx_sha256": sha256_of(out),
        "quantized_from": {"file": model.name, "onnx_sha256": sha256_of(model)},
        "quantization": {
            **({"frames": samples_from} if samples else {"seeds": list(seeds)}),
            "weights": "int8 per channel",
            "activations": "uint8",
            "format": "QDQ",
        },
    }
    out.with_suffix(".json").write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")
    return meta
