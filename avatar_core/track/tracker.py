"""The tracker: face, hands, body and person mask on one frame, tracked across frames."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from functools import partial

import numpy as np

from .face import FacePipeline
from .hands import HandPipeline
from .image import DEFAULT_MAX_PIXELS, check_frame
from .iris import IrisPipeline
from .onnx_model import ModelSource
from .pose import PosePipeline
from .segmentation import SelfieSegmentation
from .types import TrackResult

# Live driving (server-side webcam, remote tracker): a palm search every 5th frame while fewer
# than two hands are tracked keeps face + hands + body at >= 30 fps on 2 cores (docs/tracking.md:
# 31 fps, against 21 fps searching every frame); offline tracking keeps MediaPipe's 1.
LIVE_PALM_INTERVAL = 5


class Tracker:
    """Stateful monocular tracker on ONNX Runtime.

    models: None (the converted models in the default cache), a cache folder, or a mapping
    model name -> ONNX file. providers: ONNX Runtime execution providers (default CPU).
    threads: intra-op threads per model (None: ONNX Runtime's default). parallel: run the
    enabled stages concurrently in threads (worth it with one thread per model on a machine
    with a core per stage). hand_model: "full" or "lite". palm_interval: while fewer than two
    hands are tracked, look for new palms every this many frames (1 = MediaPipe's behaviour).
    iris: read both eyes' iris and eyelid points after the face mesh (`FaceLandmarks.iris`,
    `.eye_contour`; two iris_landmark runs per frame, timed as "iris"; off by default: ~6 ms
    a frame on one core, docs/tracking.md).
    """

    def __init__(self, models: ModelSource = None, face: bool = True, hands: bool = True,
                 pose: bool = True, mask: bool = False, providers: Sequence | None = None,
                 threads: int | None = None, parallel: bool = False,
                 hand_model: str = "full", max_hands: int = 2, palm_interval: int = 1,
                 max_pixels: int = DEFAULT_MAX_PIXELS, iris: bool = False):
        args = (models, providers, threads)
        self.face = FacePipeline(*args) if face else None
        self.iris = IrisPipeline(*args) if face and iris else None
        self.hands = HandPipeline(*args, max_hands=max_hands, variant=hand_model,
                                  palm_interval=palm_interval) if hands else None
        self.pose = PosePipeline(*args) if pose else None
        self.mask = SelfieSegmentation(*args) if mask else None
        self.max_pixels = max_pixels
        stages = sum(s is not None for s in (self.face, self.hands, self.pose, self.mask))
        self._pool = ThreadPoolExecutor(stages) if parallel and stages > 1 else None

    def reset(self) -> None:
        """Forget the tracked ROIs: the next frame runs the detectors again."""
        for stage in (self.face, self.hands, self.pose):
            if stage is not None:
                stage.reset()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def track(self, frame_bgr: np.ndarray) -> TrackResult:
        """One [H, W, 3] uint8 BGR frame -> landmarks in its pixels. Raises TrackingInputError
        for an unusable frame; a frame with nobody in it gives empty fields."""
        t0 = time.perf_counter()
        frame = check_frame(frame_bgr, self.max_pixels)
        timings: dict[str, float] = {}

        def timed(name: str, stage: Callable, *args):
            start = time.perf_counter()
            out = stage(*args)
            timings[name] = (time.perf_counter() - start) * 1e3
            return out

        def face_then_iris(frame: np.ndarray):
            face = timed("face", self.face, frame)
            return face if face is None or self.iris is None else timed(
                "iris", self.iris, frame, face)

        stages = {name: partial(timed, name, stage)
                  for name, stage in (("face", self.face), ("hands", self.hands),
                                      ("pose", self.pose), ("mask", self.mask))
                  if stage is not None}
        if self.face is not None:
            stages["face"] = face_then_iris  # the eyes need this frame's face mesh
        if self._pool is not None:
            futures = {n: self._pool.submit(s, frame) for n, s in stages.items()}
            out = {n: f.result() for n, f in futures.items()}
        else:
            out = {n: s(frame) for n, s in stages.items()}
        timings["total"] = (time.perf_counter() - t0) * 1e3
        h, w = frame.shape[:2]
        return TrackResult(face=out.get("face"), hands=out.get("hands", ()),
                           pose=out.get("pose"), mask=out.get("mask"), timings_ms=timings,
                           image_size=(w, h))
