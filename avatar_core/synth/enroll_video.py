"""The enrollment studio: the synthetic actor filmed by one fixed camera while turning slowly
(0 -> +yaw -> 0 -> -yaw -> 0) and gesturing, written as an mp4 - the test and benchmark input
of ``telesplat enroll``. Also the bad takes enrollment must refuse (nobody, two people, a dark
or blurred or still take) and the true per-frame parameters, which enrollment never reads."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from .tracking_eval.scene import background, subject_transl, webcam_camera

__all__ = ["EnrollVideoSpec", "film_enroll_video", "take_params", "true_alpha",
           "write_true_params"]

GESTURES = ("smile", "wave", "mouth_open", "thumbs_up", "peace", "grin")


@dataclass(frozen=True)
class EnrollVideoSpec:
    seconds: float = 4.0
    fps: float = 10.0
    width: int = 320
    height: int = 240
    fov_x_deg: float = 60.0
    yaw_deg: float = 90.0          # the turn's amplitude either way (0: never turns)
    gestures: tuple[str, ...] = GESTURES
    identity: int = 0
    people: int = 0                # 0: the actor only; 1: a second person beside (refusal)
    empty: bool = False            # nobody in the frame (refusal)
    brightness: float = 1.0        # < 1 darkens the take
    blur_px: float = 0.0           # Gaussian blur sigma on every frame
    background: str = "noise"      # "noise" (a room-like texture) or "plain"
    supersample: int = 2
    seed: int = 0

    def __post_init__(self) -> None:
        if self.seconds <= 0 or self.fps <= 0 or self.width < 32 or self.height < 32:
            raise ValueError("seconds, fps must be > 0 and the size at least 32 px")

    @property
    def num_frames(self) -> int:
        return max(1, int(round(self.seconds * self.fps)))


def _yaw(spec: EnrollVideoSpec, t: float) -> float:
    return math.radians(spec.yaw_deg) * math.sin(2 * math.pi * t / spec.seconds)


def take_params(spec: EnrollVideoSpec, actor, rig, transl: np.ndarray
                ) -> list[dict[str, np.ndarray]]:
    """True SMPL-X parameters per frame: the gesture clips played over the take, the body
    turned about its vertical axis."""
    from ..motion.library import motion_sequence

    track = motion_sequence(list(spec.gestures))
    out = []
    for i in range(spec.num_frames):
        t = i / spec.fps
        p = track.sample(t / spec.seconds * track.duration, rig)
        turn = Rotation.from_rotvec([0.0, _yaw(spec, t), 0.0])
        p["global_orient"] = (turn * Rotation.from_rotvec(p["global_orient"])).as_rotvec()
        p["transl"] = transl.copy()
        p["betas"] = np.asarray(actor.betas, dtype=np.float64)
        out.append(p)
    return out


def _frames(spec: EnrollVideoSpec, model_dir: Path | None):
    from ..motion.rig import model_rig
    from .actor import Actor
    from .model_writer import ensure_models

    files = ensure_models(model_dir)
    actor = Actor.load(files, spec.identity)
    camera = webcam_camera(spec.width, spec.height, spec.fov_x_deg)
    transl = subject_transl(actor, camera)
    bg = background(spec.width, spec.height, spec.background, seed=spec.seed + 7)
    params = take_params(spec, actor, model_rig(files, actor.model), transl)
    beside = None
    if spec.people:  # the same actor again, shifted to one side and a little nearer
        beside = np.array([0.45 * abs(transl[2]) * math.tan(math.radians(spec.fov_x_deg) / 2),
                           0.0, 0.1])
    for i, p in enumerate(params):
        rgb = bg.copy()
        if not spec.empty:
            shots = [p] if beside is None else [
                {**p, "transl": p["transl"] - beside},
                {**p, "transl": p["transl"] + beside}]
            for q in shots:
                view = actor.render(actor.pose(q), camera, background=(0.0, 0.0, 0.0),
                                    supersample=spec.supersample)
                rgb = view.rgb + (1.0 - view.alpha)[..., None] * rgb
        rgb = rgb * spec.brightness
        if spec.blur_px > 0:
            rgb = cv2.GaussianBlur(rgb, (0, 0), spec.blur_px)
        yield i, (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8), p


def film_enroll_video(out: str | Path, spec: EnrollVideoSpec, *,
                      model_dir: Path | None = None, params_out: str | Path | None = None,
                      progress=None) -> Path:
    """Write the take as an mp4 (``mp4v``) at ``out``; with ``params_out`` also the true
    per-frame parameters (.npz, frame axis first) for the benchmark."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*"mp4v"), spec.fps,
                             (spec.width, spec.height))
    if not writer.isOpened():
        raise OSError(f"cannot write {out}: OpenCV has no mp4v encoder here")
    truth = []
    try:
        for i, rgb, p in _frames(spec, model_dir):
            writer.write(np.ascontiguousarray(rgb[..., ::-1]))
            truth.append(p)
            if progress:
                progress(i + 1, spec.num_frames)
    finally:
        writer.release()
    if params_out is not None:
        np.savez(params_out, **{k: np.stack([p[k] for p in truth]) for k in truth[0]})
    return out


def write_true_params(path: str | Path, spec: EnrollVideoSpec,
                      model_dir: Path | None = None) -> Path:
    """The take's true per-frame parameters (.npz, frame axis first), without filming it."""
    from ..motion.rig import model_rig
    from .actor import Actor
    from .model_writer import ensure_models

    files = ensure_models(model_dir)
    actor = Actor.load(files, spec.identity)
    camera = webcam_camera(spec.width, spec.height, spec.fov_x_deg)
    truth = take_params(spec, actor, model_rig(files, actor.model),
                        subject_transl(actor, camera))
    np.savez(path, **{k: np.stack([p[k] for p in truth]) for k in truth[0]})
    return Path(path)


def true_alpha(spec: EnrollVideoSpec, frames: list[int], model_dir: Path | None = None
               ) -> list[np.ndarray]:
    """The actor's true coverage [H, W] float32 at the take's ``frames`` (for benchmarks)."""
    from ..motion.rig import model_rig
    from .actor import Actor
    from .model_writer import ensure_models

    files = ensure_models(model_dir)
    actor = Actor.load(files, spec.identity)
    camera = webcam_camera(spec.width, spec.height, spec.fov_x_deg)
    truth = take_params(spec, actor, model_rig(files, actor.model),
                        subject_transl(actor, camera))
    return [actor.render(actor.pose(truth[i]), camera, supersample=spec.supersample).alpha
            for i in frames]
