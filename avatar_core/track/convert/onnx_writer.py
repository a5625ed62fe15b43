"""The op-mapping layer: a parsed TFLite graph (`tflite_graph.Graph`) -> an ONNX model.

Layout strategy
---------------
TFLite computes in NHWC; ONNX's convolution, pooling, resize and depth-to-space operators are
NCHW. The converter keeps every rank-4 activation in NCHW inside the graph and records, per
tensor, which physical layout its ONNX value has. Each op asks for its inputs in the layout it
needs; a ``Transpose`` is inserted only where the physical layout differs (and is reused), which
in practice means one at the graph input, one before each output, and one at each RESHAPE of an
image-shaped tensor (TFLite's reshape order is NHWC, so the data must be NHWC when it is
flattened). Constants never go through a layout pass at run time: kernels, PReLU alphas,
padding tables, broadcast operands and axes are rewritten to NCHW here, at conversion time, as
numpy arrays. That is the point of the design: tflite2onnx's separate layout-propagation pass
trips over PReLU alphas that arrive through a float16 DEQUANTIZE; here the DEQUANTIZE is already
folded into a float32 constant by the parser, and a constant alpha is simply broadcast to
(1, H, W, C) and transposed like any other array.

The graph keeps the TFLite model's input and output names, shapes (NHWC) and dtypes, so a user's
own ONNX model with the same signature can take its place.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from .tflite_graph import Graph, Op, Tensor, UnsupportedModel

OPSET = 17
NHWC_TO_NCHW = (0, 3, 1, 2)
NCHW_TO_NHWC = (0, 2, 3, 1)
PRELU_MODES = ("rewrite", "op")


def _same_pads(size: int, kernel: int, stride: int, dilation: int = 1) -> tuple[int, int, int]:
    """TF 'SAME': output size and (begin, end) padding; the odd pixel goes at the end."""
    out = -(-size // stride)
    eff = (kernel - 1) * dilation + 1
    total = max((out - 1) * stride + eff - size, 0)
    return out, total // 2, total - total // 2


class _Builder:
    def __init__(self, graph: Graph, prelu: str):
        if prelu not in PRELU_MODES:
            raise ValueError(f"prelu must be one of {PRELU_MODES}, not {prelu!r}")
        self.g = graph
        self.prelu = prelu
        self.nodes: list[onnx.NodeProto] = []
        self.inits: list[onnx.TensorProto] = []
        self.values: dict[int, tuple[str, str]] = {}  # tensor -> (onnx name, "nchw"|"nhwc")
        self.views: dict[tuple[int, str], str] = {}  # cached transposed views
        self._n = 0

    # ------------------------------------------------------------------ helpers
    def fresh(self, hint: str) -> str:
        self._n += 1
        return f"{hint}_{self._n}"

    def node(self, op_type: str, inputs: list[str], hint: str | None = None,
             out: str | None = None, **attrs) -> str:
        out = out or self.fresh(hint or op_type.lower())
        self.nodes.append(helper.make_node(op_type, inputs, [out], name=out, **attrs))
        return out

    def const(self, value: np.ndarray, hint: str = "const") -> str:
        name = self.fresh(hint)
        self.inits.append(numpy_helper.from_array(np.ascontiguousarray(value), name))
        return name

    def t(self, i: int) -> Tensor:
        return self.g.tensors[i]

    def data(self, i: int) -> np.ndarray:
        d = self.t(i).data
        if d is None:
            raise UnsupportedModel(f"tensor {self.t(i).name!r} must be constant")
        return d

    def is_const(self, i: int) -> bool:
        return self.t(i).data is not None

    def layout(self, i: int) -> str:
        if self.is_const(i):
            return "nhwc"
        return self.values[i][1]

    def get(self, i: int, layout: str) -> str:
        """The ONNX value of tensor i in the physical layout asked for ("nchw" or "nhwc")."""
        t = self.t(i)
        if t.data is not None:
            arr = t.data
            if arr.dtype == np.float16 or arr.dtype == np.float64:
                arr = arr.astype(np.float32)
            if layout == "nchw" and arr.ndim == 4:
                arr = arr.transpose(NHWC_TO_NCHW)
            key = (i, layout)
            if key not in self.views:
                self.views[key] = self.const(arr, f"w{i}")
            return self.views[key]
        name, have = self.values[i]
        if have == layout or len(t.shape) != 4:
            return name
        key = (i, layout)
        if key not in self.views:
            perm = NHWC_TO_NCHW if layout == "nchw" else NCHW_TO_NHWC
            self.views[key] = self.node("Transpose", [name], f"{layout}{i}", perm=list(perm))
        return self.views[key]

    def broadcast_const(self, i: int, rank: int, layout: str) -> str:
        """A constant operand broadcast against a rank-`rank` NHWC tensor, in `layout`."""
        arr = self.data(i).astype(np.float32)
        arr = arr.reshape((1,) * (rank - arr.ndim) + arr.shape)
        if layout == "nchw" and rank == 4:
            arr = arr.transpose(NHWC_TO_NCHW)
        return self.const(arr, f"w{i}")

    def put(self, op: Op, name: str, layout: str, k: int = 0) -> None:
        self.values[op.outputs[k]] = (name, layout if len(self.t(op.outputs[k]).shape) == 4
                                      else "nhwc")

    def activation(self, x: str, code: int) -> str:
        if code == 0:
            return x
        if code == 1:
            return self.node("Relu", [x])
        if code == 2:
            return self.clip(x, -1.0, 1.0)
        if code == 3:
            return self.clip(x, 0.0, 6.0)
        if code == 4:
            return self.node("Tanh", [x])
        raise UnsupportedModel(f"fused activation {code}")

    def clip(self, x: str, lo: float, hi: float) -> str:
        return self.node("Clip", [x, self.scalar(lo), self.scalar(hi)])

    def scalar(self, v: float) -> str:
        key = (-1, f"scalar{v}")
        if key not in self.views:
            self.views[key] = self.const(np.array(v, np.float32), "scalar")
        return self.views[key]

    def pool_pads(self, op: Op, kh: int, kw: int, sh: int, sw: int,
                  dh: int = 1, dw: int = 1) -> list[int]:
        _, h, w, _ = self.t(op.inputs[0]).shape
        if op.options.get("Padding", 0) == 1:  # VALID
            return [0, 0, 0, 0]
        _, ht, hb = _same_pads(h, kh, sh, dh)
        _, wl, wr = _same_pads(w, kw, sw, dw)
        return [ht, wl, hb, wr]

    # ------------------------------------------------------------------ ops
    def conv(self, op: Op) -> None:
        o = op.options
        w = self.data(op.inputs[1]).astype(np.float32)  # OHWI
        x = self.get(op.inputs[0], "nchw")
        sh, sw = o["StrideH"], o["StrideW"]
        dh, dw = o.get("DilationHFactor", 1), o.get("DilationWFactor", 1)
        attrs = dict(strides=[sh, sw], dilations=[dh, dw])
        if op.kind == "DEPTHWISE_CONV_2D":
            cin = self.t(op.inputs[0]).shape[3]
            w = w.transpose(3, 0, 1, 2)  # (1, H, W, C*M) -> (C*M, 1, H, W)
            attrs["group"] = cin
        else:
            w = w.transpose(0, 3, 1, 2)  # OHWI -> OIHW
        kh, kw = w.shape[2], w.shape[3]
        attrs["pads"] = self.pool_pads(op, kh, kw, sh, sw, dh, dw)
        attrs["kernel_shape"] = [kh, kw]
        ins = [x, self.const(w, f"w{op.inputs[1]}")]
        if len(op.inputs) > 2 and op.inputs[2] >= 0:
            ins.append(self.get(op.inputs[2], "nhwc"))
        y = self.node("Conv", ins, **attrs)
        self.put(op, self.activation(y, o.get("FusedActivationFunction", 0)), "nchw")

    def transpose_conv_bias(self, op: Op) -> None:
        # MediaPipe's custom op: custom options are TfLiteTransposeConvParams
        # (int32 padding [1 SAME, 2 VALID], int32 stride_width, int32 stride_height).
        if len(op.custom_options) < 12:
            raise UnsupportedModel("Convolution2DTransposeBias without its options")
        _, sw, sh = struct.unpack("<iii", op.custom_options[:12])
        w = self.data(op.inputs[1]).astype(np.float32)  # (O, H, W, I)
        kh, kw = w.shape[1], w.shape[2]
        _, ih, iw, _ = self.t(op.inputs[0]).shape
        _, oh, ow, _ = self.t(op.outputs[0]).shape
        th, tw = (ih - 1) * sh + kh - oh, (iw - 1) * sw + kw - ow
        if th < 0 or tw < 0:
            raise UnsupportedModel("Convolution2DTransposeBias with output padding")
        ins = [self.get(op.inputs[0], "nchw"), self.const(w.transpose(3, 0, 1, 2), "wt")]
        if len(op.inputs) > 2 and op.inputs[2] >= 0:
            ins.append(self.get(op.inputs[2], "nhwc"))
        y = self.node("ConvTranspose", ins, strides=[sh, sw], kernel_shape=[kh, kw],
                      pads=[th // 2, tw // 2, th - th // 2, tw - tw // 2])
        self.put(op, y, "nchw")

    def pool(self, op: Op) -> None:
        o = op.options
        kh, kw, sh, sw = o["FilterHeight"], o["FilterWidth"], o["StrideH"], o["StrideW"]
        # TF's SAME average pool divides by the number of valid pixels: count_include_pad=0.
        y = self.node("MaxPool" if op.kind == "MAX_POOL_2D" else "AveragePool",
                      [self.get(op.inputs[0], "nchw")], kernel_shape=[kh, kw],
                      strides=[sh, sw], pads=self.pool_pads(op, kh, kw, sh, sw))
        self.put(op, self.activation(y, o.get("FusedActivationFunction", 0)), "nchw")

    def binary(self, op: Op) -> None:
        a, b = op.inputs[:2]
        rank = len(self.t(op.outputs[0]).shape)
        acts = [i for i in (a, b) if not self.is_const(i)]
        layout = "nchw" if rank == 4 and any(
            self.layout(i) == "nchw" for i in acts) else "nhwc"
        names = []
        for i in (a, b):
            if self.is_const(i):
                names.append(self.broadcast_const(i, rank, layout))
            elif len(self.t(i).shape) == rank:
                names.append(self.get(i, layout))
            elif layout == "nhwc":
                names.append(self.get(i, "nhwc"))  # numpy broadcasting from the right
            else:
                raise UnsupportedModel(f"{op.kind} broadcasting a rank-{len(self.t(i).shape)} "
                                       "activation against an image")
        kind = {"ADD": "Add", "MUL": "Mul", "SUB": "Sub", "DIV": "Div"}[op.kind]
        y = self.node(kind, names)
        self.put(op, self.activation(y, op.options.get("FusedActivationFunction", 0)), layout)

    def unary(self, op: Op) -> None:
        i = op.inputs[0]
        layout = self.layout(i)
        x = self.get(i, layout)
        if op.kind == "RELU":
            y = self.node("Relu", [x])
        elif op.kind == "RELU6":
            y = self.clip(x, 0.0, 6.0)
        elif op.kind == "RELU_N1_TO_1":
            y = self.clip(x, -1.0, 1.0)
        elif op.kind == "LOGISTIC":
            y = self.node("Sigmoid", [x])
        elif op.kind == "TANH":
            y = self.node("Tanh", [x])
        elif op.kind == "HARD_SWISH":
            y = self.node("HardSwish", [x])
        else:
            raise AssertionError(op.kind)
        self.put(op, y, layout)

    def prelu(self, op: Op) -> None:
        i = op.inputs[0]
        rank = len(self.t(i).shape)
        layout = self.layout(i) if rank == 4 else "nhwc"
        x = self.get(i, layout)
        alpha = self.broadcast_const(op.inputs[1], rank, layout)
        if self.prelu == "op":
            y = self.node("PRelu", [x, alpha])
        else:  # Relu(x) + alpha * Min(x, 0): two cheap element-wise passes that ORT fuses well
            neg = self.node("Mul", [alpha, self.node("Min", [x, self.scalar(0.0)])])
            y = self.node("Add", [self.node("Relu", [x]), neg])
        self.put(op, y, layout)

    def pad(self, op: Op) -> None:
        i = op.inputs[0]
        p = self.data(op.inputs[1]).astype(np.int64).reshape(-1, 2)
        layout = self.layout(i) if len(p) == 4 else "nhwc"
        if layout == "nchw":
            p = p[list(NHWC_TO_NCHW)]
        ins = [self.get(i, layout), self.const(np.concatenate([p[:, 0], p[:, 1]]), "pads")]
        if op.kind == "PADV2" and len(op.inputs) > 2:
            ins.append(self.get(op.inputs[2], "nhwc"))
        self.put(op, self.node("Pad", ins, mode="constant"), layout)

    def reshape(self, op: Op) -> None:
        shape = np.asarray(self.t(op.outputs[0]).shape, np.int64)
        y = self.node("Reshape", [self.get(op.inputs[0], "nhwc"), self.const(shape, "shape")])
        self.put(op, y, "nhwc")

    def concat(self, op: Op) -> None:
        rank = len(self.t(op.outputs[0]).shape)
        axis = op.options.get("Axis", 0) % rank
        layout = "nchw" if rank == 4 and any(
            not self.is_const(i) and self.layout(i) == "nchw" for i in op.inputs) else "nhwc"
        if layout == "nchw":
            axis = NHWC_TO_NCHW.index(axis)
        y = self.node("Concat", [self.get(i, layout) for i in op.inputs], axis=axis)
        self.put(op, self.activation(y, op.options.get("FusedActivationFunction", 0)), layout)

    def mean(self, op: Op) -> None:
        i = op.inputs[0]
        rank = len(self.t(i).shape)
        axes = sorted(int(a) % rank for a in np.atleast_1d(self.data(op.inputs[1])))
        keep = bool(op.options.get("KeepDims", False))
        layout = self.layout(i) if rank == 4 else "nhwc"
        if layout == "nchw" and not keep:
            kept = [d for d in range(4) if d not in axes]
            if [d for d in NHWC_TO_NCHW if d in kept] != kept:
                layout = "nhwc"  # the remaining dimensions would come out in another order
        if layout == "nchw":
            axes = sorted(NHWC_TO_NCHW.index(a) for a in axes)
        y = self.node("ReduceMean", [self.get(i, layout)], axes=axes, keepdims=int(keep))
        self.put(op, y, layout)

    def fully_connected(self, op: Op) -> None:
        o = op.options
        w = self.data(op.inputs[1]).astype(np.float32)  # (out, in)
        x = self.get(op.inputs[0], "nhwc")
        if len(self.t(op.inputs[0]).shape) != 2 or self.t(op.inputs[0]).shape[1] != w.shape[1]:
            x = self.node("Reshape", [x, self.const(np.array([-1, w.shape[1]], np.int64))])
        ins = [x, self.const(w, f"w{op.inputs[1]}")]
        if len(op.inputs) > 2 and op.inputs[2] >= 0:
            ins.append(self.get(op.inputs[2], "nhwc"))
        y = self.node("Gemm", ins, transB=1)
        y = self.activation(y, o.get("FusedActivationFunction", 0))
        out_shape = self.t(op.outputs[0]).shape
        if len(out_shape) != 2:
            y = self.node("Reshape", [y, self.const(np.asarray(out_shape, np.int64))])
        self.put(op, y, "nhwc")

    def resize_bilinear(self, op: Op) -> None:
        o = op.options
        if o.get("AlignCorners"):
            mode = "align_corners"
        elif o.get("HalfPixelCenters"):
            mode = "half_pixel"  # in = (out + 0.5) / scale - 0.5, edges clamped (as TF)
        else:
            mode = "asymmetric"
        n, h, w, c = self.t(op.outputs[0]).shape
        y = self.node("Resize", [self.get(op.inputs[0], "nchw"), "", "",
                                 self.const(np.array([n, c, h, w], np.int64), "sizes")],
                      mode="linear", coordinate_transformation_mode=mode)
        self.put(op, y, "nchw")

    def depth_to_space(self, op: Op) -> None:
        # TF's DepthToSpace reads channel (i * bs + j) * C_out + c: ONNX's "DCR" mode.
        y = self.node("DepthToSpace", [self.get(op.inputs[0], "nchw")],
                      blocksize=op.options["BlockSize"], mode="DCR")
        self.put(op, y, "nchw")

    def dequantize(self, op: Op) -> None:  # float16 activation -> float32 (no constant input)
        i = op.inputs[0]
        if self.t(i).dtype != np.float16:
            raise UnsupportedModel(f"DEQUANTIZE of a non-constant {self.t(i).dtype} tensor")
        layout = self.layout(i)
        self.put(op, self.node("Cast", [self.get(i, layout)], to=TensorProto.FLOAT), layout)

    HANDLERS: dict[str, Callable[[_Builder, Op], None]] = {
        "CONV_2D": conv, "DEPTHWISE_CONV_2D": conv,
        "CUSTOM:Convolution2DTransposeBias": transpose_conv_bias,
        "MAX_POOL_2D": pool, "AVERAGE_POOL_2D": pool,
        "ADD": binary, "MUL": binary, "SUB": binary, "DIV": binary,
        "RELU": unary, "RELU6": unary, "RELU_N1_TO_1": unary, "LOGISTIC": unary,
        "TANH": unary, "HARD_SWISH": unary,
        "PRELU": prelu, "PAD": pad, "PADV2": pad, "RESHAPE": reshape,
        "CONCATENATION": concat, "MEAN": mean, "FULLY_CONNECTED": fully_connected,
        "RESIZE_BILINEAR": resize_bilinear, "DEPTH_TO_SPACE": depth_to_space,
        "DEQUANTIZE": dequantize,
    }

    def build(self, name: str) -> onnx.ModelProto:
        missing = sorted({op.kind for op in self.g.ops if op.kind not in self.HANDLERS})
        if missing:
            raise UnsupportedModel(f"unsupported TFLite ops: {', '.join(missing)}")
        inputs, outputs = [], []
        for i in self.g.inputs:
            t = self.t(i)
            if t.dtype != np.float32:
                raise UnsupportedModel(f"input {t.name!r} is {t.dtype}, not float32")
            self.values[i] = (t.name, "nhwc")
            inputs.append(helper.make_tensor_value_info(t.name, TensorProto.FLOAT, list(t.shape)))
        for op in self.g.ops:
            self.HANDLERS[op.kind](self, op)
        for i in self.g.outputs:
            t = self.t(i)
            self.node("Identity", [self.get(i, "nhwc")], out=t.name)
            outputs.append(helper.make_tensor_value_info(t.name, TensorProto.FLOAT,
                                                         list(t.shape)))
        graph = helper.make_graph(self.nodes, name, inputs, outputs, initializer=self.inits)
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                                  producer_name="telesplat.track.convert")
        model.ir_version = 8  # readable by onnxruntime >= 1.14
        onnx.checker.check_model(model, full_check=True)
        return model


def to_onnx(graph: Graph, name: str = "model", prelu: str = "rewrite") -> onnx.ModelProto:
    """Write a parsed TFLite graph as a checked ONNX model (opset 17, float32, NHWC I/O)."""
    return _Builder(graph, prelu).build(name)
