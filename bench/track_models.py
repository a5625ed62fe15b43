"""The converted MediaPipe models: parity with TFLite and onnxruntime speed, PRelu vs rewrite.

For each model: the max abs difference of the converted ONNX model against the reference TFLite
interpreter (ai-edge-litert) on the astronaut photograph, relative to the output's scale, and
ms per inference in onnxruntime (CPU, one thread) with PReLU written as the PRelu op and as
Relu(x) + alpha * Min(x, 0), next to the TFLite interpreter's own time (one thread).

    python bench/track_models.py [--repeat N] [--models a,b]
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import onnxruntime as ort  # noqa: E402

from avatar_core.track.convert import convert  # noqa: E402
from avatar_core.track.models import MODELS, fetch_models  # noqa: E402


def _timed(fn, repeat: int) -> float:
    fn()  # warm-up
    fn()
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1000 * float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=30)
    parser.add_argument("--models", default=None, help="comma-separated (default: all)")
    args = parser.parse_args()
    import cv2
    from ai_edge_litert.interpreter import Interpreter
    from skimage.data import astronaut

    names = args.models.split(",") if args.models else list(MODELS)
    paths = fetch_models(convert=False, names=names)
    photo = astronaut().astype(np.float32) / 255.0
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    print(f"onnxruntime {ort.__version__}, 1 thread; median of {args.repeat} runs")
    print("| model | PReLUs | max abs diff / scale | PRelu op ms | rewrite ms | speed-up "
          "| TFLite ms |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name in names:
        interp = Interpreter(model_path=str(paths[name]), num_threads=1)
        interp.allocate_tensors()
        (inp,) = interp.get_input_details()
        _, h, w, _ = inp["shape"]
        lo = -1.0 if name == "face_detection_short_range" else 0.0
        x = (lo + (1 - lo) * cv2.resize(photo, (int(w), int(h)), interpolation=cv2.INTER_AREA)
             )[None].astype(np.float32)
        interp.set_tensor(inp["index"], x)
        ms_tflite = _timed(interp.invoke, args.repeat)
        refs = [interp.get_tensor(o["index"]) for o in interp.get_output_details()]
        ms = {}
        rel = 0.0
        n_prelu = 0
        for mode in ("op", "rewrite"):
            model = convert(paths[name], prelu=mode)
            inference = ort.InferenceSession(model.SerializeToString(), options,
                                             providers=["CPUExecutionProvider"])
            outs = inference.run(None, {inp["name"]: x})
            for y, ref in zip(outs, refs, strict=True):
                rel = max(rel, float(np.abs(y - ref).max()) / max(1.0, float(np.abs(ref).max())))
            feeds = {inp["name"]: x}
            ms[mode] = _timed(lambda s=inference, f=feeds: s.run(None, f), args.repeat)
            if mode == "op":
                n_prelu = sum(n.op_type == "PRelu" for n in model.graph.node)
        print(f"| {name} | {n_prelu} | {rel:.1e} | {ms['op']:.2f} | {ms['rewrite']:.2f} "
              f"| {ms['op'] / ms['rewrite']:.2f}x | {ms_tflite:.2f} |")


if __name__ == "__main__":
    main()
