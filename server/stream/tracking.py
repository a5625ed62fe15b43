"""Server-side webcam tracking: ``image`` messages -> fitted SMPL-X parameters.

Each session gets its own tracker and fit state, created on its first image (the landmark
models come from the converted-model cache; when they are missing, tracking is unsupported
for the session and says why). Tracking runs on a small shared pool of tracking threads, off
the event loop and off the render threads; a session never has more than one image in
flight, and an image that arrives meanwhile replaces the waiting one (latest wins).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from avatar_core.body.models import SMPLXModel
from protocol import Image, Limits


class TrackingUnavailable(RuntimeError):
    """Tracking cannot run in this server (e.g. the landmark models are not installed)."""


class TrackingInputInvalid(ValueError):
    """This image cannot be tracked (corrupt, too large, not JPEG / PNG)."""


@dataclass(frozen=True)
class DecodedImage:
    """A webcam frame that arrives decoded (a WHIP video track), not as an ``image`` message;
    ``to_bgr`` converts it on the tracking thread, off the event loop."""

    seq: int
    width: int
    height: int
    to_bgr: Callable[[], np.ndarray]  # -> [H, W, 3] uint8 BGR
    t_capture: float | None = None    # when the camera took it, on the performer's clock


@dataclass
class TrackedImage:
    seq: int
    params: dict[str, np.ndarray]  # SMPL-X fields for a drive (no transl)
    track_ms: float                 # decode + landmarks + fit
    seen: dict[str, bool]
    t_capture: float | None = None  # the image's: the drive tracked from it carries it


class SessionTracker:
    """Decode, track and fit one session's images; call from one thread at a time."""

    def __init__(self, body_model: SMPLXModel, betas: np.ndarray | None, limits: Limits) -> None:
        self.body_model = body_model
        self.betas = betas
        self.limits = limits
        self._tracker = None
        self._fit = None
        self.unavailable: str | None = None  # the reason, once known

    def _ensure(self) -> None:
        if self.unavailable:
            raise TrackingUnavailable(self.unavailable)
        if self._tracker is not None:
            return
        try:
            from avatar_core.track.fit.sequence import SequenceFit, live_config
            from avatar_core.track.tracker import LIVE_PALM_INTERVAL, Tracker

            tracker = Tracker(threads=1, palm_interval=LIVE_PALM_INTERVAL, iris=True)
        except (ImportError, RuntimeError, OSError, ValueError) as exc:
            self.unavailable = f"server-side tracking is not available: {exc}"
            raise TrackingUnavailable(self.unavailable) from exc
        self._tracker = tracker
        self._fit = SequenceFit(self.body_model, self.betas, live_config())

    def process(self, image: Image | DecodedImage, received_at: float) -> TrackedImage:
        """Raises TrackingUnavailable or TrackingInputInvalid; anything else is a bug."""
        from avatar_core.track.fit.observations import from_track_result
        from avatar_core.track.fit.sequence import drive_params
        from avatar_core.track.image import decode_image
        from avatar_core.track.types import TrackingInputError

        t0 = time.perf_counter()
        self._ensure()
        try:
            frame = (self._decoded(image) if isinstance(image, DecodedImage) else
                     decode_image(image.data, max_pixels=self.limits.max_image_pixels))
            result = self._tracker.track(frame)
        except TrackingInputError as exc:
            raise TrackingInputInvalid(str(exc)) from exc
        out = self._fit.step(from_track_result(result), received_at)
        return TrackedImage(image.seq, drive_params(out.params),
                            (time.perf_counter() - t0) * 1e3, out.seen, image.t_capture)

    def _decoded(self, image: DecodedImage) -> np.ndarray:
        from avatar_core.track.types import TrackingInputError

        pixels = image.width * image.height
        if pixels > self.limits.max_image_pixels:
            raise TrackingInputError(f"video frame too large: {image.width}x{image.height} = "
                                     f"{pixels} pixels > {self.limits.max_image_pixels}")
        return image.to_bgr()

    def close(self) -> None:
        if self._tracker is not None:
            self._tracker.close()
