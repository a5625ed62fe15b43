"""The parser layer: a .tflite flatbuffer -> tensors, constant buffers and operators.

Reads the model with the `tflite` package (the generated flatbuffer schema) and folds the
weight-decoding operators that a TFLite model carries for compression, so that the op-mapping
layer only sees float32 constants:

- ``DEQUANTIZE`` of a float16 constant becomes a float32 constant (int8/uint8 constants with a
  per-tensor or per-axis scale and zero point are dequantized the same way);
- ``DENSIFY`` of a sparse constant (TFLite's sparsity format: traversal order, block map and a
  dense / CSR metadata entry per traversed dimension) becomes the dense constant.

A ``DEQUANTIZE`` whose input is not constant stays an operator (a cast at run time).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

_DTYPES = {
    0: np.float32, 1: np.float16, 2: np.int32, 3: np.uint8, 4: np.int64, 6: np.bool_,
    7: np.int16, 9: np.int8, 10: np.float64,
}


class UnsupportedModel(ValueError):
    """The model uses something the converter does not cover (it names what)."""


@dataclass
class Tensor:
    index: int
    name: str
    shape: tuple[int, ...]
    dtype: Any
    data: np.ndarray | None = None  # constant value (float32 once folded), None for activations
    quant: dict | None = None  # scale / zero_point / axis, when the tensor is quantized
    sparsity: dict | None = None


@dataclass
class Op:
    kind: str  # builtin name ("CONV_2D") or "CUSTOM:<code>"
    inputs: list[int]  # tensor indices, -1 for an omitted optional input
    outputs: list[int]
    options: dict[str, Any] = field(default_factory=dict)
    custom_options: bytes = b""


@dataclass
class Graph:
    tensors: list[Tensor]
    ops: list[Op]
    inputs: list[int]
    outputs: list[int]
    folded: dict[str, int] = field(default_factory=dict)  # op kind -> how many were folded


def _enum_names(enum_cls: type) -> dict[int, str]:
    return {v: k for k, v in vars(enum_cls).items() if not k.startswith("_") and isinstance(v, int)}


def _read_table(table: Any) -> dict[str, Any]:
    """Every scalar / vector field of a flatbuffer options table, by its schema name."""
    out: dict[str, Any] = {}
    for name in dir(table):
        if name.startswith("_") or name.startswith("Init") or name.startswith("GetRootAs"):
            continue
        if name.endswith(("Length", "IsNone")) or "BufferHasIdentifier" in name:
            continue
        attr = getattr(table, name)
        if not callable(attr):
            continue
        try:
            value = attr()
        except TypeError:  # needs an index: the AsNumpy twin is read instead
            continue
        if name.endswith("AsNumpy"):
            name = name[: -len("AsNumpy")]
            value = np.asarray(value).tolist() if not isinstance(value, int) else []
        if isinstance(value, int | float | bool | list | bytes):
            out[name] = value
    return out


def _index_vector(metadata: Any, which: str) -> np.ndarray:
    import tflite

    kind = getattr(metadata, f"{which}Type")()
    table = getattr(metadata, which)()
    classes = {tflite.SparseIndexVector.Int32Vector: tflite.Int32Vector,
               tflite.SparseIndexVector.Uint16Vector: tflite.Uint16Vector,
               tflite.SparseIndexVector.Uint8Vector: tflite.Uint8Vector}
    if kind not in classes or table is None:
        raise UnsupportedModel(f"sparse index vector of type {kind}")
    vec = classes[kind]()
    vec.Init(table.Bytes, table.Pos)
    return np.asarray(vec.ValuesAsNumpy(), dtype=np.int64)


def _read_sparsity(sp: Any) -> dict:
    levels = []
    for k in range(sp.DimMetadataLength()):
        md = sp.DimMetadata(k)
        if md.Format() == 0:  # DENSE
            levels.append({"format": "dense", "size": int(md.DenseSize())})
        else:  # SPARSE_CSR
            levels.append({"format": "csr", "segments": _index_vector(md, "ArraySegments"),
                           "indices": _index_vector(md, "ArrayIndices")})
    return {
        "traversal_order": np.asarray(sp.TraversalOrderAsNumpy(), dtype=np.int64).tolist()
        if sp.TraversalOrderLength() else [],
        "block_map": np.asarray(sp.BlockMapAsNumpy(), dtype=np.int64).tolist()
        if sp.BlockMapLength() else [],
        "levels": levels,
    }


def densify(values: np.ndarray, shape: tuple[int, ...], sparsity: dict) -> np.ndarray:
    """TFLite's sparse format -> the dense array (tflite FormatConverter::SparseToDense).

    ``levels`` follow the traversal order: the first ``rank`` entries walk the (blocked) original
    dimensions, the rest walk the blocks' inner dimensions (``block_map`` says which original
    dimension each block dimension splits). A dense level enumerates ``size`` indices; a CSR
    level enumerates ``indices[segments[p]:segments[p + 1]]`` for its parent position ``p``.
    ``values`` are consumed in that depth-first order. Vectorized level by level.
    """
    rank = len(shape)
    levels = sparsity["levels"]
    order = sparsity["traversal_order"] or list(range(len(levels)))
    block_map = sparsity["block_map"]
    if len(order) != len(levels):
        raise UnsupportedModel("sparsity: traversal order and dim metadata disagree")
    idx = np.zeros((1, 0), dtype=np.int64)  # one row per partial path, one column per level
    parent = np.zeros(1, dtype=np.int64)  # position of each path within its level
    for level in levels:
        if level["format"] == "dense":
            n = level["size"]
            idx = np.concatenate([np.repeat(idx, n, axis=0),
                                  np.tile(np.arange(n), len(idx))[:, None]], axis=1)
            parent = (np.repeat(parent, n) * n + np.tile(np.arange(n), len(parent)))
        else:
            seg, ind = level["segments"], level["indices"]
            starts, stops = seg[parent], seg[parent + 1]
            counts = stops - starts
            rows = np.repeat(np.arange(len(idx)), counts)
            pos = (np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
                   + np.repeat(starts, counts))
            idx = np.concatenate([idx[rows], ind[pos][:, None]], axis=1)
            parent = pos
    if len(idx) != values.size:
        raise UnsupportedModel(f"sparsity: {len(idx)} positions for {values.size} values")
    # Block sizes: the dense size of the level that walks each block dimension.
    block_size = [0] * len(block_map)
    for pos_, dim in enumerate(order):
        if dim >= rank:
            block_size[dim - rank] = levels[pos_]["size"]
    orig = np.zeros((len(idx), rank), dtype=np.int64)
    for pos_ in range(rank):
        orig[:, order[pos_]] = idx[:, pos_]
    for pos_ in range(rank, len(order)):
        b = order[pos_] - rank
        d = block_map[b]
        orig[:, d] = orig[:, d] * block_size[b] + idx[:, pos_]
    dense = np.zeros(shape, dtype=values.dtype)
    dense[tuple(orig.T)] = values.reshape(-1)
    return dense


def _dequantize(t: Tensor) -> np.ndarray:
    assert t.data is not None
    if t.data.dtype == np.float16:
        return t.data.astype(np.float32)
    if t.quant is None:
        raise UnsupportedModel(f"DEQUANTIZE of {t.data.dtype} without quantization parameters")
    scale = np.asarray(t.quant["scale"], np.float32)
    zero = np.asarray(t.quant["zero_point"], np.float32)
    if scale.size > 1:  # per-axis
        shape = [1] * t.data.ndim
        shape[t.quant["axis"]] = -1
        scale, zero = scale.reshape(shape), zero.reshape(shape)
    return ((t.data.astype(np.float32) - zero) * scale).astype(np.float32)


def load(path: str | Path | bytes, fold: bool = True) -> Graph:
    """Parse the first subgraph of a .tflite model (path or bytes)."""
    import tflite

    buf = path if isinstance(path, bytes | bytearray) else Path(path).read_bytes()
    model = tflite.Model.GetRootAsModel(buf, 0)
    if model.SubgraphsLength() != 1:
        raise UnsupportedModel(f"{model.SubgraphsLength()} subgraphs (only one is supported)")
    g = model.Subgraphs(0)
    op_names = _enum_names(tflite.BuiltinOperator)
    option_names = _enum_names(tflite.BuiltinOptions)

    tensors = []
    for i in range(g.TensorsLength()):
        t = g.Tensors(i)
        if t.Type() not in _DTYPES:
            raise UnsupportedModel(f"tensor {t.Name().decode()!r} has TFLite type {t.Type()}")
        dtype = _DTYPES[t.Type()]
        shape = tuple(int(s) for s in t.ShapeAsNumpy()) if t.ShapeLength() else ()
        data = None
        b = model.Buffers(t.Buffer())
        if b is not None and b.DataLength():
            raw = b.DataAsNumpy().tobytes()
            data = np.frombuffer(raw, dtype=dtype).copy()
            if t.Sparsity() is None:
                data = data.reshape(shape)
        quant = None
        q = t.Quantization()
        if q is not None and q.ScaleLength():
            quant = {"scale": q.ScaleAsNumpy().tolist(),
                     "zero_point": q.ZeroPointAsNumpy().tolist() if q.ZeroPointLength() else [0],
                     "axis": int(q.QuantizedDimension())}
        sparsity = _read_sparsity(t.Sparsity()) if t.Sparsity() is not None else None
        tensors.append(Tensor(i, t.Name().decode(), shape, dtype, data, quant, sparsity))

    ops = []
    for i in range(g.OperatorsLength()):
        o = g.Operators(i)
        code = model.OperatorCodes(o.OpcodeIndex())
        builtin = max(code.BuiltinCode(), code.DeprecatedBuiltinCode())
        kind = op_names.get(builtin, str(builtin))
        if kind == "CUSTOM":
            kind = "CUSTOM:" + code.CustomCode().decode()
        options: dict[str, Any] = {}
        opt_type = o.BuiltinOptionsType()
        if opt_type:
            cls = getattr(tflite, option_names[opt_type])
            table = cls()
            raw = o.BuiltinOptions()
            table.Init(raw.Bytes, raw.Pos)
            options = _read_table(table)
        custom = o.CustomOptionsAsNumpy().tobytes() if o.CustomOptionsLength() else b""
        ops.append(Op(kind, [int(x) for x in o.InputsAsNumpy()] if o.InputsLength() else [],
                      [int(x) for x in o.OutputsAsNumpy()], options, custom))

    graph = Graph(tensors, ops, [int(x) for x in g.InputsAsNumpy()],
                  [int(x) for x in g.OutputsAsNumpy()])
    if fold:
        fold_weight_decoding(graph)
    return graph


def fold_weight_decoding(graph: Graph) -> None:
    """Replace DENSIFY / DEQUANTIZE of constants by their constant result, in place."""
    kept = []
    for op in graph.ops:
        src = graph.tensors[op.inputs[0]] if op.inputs else None
        if op.kind in ("DENSIFY", "DEQUANTIZE") and src is not None and src.data is not None:
            dst = graph.tensors[op.outputs[0]]
            if op.kind == "DENSIFY":
                if src.sparsity is None:
                    raise UnsupportedModel(f"DENSIFY of {src.name!r}, which is not sparse")
                dst.data = densify(src.data, src.shape, src.sparsity)
            else:
                dst.data = _dequantize(src)
            graph.folded[op.kind] = graph.folded.get(op.kind, 0) + 1
            continue
        kept.append(op)
    graph.ops = kept
