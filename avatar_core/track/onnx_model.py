"""The converted models on ONNX Runtime (one inference session each), with a call counter."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from .models import model_path

# models= for the pipelines: None (the default cache), a cache folder, or name -> ONNX file
# (each checked against the converted model's signature).
ModelSource = str | Path | Mapping[str, str | Path] | None


def resolve_model(name: str, models: ModelSource) -> Path:
    if isinstance(models, Mapping):
        override = models.get(name)
        return model_path(name, override=override) if override else model_path(name)
    return model_path(name, cache=models)


class OnnxModel:
    """One converted model on onnxruntime. `providers` defaults to the CPU; a GPU server can
    pass e.g. ["TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"]."""

    def __init__(self, name: str, models: ModelSource = None,
                 providers: Sequence | None = None, threads: int | None = None):
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
                                              providers=list(providers or
                                                             ["CPUExecutionProvider"]))
        inp = self.inference.get_inputs()[0]
        self.input_name = inp.name
        self.input_size = (int(inp.shape[2]), int(inp.shape[1]))  # (w, h) of NHWC
        self.calls = 0

    def __call__(self, x: np.ndarray) -> list[np.ndarray]:
        self.calls += 1
        return self.inference.run(None, {self.input_name: x})
