"""The learned segmenter on a GPU (`[segmenter.learned] device`): onnxruntime's CUDA or TensorRT provider when the
installed onnxruntime has it, a clear refusal when it has not — never a GPU model run on the CPU unnoticed — and
the same labels as on the CPU where a GPU is there."""

from __future__ import annotations

import numpy as np
import pytest

from branchrange.core.geometry import StereoGeometry
from branchrange.core.segmentation.learned import LearnedSegmenter, LearnedSegmenterConfig
from branchrange.core.segmentation.onnx_model import EXECUTION_PROVIDERS, OnnxSegmenterError, execution_providers
from stereo.onnx_runtime import import_onnxruntime

AVAILABLE = list(import_onnxruntime().get_available_providers())


def test_each_device_asks_for_its_own_provider_first_and_the_cpu_last():
    gpu = ["TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"]
    assert execution_providers("cpu", gpu) == ["CPUExecutionProvider"]
    assert execution_providers("cuda", gpu) == ["CUDAExecutionProvider", "CPUExecutionProvider"]
    assert execution_providers("tensorrt", gpu) == gpu
    assert execution_providers("tensorrt", ["CPUExecutionProvider", "TensorrtExecutionProvider"]) == [
        "TensorrtExecutionProvider",
        "CPUExecutionProvider",
    ]  # the CUDA provider a build lacks is left out, the order kept
    assert set(EXECUTION_PROVIDERS) == {"cpu", "cuda", "tensorrt"}


@pytest.mark.parametrize("device", ["cuda", "tensorrt"])
def test_a_gpu_device_without_its_provider_is_refused_with_the_fix(device):
    with pytest.raises(OnnxSegmenterError, match="install onnxruntime-gpu") as refused:
        execution_providers(device, ["CPUExecutionProvider"])
    assert EXECUTION_PROVIDERS[device][0] in str(refused.value) and 'device = "cpu"' in str(refused.value)


@pytest.mark.skipif("CUDAExecutionProvider" in AVAILABLE, reason="this onnxruntime has the CUDA provider")
def test_the_segmenter_asked_for_cuda_here_refuses_to_start():
    with pytest.raises(OnnxSegmenterError, match="CUDAExecutionProvider"):
        LearnedSegmenter(LearnedSegmenterConfig(device="cuda"))


def test_settings_refuse_an_unknown_device_and_int8_on_cuda():
    with pytest.raises(OnnxSegmenterError, match="segmenter.learned.device = 'gpu'"):
        LearnedSegmenterConfig(device="gpu")
    with pytest.raises(OnnxSegmenterError, match="not 'cuda'"):
        LearnedSegmenterConfig(device="cuda", precision="int8")
    assert LearnedSegmenterConfig(device="tensorrt", precision="int8").device == "tensorrt"


@pytest.mark.skipif("CUDAExecutionProvider" not in AVAILABLE, reason="needs onnxruntime-gpu with a CUDA device")
def test_on_cuda_the_segmenter_labels_a_frame_as_on_the_cpu():
    rng = np.random.default_rng(0)
    left = rng.integers(0, 255, (360, 640, 3), dtype=np.uint8)
    disparity = rng.uniform(5, 40, (360, 640)).astype(np.float32)
    geometry = StereoGeometry.centred(700.0, 0.063, 640, 360)
    on_cpu = LearnedSegmenter(LearnedSegmenterConfig()).segment(left, disparity, geometry)
    on_gpu = LearnedSegmenter(LearnedSegmenterConfig(device="cuda")).segment(left, disparity, geometry)
    assert np.mean(on_cpu.labels == on_gpu.labels) > 0.999  # fp32 on either: rounding may flip a border pixel
