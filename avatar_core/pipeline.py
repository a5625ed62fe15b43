"""The frame pipeline: avatar + parameters + camera -> image. Used by the CLI and the server.

Resolves what to render (an avatar package, or an untrained avatar on the synthetic model),
reads motions and cameras from files or built-ins, and renders sequences to PNGs or MP4.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from .body.model_data import load_mano
from .body.model_paths import BodyModelFiles, synthetic_body_models
from .body.models import MANOModel
from .gaussians.animate import AvatarAnimator, synthetic_package
from .gaussians.package import AvatarPackage, load_package
from .motion.library import demo_clip
from .motion.rig import model_rig
from .render.camera import Camera, orbit
from .render.mp4_writer import Mp4Writer
from .render.rasterize import rasterize
from .render.types import RenderRequest


@dataclass
class LoadedAvatar:
    package: AvatarPackage
    animator: AvatarAnimator
    files: BodyModelFiles


def load_avatar(spec: str, model_dir: Path | None = None, **package_limits: Any
                ) -> LoadedAvatar:
    """`synthetic[:IDENTITY]` for an untrained avatar on the synthetic model, or the path of a
    package bound to the synthetic model (its body reference says which seed).
    ``package_limits``: ``max_bytes`` / ``npz_limits`` for ``load_package``."""
    if spec == "synthetic" or spec.startswith("synthetic:"):
        identity = int(spec.split(":", 1)[1]) if ":" in spec else 0
        files = synthetic_body_models(model_dir)
        package, model = synthetic_package(files.root, identity)
    else:
        package = load_package(spec, **package_limits)
        ref = package.body.model
        if not ref.startswith("synthetic:seed"):
            raise ValueError(f"{spec}: bound to body model {ref!r}; only synthetic models can be "
                             "resolved here (the licensed SMPL-X files are not available)")
        files = synthetic_body_models(model_dir, seed=int(ref.removeprefix("synthetic:seed")))
        _, model = synthetic_package(files.root, 0)
        package.body.check_faces(model.faces.cpu().numpy())
    animator = AvatarAnimator(model, package.avatar, betas=np.asarray(package.body.betas))
    return LoadedAvatar(package, animator, files)


def mano_models(loaded: LoadedAvatar) -> dict[str, MANOModel]:
    """The MANO models per side that exist beside the avatar's body model (same dtype), for
    fusing MANO hand parameters into SMPL-X."""
    dtype = loaded.animator.body_model.dtype
    out = {}
    for side in ("left", "right"):
        path = loaded.files.mano_pkl(side)
        if path.is_file():
            out[side] = MANOModel(load_mano(path), dtype=dtype)
    return out


def motion_frames(spec: str, loaded: LoadedAvatar, fps: float,
                  frames: int | None = None) -> list[dict[str, np.ndarray]]:
    """Per-frame SMPL-X parameters: a built-in clip name ('demo', 'rest'), a .json list of
    per-frame dicts, or an .npz of arrays with a leading frame axis."""
    if spec == "rest":
        return [{} for _ in range(frames or 1)]
    if spec == "demo":
        clip = demo_clip()
        rig = model_rig(loaded.files, loaded.animator.body_model)
        n = frames or max(1, int(round(clip.duration * fps)))
        out = []
        for i in range(n):
            p = clip.sample(clip.duration * i / max(n - 1, 1), rig)
            p.pop("betas")
            out.append(p)
        return out
    path = Path(spec)
    if not path.is_file():
        raise ValueError(f"motion {spec!r} is neither a built-in clip (demo, rest) nor a file")
    if path.suffix == ".json":
        data = json.loads(path.read_text())
        if not isinstance(data, list) or not all(isinstance(d, dict) for d in data):
            raise ValueError(f"{path}: expected a JSON list of per-frame parameter objects")
        seq = [{k: np.asarray(v, dtype=np.float64) for k, v in d.items()} for d in data]
    elif path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
        lengths = {len(v) for v in arrays.values()}
        if len(lengths) != 1:
            raise ValueError(f"{path}: arrays disagree on the number of frames: {lengths}")
        seq = [{k: v[i] for k, v in arrays.items()} for i in range(lengths.pop())]
    else:
        raise ValueError(f"{path}: motion files are .json or .npz")
    return seq[:frames] if frames else seq


def cameras_for(spec: str, n: int, size: int, target: np.ndarray) -> list[Camera]:
    """'orbit' (a half-circle sweep around the upper body) or a JSON camera / list of cameras."""
    if spec == "orbit":
        return [orbit(target, yaw_deg=-60.0 + 120.0 * i / max(n - 1, 1), pitch_deg=5.0,
                      distance=2.7, width=size, height=size, fov_y_deg=30.0) for i in range(n)]
    data = json.loads(Path(spec).read_text())
    cams = [Camera.from_dict(d) for d in (data if isinstance(data, list) else [data])]
    if len(cams) == 1:
        cams = cams * n
    if len(cams) != n:
        raise ValueError(f"{spec}: {len(cams)} cameras for {n} frames")
    return [c.resized(size, size * c.height // c.width) if c.width != size else c for c in cams]


def render_frames(loaded: LoadedAvatar, params: list[dict], cameras: list[Camera],
                  request: RenderRequest) -> Iterator[np.ndarray]:
    """uint8 RGB frames [H, W, 3]."""
    with torch.no_grad():
        for p, cam in zip(params, cameras, strict=True):
            posed = loaded.animator.pose(p)
            rgb = rasterize(posed.gaussians, cam, request).rgb
            yield (rgb.clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()


def write_frames(frames: Iterator[np.ndarray], out: Path, fps: float, total: int,
                 progress: Callable[[int, int], None] | None = None) -> Path:
    """uint8 RGB frames as PNGs into a folder, or as an .mp4."""
    as_video = out.suffix.lower() == ".mp4"
    if not as_video:
        out.mkdir(parents=True, exist_ok=True)
    with Mp4Writer(out, fps) as video:
        for i, frame in enumerate(frames):
            if as_video:
                video.write(frame)
            elif not cv2.imwrite(str(out / f"frame_{i:05d}.png"), frame[..., ::-1]):
                raise OSError(f"could not write {out / f'frame_{i:05d}.png'}")
            if progress:
                progress(i + 1, total)
    return out


def render_sequence(avatar: str, motion: str, camera: str, out: Path, *, size: int = 512,
                    fps: float = 25.0, frames: int | None = None, model_dir: Path | None = None,
                    request: RenderRequest | None = None,
                    progress: Callable[[int, int], None] | None = None) -> Path:
    loaded = load_avatar(avatar, model_dir)
    params = motion_frames(motion, loaded, fps, frames)
    target = loaded.animator.body_model.joint_template[12].cpu().numpy() - np.array([0, 0.2, 0])
    cams = cameras_for(camera, len(params), size, target)
    req = request or RenderRequest()
    return write_frames(render_frames(loaded, params, cams, req), out, fps, len(params), progress)

