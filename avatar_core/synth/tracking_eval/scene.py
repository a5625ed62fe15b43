"""The scene: the synthetic actor framed head to waist by the fitter's 640x480 webcam, over a
static background, and the true parameters of a library clip."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from avatar_core.body.skeleton import JOINT
from avatar_core.render.camera import Camera, look_at

WIDTH, HEIGHT, FOV_X_DEG = 640, 480, 60.0
CLIPS = ("smile", "mouth_open", "jaw_left", "shake_head", "thumbs_up", "peace", "heart",
         "clapping", "talk_animated")


def webcam_camera(width: int = WIDTH, height: int = HEIGHT, fov_x_deg: float = FOV_X_DEG
                  ) -> Camera:
    """The fitter's webcam (`WebcamCamera`) as a render camera: at the origin, looking down -z,
    y up, principal point at the centre, square pixels."""
    focal = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    fov_y = 2 * math.degrees(math.atan(0.5 * height / focal))
    return look_at((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), width=width, height=height,
                   fov_y_deg=fov_y)


def subject_transl(actor, camera: Camera, margin: float = 1.05) -> np.ndarray:
    """`transl` that frames the actor head to waist (top of the head to the pelvis), centred."""
    with torch.no_grad():
        joints = actor.model({"betas": actor.betas}).joints[0].numpy()
    top = joints[JOINT["head"], 1] + 0.30  # above the hair
    bottom = joints[JOINT["pelvis"], 1]
    centre = 0.5 * (top + bottom)
    fov_y = 2 * math.atan(0.5 * camera.height / camera.fy)
    distance = margin * (top - bottom) / (2 * math.tan(fov_y / 2))
    return np.array([-joints[JOINT["pelvis"], 0], -centre, -distance - joints[JOINT["head"], 2]])


def background(width: int, height: int, kind: str = "noise", seed: int = 7) -> np.ndarray:
    """[H, W, 3] float32 in [0, 1]: a plain grey wall or a static blotchy room-like texture."""
    if kind == "plain":
        return np.full((height, width, 3), 0.55, np.float32)
    rng = np.random.default_rng(seed)

    def blotches(rows: int, cols: int, lo: float, hi: float, channels: int) -> np.ndarray:
        small = rng.uniform(lo, hi, (rows, cols, channels)).astype(np.float32)
        out = cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC)
        return out.reshape(height, width, channels)

    low = blotches(6, 8, 0.3, 0.75, 1) + blotches(6, 8, -0.07, 0.07, 3)  # walls, light tint
    mid = blotches(30, 40, -0.08, 0.08, 1)  # clutter
    fine = rng.normal(0.0, 0.02, (height, width, 3)).astype(np.float32)  # texture
    return np.clip(low + mid + fine, 0.0, 1.0)


def render_frame(actor, params: dict, camera: Camera, bg: np.ndarray, sensor_noise: float,
                 rng: np.random.Generator, supersample: int = 2) -> np.ndarray:
    """One [H, W, 3] uint8 BGR webcam frame of the actor posed by `params`."""
    posed = actor.pose(params)
    view = actor.render(posed, camera, background=(0.0, 0.0, 0.0), supersample=supersample)
    rgb = view.rgb + (1.0 - view.alpha)[..., None] * bg  # premultiplied over the background
    if sensor_noise > 0:
        rgb = rgb + rng.normal(0.0, sensor_noise, rgb.shape).astype(np.float32)
    return (np.clip(rgb, 0.0, 1.0)[..., ::-1] * 255.0 + 0.5).astype(np.uint8)


@dataclass
class Scene:
    actor: object
    rig: object
    camera: Camera
    transl: np.ndarray
    bg: np.ndarray
    model_dir: Path


def make_scene(background_kind: str = "noise") -> Scene:
    from avatar_core.motion.rig import model_rig
    from avatar_core.synth.actor import Actor
    from avatar_core.synth.model_writer import ensure_models

    files = ensure_models()
    actor = Actor.load(files, 0)
    camera = webcam_camera()
    return Scene(actor, model_rig(files, actor.model), camera, subject_transl(actor, camera),
                 background(camera.width, camera.height, background_kind), files.root)


def clip_params(scene: Scene, name: str, fps: float, start: float = 0.0,
                max_frames: int | None = None) -> list[dict[str, np.ndarray]]:
    """The true SMPL-X parameters of a library motion sampled at `fps`, placed in the view."""
    from avatar_core.motion.library import motion_sequence

    track = motion_sequence([name])
    n = int(math.floor((track.duration - start) * fps + 1e-9)) + 1
    n = n if max_frames is None else min(n, max_frames)
    out = []
    for i in range(n):
        p = track.sample(start + i / fps, scene.rig)
        p["transl"] = scene.transl.copy()
        p["betas"] = np.asarray(scene.actor.betas, dtype=np.float64)
        out.append(p)
    return out
