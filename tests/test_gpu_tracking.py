"""Tracking's execution providers: onnxruntime's CUDA one where onnxruntime-gpu is installed,
the CPU one otherwise or when forced; the choice is tested with the available providers given
as an argument, the CUDA run itself only on CUDA (marked ``gpu``)."""

import numpy as np
import pytest

from avatar_core.track.models import ModelFetchError, model_path
from avatar_core.track.onnx_model import (
    CPU_EP,
    CUDA_EP,
    DEVICE_ENV,
    OnnxModel,
    choose_providers,
    resolve_providers,
)

ort = pytest.importorskip("onnxruntime")
GPU_BUILD = [CUDA_EP, CPU_EP]
CPU_BUILD = ["AzureExecutionProvider", CPU_EP]


@pytest.mark.parametrize(("available", "device", "want"), [
    (GPU_BUILD, "auto", [CUDA_EP, CPU_EP]),
    (GPU_BUILD, "cuda", [CUDA_EP, CPU_EP]),
    (GPU_BUILD, "cpu", [CPU_EP]),
    (CPU_BUILD, "auto", [CPU_EP]),
    (CPU_BUILD, "cpu", [CPU_EP]),
])
def test_providers_from_what_onnxruntime_offers(available, device, want):
    assert choose_providers(available, device) == want


def test_cuda_asked_without_the_gpu_build_is_a_clear_error():
    with pytest.raises(ValueError, match="install onnxruntime-gpu"):
        choose_providers(CPU_BUILD, "cuda")
    with pytest.raises(ValueError, match="one of"):
        choose_providers(GPU_BUILD, "tpu")


def test_the_environment_sets_the_default(monkeypatch):
    monkeypatch.setenv(DEVICE_ENV, "cpu")
    assert resolve_providers(None) == [CPU_EP]
    monkeypatch.setenv(DEVICE_ENV, "bogus")
    with pytest.raises(ValueError, match="tracking device"):
        resolve_providers(None)
    monkeypatch.delenv(DEVICE_ENV)
    want = [CUDA_EP, CPU_EP] if CUDA_EP in ort.get_available_providers() else [CPU_EP]
    assert resolve_providers(None) == want
    assert resolve_providers(["X", CPU_EP]) == ["X", CPU_EP]  # a list goes as given


@pytest.fixture(scope="module")
def iris_model():
    try:
        return model_path("iris_landmark")
    except ModelFetchError as exc:
        pytest.skip(f"tracking models not converted here: {exc}")


def test_the_model_reports_its_provider(iris_model):
    model = OnnxModel("iris_landmark", providers="cpu", threads=1)
    assert model.providers == [CPU_EP]
    if CUDA_EP not in ort.get_available_providers():
        assert OnnxModel("iris_landmark", threads=1).providers == [CPU_EP]  # auto: the CPU
        with pytest.raises(ValueError, match="onnxruntime-gpu"):
            OnnxModel("iris_landmark", providers="cuda")


@pytest.mark.gpu
def test_cuda_provider_runs_and_agrees_with_the_cpu(iris_model):  # pragma: no cover
    if CUDA_EP not in ort.get_available_providers():
        pytest.skip("onnxruntime-gpu not installed (the cuda extra)")
    cpu = OnnxModel("iris_landmark", providers="cpu")
    gpu = OnnxModel("iris_landmark", providers="cuda")
    assert gpu.providers[0] == CUDA_EP
    w, h = cpu.input_size
    x = np.random.default_rng(0).random((1, h, w, 3), dtype=np.float32)
    for a, b in zip(cpu(x), gpu(x), strict=True):
        assert np.allclose(a, b, atol=1e-2, rtol=1e-2)
