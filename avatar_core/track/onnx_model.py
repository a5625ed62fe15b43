"""The converted models on ONNX Runtime (one inference session each), with a call counter.

Execution providers: a list of names, or a device, ``"auto"`` (the default), ``"cpu"`` or
``"cuda"``. auto takes onnxruntime's CUDA execution provider where it is installed
(``onnxruntime-gpu``, the ``cuda`` extra) and the CPU one otherwise; ``TELESPLAT_TRACK_DEVICE``
sets the default for every command and the server (``cpu`` forces the CPU on a GPU machine).
``OnnxModel.providers`` is what the session actually runs on (onnxruntime falls back to the
CPU by itself when the CUDA provider cannot load).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from .models import model_path

log = logging.getLogger(__name__)

DEVICES = ("auto", "cpu", "cuda")
DEVICE_ENV = "TELESPLAT_TRACK_DEVICE"
CPU_EP, CUDA_EP = "CPUExecutionProvider", "CUDAExecutionProvider"

# models= for the pipelines: None (the default cache), a cache folder, or name -> ONNX file
# (each checked against the converted model's signature).
ModelSource = str | Path | Mapping[str, str | Path] | None


def resolve_model(name: str, models: ModelSource) -> Path:
    if isinstance(models, Mapping):
        override = models.get(name)
        return model_path(name, override=override) if override else model_path(name)
    return model_path(name, cache=models)


def choose_providers(available: Sequence[str], device: str = "auto") -> list[str]:
    """Execution providers for ``device`` given onnxruntime's ``available`` ones: auto: CUDA
    (then CPU) where listed, else CPU; cpu: CPU; cuda: CUDA then CPU, an error where absent."""
    if device not in DEVICES:
        raise ValueError(f"tracking device must be one of {DEVICES}, got {device!r}")
    cuda = CUDA_EP in available
    if device == "cuda" and not cuda:
        raise ValueError(f"tracking device 'cuda' asked but onnxruntime offers only "
                         f"{list(available)}: install onnxruntime-gpu (the cuda extra) in "
                         f"place of onnxruntime")
    return [CUDA_EP, CPU_EP] if cuda and device != "cpu" else [CPU_EP]


def resolve_providers(providers: Sequence[str] | str | None) -> list[str]:
    """A providers argument as onnxruntime takes it: a list as given, a device (or None:
    ``TELESPLAT_TRACK_DEVICE``, else auto) through :func:`choose_providers`."""
    if providers is not None and not isinstance(providers, str):
        return list(providers)
    import onnxruntime as ort

    device = providers or os.environ.get(DEVICE_ENV, "").strip().lower() or "auto"
    return choose_providers(ort.get_available_providers(), device)


class OnnxModel:
    """One converted model on onnxruntime. ``providers``: a device ("auto", "cpu", "cuda";
    None: ``TELESPLAT_TRACK_DEVICE`` or auto) or a list of provider names, e.g.
    ["TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"]."""

    def __init__(self, name: str, models: ModelSource = None,
                 providers: Sequence[str] | str | None = None, threads: int | None = None):
        import onnxruntime as ort

        self.name = name
        self.path = resolve_model(name, models)
        options = ort.SessionOptions()
        if threads:
            options.intra_op_num_threads = threads
            options.inter_op_num_threads = 1
            # No busy-waiting between ops: on a shared, loaded machine spinning threads
            # fight the other stages (and processes) for the cores.
            options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        self.inference = ort.InferenceSession(str(self.path), options,
                                              providers=resolve_providers(providers))
        self.providers: list[str] = self.inference.get_providers()  # what it runs on
        log.info("%s on %s", name, self.providers[0])
        inp = self.inference.get_inputs()[0]
        self.input_name = inp.name
        self.input_size = (int(inp.shape[2]), int(inp.shape[1]))  # (w, h) of NHWC
        self.calls = 0

    def __call__(self, x: np.ndarray) -> list[np.ndarray]:
        self.calls += 1
        return self.inference.run(None, {self.input_name: x})
