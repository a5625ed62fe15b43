"""The project's TFLite -> ONNX converter for the MediaPipe models.

Two layers: `tflite_graph` parses the flatbuffer with the `tflite` package and folds the weight
decoding (float16 DEQUANTIZE, DENSIFY of sparse weights) into float32 constants; `onnx_writer`
maps each op to ONNX, keeps activations NCHW inside the graph (constants are re-laid out at
conversion time), and validates the result with `onnx.checker`. Inputs and outputs keep the
TFLite names and NHWC shapes.
"""

from __future__ import annotations

from pathlib import Path

from .onnx_writer import PRELU_MODES, to_onnx
from .tflite_graph import Graph, UnsupportedModel, densify, load

__all__ = ["PRELU_MODES", "Graph", "UnsupportedModel", "convert", "densify", "load", "to_onnx"]


def convert(tflite_model: str | Path | bytes, out: str | Path | None = None, *,
            prelu: str = "rewrite", name: str | None = None):
    """Convert a .tflite model (path or bytes) to ONNX; write it to `out` when given.

    ``prelu="rewrite"`` writes PReLU as Relu(x) + alpha * Min(x, 0) (faster in onnxruntime on
    CPU, see docs/tracking.md); ``prelu="op"`` writes the PRelu operator.
    """
    import onnx

    if name is None:
        name = Path(tflite_model).stem if not isinstance(tflite_model, bytes | bytearray) \
            else "model"
    model = to_onnx(load(tflite_model), name=name, prelu=prelu)
    if out is not None:
        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_suffix(out.suffix + ".tmp")
        onnx.save(model, tmp)
        tmp.replace(out)
    return model
