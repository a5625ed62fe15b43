"""One session's frame work, run on a render thread: pose -> rasterize -> encode.

A session never has two renders in flight, so the state here (the animator's caches, the H.264
encoder) is touched by one thread at a time.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
import torch

from avatar_core.body.models import MANOModel
from avatar_core.gaussians.animate import AvatarAnimator, PosedAvatar
from avatar_core.render.camera import Camera, orbit
from avatar_core.render.camera_path import framing_target
from avatar_core.render.rasterize import rasterize
from avatar_core.render.types import RenderRequest, to_uint8
from protocol import Request, Timings, View

from .drive import DriveState, drive_shapes
from .encoders import H264Encoder, encode_depth_png, encode_jpeg, encode_png


@dataclass(frozen=True)
class FrameJob:
    """A snapshot of what one frame shows."""

    drive: DriveState
    view: View
    request: Request          # effective: every field set
    jpeg_quality: int         # already lowered when the view moves
    track_ms: float = 0.0     # tracking time of the webcam image this frame first shows


@dataclass
class RenderedFrame:
    seq: int
    codec: str
    width: int
    height: int
    data: bytes
    depth: bytes | None
    keyframe: bool
    timings: Timings


class SessionRenderer:
    def __init__(self, animator: AvatarAnimator, manos: dict[str, MANOModel],
                 backend: str = "auto") -> None:
        self.animator = animator
        self.manos = manos
        self.backend = backend
        model = animator.body_model
        self.shapes = drive_shapes(model, manos)
        self.chest = framing_target(model.joint_template)  # the default orbit target
        self._posed: PosedAvatar | None = None  # of the drive state version below
        self._posed_version = -1
        self._h264: H264Encoder | None = None
        self._last_codec: str | None = None
        self._closed = threading.Event()

    def camera(self, view: View, width: int, height: int) -> Camera:
        if view.camera is not None:
            c = view.camera
            cam = Camera(np.asarray(c.K), np.asarray(c.R), np.asarray(c.t), c.width, c.height)
            return cam if cam.size == (width, height) else cam.resized(width, height)
        o = view.orbit
        target = self.chest if o.target is None else np.asarray(o.target, dtype=np.float64)
        return orbit(target, o.yaw_deg, o.pitch_deg, o.distance, width=width, height=height,
                     fov_y_deg=o.fov_y_deg)

    def render(self, job: FrameJob) -> RenderedFrame:
        req = job.request
        t0 = time.perf_counter()
        with torch.no_grad():
            if self._posed is None or job.drive.version != self._posed_version:
                params = job.drive.smplx_params(self.animator.body_model, self.manos)
                self._posed = self.animator.pose(params)
                self._posed_version = job.drive.version
            posed = self._posed  # only the view or the request changed: no fusion, no pose
            t1 = time.perf_counter()
            cam = self.camera(job.view, req.width, req.height)
            outputs = tuple(dict.fromkeys(("rgb", *req.outputs)))  # rgb always: frame.data
            budget = None if req.quality >= 1.0 else float(req.quality)
            out = rasterize(posed.gaussians, cam, RenderRequest(
                outputs=outputs, background=tuple(req.background), sh_degree=req.sh_degree,
                budget=budget, backend=self.backend))
            rgb = to_uint8(out.rgb)  # [H, W, 3]
            alpha = None if out.alpha is None else to_uint8(out.alpha)  # [H, W]
            depth = None if out.depth is None else out.depth.cpu().numpy()  # [H, W] metres
        t2 = time.perf_counter()
        codec, keyframe = req.codec, True
        if "alpha" in req.outputs and codec != "h264":
            codec, data = "png", encode_png(rgb, alpha)
        elif codec == "png":
            data = encode_png(rgb)
        elif codec == "h264":
            data, keyframe = self._encode_h264(rgb, req)
        else:
            data = encode_jpeg(rgb, job.jpeg_quality)
        self._last_codec = codec
        depth_png = encode_depth_png(depth) if "depth" in req.outputs else None
        t3 = time.perf_counter()
        timings = Timings(track=job.track_ms, pose=(t1 - t0) * 1e3, render=(t2 - t1) * 1e3,
                          encode=(t3 - t2) * 1e3)
        return RenderedFrame(job.drive.seq, codec, cam.width, cam.height, data, depth_png,
                             keyframe, timings)

    def _encode_h264(self, rgb: np.ndarray, req: Request) -> tuple[bytes, bool]:
        h, w = rgb.shape[:2]
        if self._h264 is None or (self._h264.width, self._h264.height) != (w, h):
            if self._h264 is not None:
                self._h264.close()
            self._h264 = H264Encoder(w, h, fps=req.max_fps)
        elif self._last_codec != "h264":
            self._h264.force_keyframe()  # back from another codec: the client restarts here
        return self._h264.encode(rgb)

    def close(self) -> None:
        if self._h264 is not None:
            self._h264.close()
            self._h264 = None
