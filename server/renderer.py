"""One session's frame work, run on a render thread: pose -> rasterize -> encode.

A session never has two renders in flight, so the state here (the animator's caches, the H.264
encoder) is touched by one thread at a time.
"""

from __future__ import annotations

import concurrent.futures
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

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
from .encoders import H264Encoder, encode_depth_png, encode_jpeg, encode_png, frame_rgb
from .view_batch import DeviceCopies, render_device

if TYPE_CHECKING:
    from .scheduler import RenderScheduler


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


def view_camera(view: View, width: int, height: int, default_target: np.ndarray) -> Camera:
    """The camera of a view; an orbit without a target looks at ``default_target``."""
    if view.camera is not None:
        c = view.camera
        cam = Camera(np.asarray(c.K), np.asarray(c.R), np.asarray(c.t), c.width, c.height)
        return cam if cam.size == (width, height) else cam.resized(width, height)
    o = view.orbit
    target = default_target if o.target is None else np.asarray(o.target, dtype=np.float64)
    return orbit(target, o.yaw_deg, o.pitch_deg, o.distance, width=width, height=height,
                 fov_y_deg=o.fov_y_deg)


def encode_outputs(rgb: np.ndarray, alpha: np.ndarray | None, depth: np.ndarray | None,
                   req: Request, jpeg_quality: int,
                   encode_h264: Callable[[np.ndarray, Request], tuple[bytes, bool]]
                   ) -> tuple[str, bytes, bool, bytes | None]:
    """(codec, data, keyframe, depth PNG) of a rendered frame as ``req`` asks."""
    codec, keyframe = req.codec, True
    if "alpha" in req.outputs and codec != "h264":
        codec, data = "png", encode_png(rgb, alpha)
    elif codec == "png":
        data = encode_png(rgb)
    elif codec == "h264":
        data, keyframe = encode_h264(rgb, req)
    else:
        data = encode_jpeg(rgb, jpeg_quality)
    depth_png = encode_depth_png(depth) if "depth" in req.outputs else None
    return codec, data, keyframe, depth_png


class H264Stream:
    """One client's H.264 stream (stateful: never shared); opened at the first frame, reopened
    when the size changes, a keyframe when the client comes back from another codec."""

    def __init__(self) -> None:
        self._encoder: H264Encoder | None = None

    def encode(self, rgb: np.ndarray, req: Request, last_codec: str | None
               ) -> tuple[bytes, bool]:
        h, w = rgb.shape[:2]
        enc = self._encoder
        if enc is None or (enc.width, enc.height) != (w, h):
            if enc is not None:
                enc.close()
            enc = self._encoder = H264Encoder(w, h, fps=req.max_fps)
        elif last_codec != "h264":
            enc.force_keyframe()  # back from another codec: the client restarts here
        return enc.encode(rgb)

    def close(self) -> None:
        if self._encoder is not None:
            self._encoder.close()
            self._encoder = None


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
        self._h264 = H264Stream()
        self._on_device = DeviceCopies(render_device(backend), keep=1)  # CUDA: one upload
        self._last_codec: str | None = None
        self._closed = threading.Event()

    def camera(self, view: View, width: int, height: int) -> Camera:
        return view_camera(view, width, height, self.chest)

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
            gaussians = self._on_device.get(self._posed_version, posed.gaussians)
            out = rasterize(gaussians, cam, RenderRequest(
                outputs=outputs, background=tuple(req.background), sh_degree=req.sh_degree,
                budget=budget, backend=self.backend))
            rgb = frame_rgb(out.rgb, req.codec, "alpha" in req.outputs)  # [H, W, 3] uint8
            alpha = None if out.alpha is None else to_uint8(out.alpha)  # [H, W]
            depth = None if out.depth is None else out.depth.cpu().numpy()  # [H, W] metres
        t2 = time.perf_counter()
        codec, data, keyframe, depth_png = encode_outputs(
            rgb, alpha, depth, req, job.jpeg_quality, self._encode_h264)
        self._last_codec = codec
        t3 = time.perf_counter()
        timings = Timings(track=job.track_ms, pose=(t1 - t0) * 1e3, render=(t2 - t1) * 1e3,
                          encode=(t3 - t2) * 1e3)
        return RenderedFrame(job.drive.seq, codec, cam.width, cam.height, data, depth_png,
                             keyframe, timings)

    def submit(self, scheduler: RenderScheduler, job: FrameJob, session: Any
               ) -> concurrent.futures.Future:
        """The frame of ``job`` on this server's render threads, on the session's account
        (render_backend ray makes it on a render worker: server/cluster_render/)."""
        return scheduler.submit(self.render, job, key=session.share_key)

    def _encode_h264(self, rgb: np.ndarray, req: Request) -> tuple[bytes, bool]:
        return self._h264.encode(rgb, req, self._last_codec)

    def close(self) -> None:
        self._h264.close()
