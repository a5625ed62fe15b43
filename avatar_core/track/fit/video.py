"""Frames from a video, a webcam or one image -> per-frame SMPL-X parameters -> a motion file.

The file is what `telesplat render --motion` and `telesplat-client stream --motion` read:
`.json`, a list of per-frame dicts of SMPL-X fields; or `.npz`, one array per field with the
frame axis first.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .observations import from_track_result
from .sequence import SequenceFit, drive_params, live_config


def frames_from(source: str | int, max_frames: int | None = None
                ) -> Iterator[tuple[np.ndarray, float]]:
    """(BGR frame, seconds) from a video path, a webcam index, or a still image (one frame)."""
    if isinstance(source, str) and Path(source).suffix.lower() in (".jpg", ".jpeg", ".png"):
        from ..image import decode_image

        yield decode_image(Path(source).read_bytes()), 0.0
        return
    cap = cv2.VideoCapture(source)
    if not cap.isOpened():
        raise OSError(f"cannot open {'webcam' if isinstance(source, int) else 'video'} "
                      f"{source!r}")
    fps = cap.get(cv2.CAP_PROP_FPS) or 30.0
    live, start, i = isinstance(source, int), time.monotonic(), 0
    try:
        while max_frames is None or i < max_frames:
            ok, frame = cap.read()
            if not ok:
                return
            yield frame, (time.monotonic() - start) if live else i / fps
            i += 1
    finally:
        cap.release()


@dataclass
class TrackedFrame:
    params: dict[str, np.ndarray]  # the fitted SMPL-X fields (see `drive_params`)
    seen: dict[str, bool]          # group -> seen in this frame
    t: float
    track_ms: float                # landmarks
    fit_ms: float                  # SequenceFit.step


def tracked_frames(frames: Iterable[tuple[np.ndarray, float]], sequence_fit: SequenceFit, tracker,
                   with_transl: bool = False) -> Iterator[TrackedFrame]:
    """Track and fit frames in order, two stages overlapped: while frame i is fitted (a
    second thread) frame i + 1's landmarks are found, so on two cores a frame costs the
    slower stage, not their sum (docs/tracking.md). Every frame is kept, in order."""

    def fit(result, t: float, track_ms: float) -> TrackedFrame:
        t0 = time.perf_counter()
        out = sequence_fit.step(from_track_result(result), t)
        return TrackedFrame(drive_params(out.params, with_transl), out.seen, t, track_ms,
                            (time.perf_counter() - t0) * 1e3)

    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="fit") as pool:
        pending: Future | None = None
        for frame, t in frames:
            t0 = time.perf_counter()
            result = tracker.track(frame)
            track_ms = (time.perf_counter() - t0) * 1e3
            if pending is not None:
                yield pending.result()
            pending = pool.submit(fit, result, t, track_ms)
        if pending is not None:
            yield pending.result()


def track_params(frames: Iterable[tuple[np.ndarray, float]], sequence_fit: SequenceFit, tracker,
                 with_transl: bool = False,
                 progress: Callable[[], None] | None = None) -> list[dict[str, np.ndarray]]:
    out = []
    for tracked in tracked_frames(frames, sequence_fit, tracker, with_transl):
        out.append(tracked.params)
        if progress:
            progress()
    return out


def write_params(frames: list[dict[str, np.ndarray]], path: Path) -> Path:
    if not frames:
        raise ValueError("no frames were tracked")
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".json":
        path.write_text(json.dumps([{k: np.asarray(v).tolist() for k, v in f.items()}
                                    for f in frames]))
    elif path.suffix == ".npz":
        np.savez(path, **{k: np.stack([f[k] for f in frames]) for k in frames[0]})
    else:
        raise ValueError(f"{path}: parameter files are .json or .npz")
    return path


def default_sequence_fit(fov_x_deg: float = 60.0, smoothing: bool = True,
                         body_models: str | Path | None = None) -> SequenceFit:
    """A sequence fit on the body model that ``resolve_body_models`` finds (``body_models``,
    then ``$TELESPLAT_BODY_MODELS``, else the synthetic family), with the shape of the family's
    first identity where it has identities (the synthetic one), else the mean shape."""
    from ...body.model_paths import resolve_body_models
    from ...body.upper_body import UpperBodyModel

    files = resolve_body_models(body_models)
    files.require()
    model = UpperBodyModel.load(files.smplx_npz, files.segmentation)
    identities = files.identities()
    if identities:
        with np.load(identities[0]) as identity:
            betas = np.asarray(identity["betas"], dtype=np.float64)
    else:
        betas = np.zeros(model.num_betas)
    return SequenceFit(model, betas, live_config(fov_x_deg=fov_x_deg, smoothing=smoothing))
