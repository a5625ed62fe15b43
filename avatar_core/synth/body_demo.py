"""A short animation of the posed synthetic upper body, for a person to look at.

The synthetic model family is generated (or reused from a cache folder), the upper-body model
goes through gestures and expressions, and a z-buffer mesh renderer draws each frame.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import torch

from ..body.model_data import load_smplx
from ..body.upper_body import UpperBodyModel, load_segmentation
from ..render.camera import look_at
from .mesh_render import render_mesh
from .model_files import GENERATOR_VERSION, SyntheticModelFiles, write_synthetic_models
from .motion import Clip, Pose, Rig, Track, chain
from .video import Mp4Writer


def default_model_dir(seed: int = 0) -> Path:
    base = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
    return base / "telesplat" / f"synthetic-seed{seed}"


def ensure_models(model_dir: Path | None = None, seed: int = 0) -> SyntheticModelFiles:
    """The synthetic model files in `model_dir`, written first if they are not there yet or
    were written by another generator version (an old cache lacks newer gestures)."""
    files = SyntheticModelFiles(model_dir or default_model_dir(seed))
    if generator_version(files) != GENERATOR_VERSION:
        _rewrite(files.root, seed)
    return files


def generator_version(files: SyntheticModelFiles) -> int | None:
    """The generator version a folder's manifest records; None without a readable manifest."""
    try:
        version = json.loads(files.manifest.read_text()).get("generator_version")
    except (OSError, ValueError, AttributeError):
        return None
    return version if isinstance(version, int) else None


def _rewrite(root: Path, seed: int) -> None:
    """Write the family into a scratch folder inside `root`, then move each file into place
    (atomic per file, the manifest last): a process reading the cache meanwhile never sees a
    half-written file, and other files in `root` are left alone."""
    root.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".writing-", dir=root) as scratch:
        write_synthetic_models(scratch, seed=seed)
        names = sorted(p.relative_to(scratch) for p in Path(scratch).rglob("*") if p.is_file())
        names.sort(key=lambda rel: rel.name == "manifest.json")  # stable: the manifest last
        for rel in names:
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            os.replace(Path(scratch) / rel, root / rel)


def demo_clip() -> Track:
    """Gestures and expressions, about eleven seconds long."""
    look = {"neck": (0.0, 0.0, 0.0)}
    wave_up = {"left_shoulder": (0.0, 0.0, 0.35), "left_elbow": (0.0, -0.3, 1.6)}
    wave_a = {**wave_up, "left_wrist": (0.0, 0.0, 0.35)}
    wave_b = {**wave_up, "left_wrist": (0.0, 0.0, -0.35)}
    show = {"right_shoulder": (0.0, 0.0, 1.0), "right_elbow": (0.0, 2.1, 0.0),
            "right_wrist": (-0.3, 0.0, 0.0)}
    face = Clip("face", (
        (0.0, Pose(look)),
        (0.8, Pose(look, {"smile": 1.0})),
        (1.6, Pose({"jaw": (0.35, 0.0, 0.0)}, {"lips_part": 0.8})),
        (2.4, Pose(look, {"blink_left": 1.0, "blink_right": 1.0, "brows_raise": 0.3})),
        (3.0, Pose(look, {"brows_raise": 1.2, "pucker": 0.8})),
        (3.8, Pose({"head": (0.0, 0.45, 0.0)}, {"cheek_puff": 1.0, "brows_lower": 0.8})),
        (4.6, Pose({"head": (0.0, -0.45, 0.1)}, {"frown": 1.0, "grin": 0.0})),
    ))
    hands = Clip("hands", (
        (0.0, Pose(wave_a, left_hand="spread")),
        (0.4, Pose(wave_b, left_hand="spread")),
        (0.8, Pose(wave_a, left_hand="spread")),
        (1.2, Pose(wave_b, {"grin": 0.8}, left_hand="spread")),
        (2.0, Pose(show, {"smile": 0.8}, right_hand="thumbs_up")),
        (2.8, Pose(show, right_hand="peace")),
        (3.6, Pose(show, right_hand="point")),
        (4.4, Pose(show, right_hand="fist")),
        (5.2, Pose(look)),
    ))
    return chain("body demo", [face, hands])


def model_rig(files: SyntheticModelFiles, model: UpperBodyModel) -> Rig:
    """Expression names, gestures and hand means of a synthetic model, for pose descriptions."""
    manifest = json.loads(files.manifest.read_text())
    with np.load(files.gestures) as g:
        gestures = {k: g[k] for k in g.files}
    means = {s: getattr(model, f"{s}_hand_mean").cpu().numpy() for s in ("left", "right")}
    return Rig(tuple(manifest["expression_names"]), gestures, means, model.num_betas)


def render_demo(out: Path, *, model_dir: Path | None = None, frames: int = 96, size: int = 384,
                fps: int = 24, identity: int = 0,
                progress: Callable[[int, int], None] | None = None) -> Path:
    """Render the demo to an .mp4 video or a .png strip of frames; returns the path written."""
    if frames < 1 or size < 16:
        raise ValueError("frames must be >= 1 and size >= 16")
    files = ensure_models(model_dir)
    identities = files.identities()
    if not 0 <= identity < len(identities):
        raise ValueError(f"identity must be in [0, {len(identities)})")
    data = load_smplx(files.smplx_npz)
    model = UpperBodyModel(data, load_segmentation(files.segmentation, data.num_vertices),
                           dtype=torch.float32)
    with np.load(identities[identity]) as ident:
        betas, colors = ident["betas"], ident["vertex_colors"][model.vertex_ids]
    rig, clip = model_rig(files, model), demo_clip()
    head = data.joint_template[15]
    camera = look_at(eye=(0.6, head[1] + 0.05, 2.6), target=(0.0, head[1] - 0.28, 0.0),
                     width=size, height=size, fov_y_deg=32.0)
    faces = model.faces.cpu().numpy()
    images = []
    with torch.no_grad():
        for i in range(frames):
            t = clip.duration * i / max(frames - 1, 1)
            params = clip.sample(t, rig)
            params["betas"] = betas
            verts = model(params).vertices[0].cpu().numpy()
            rgb = render_mesh(verts, faces, camera, vertex_colors=colors,
                              background=(0.93, 0.94, 0.96)).rgb
            images.append((np.clip(rgb, 0, 1) * 255).astype(np.uint8))  # RGB
            if progress:
                progress(i + 1, frames)
    return _write(out, images, fps)


def _write(out: Path, images: list[np.ndarray], fps: int) -> Path:
    """An .mp4 of all frames, or a .png strip of up to 8 of them. images: uint8 RGB."""
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.suffix.lower() == ".png":
        step = max(1, len(images) // 8)
        strip = np.concatenate(images[::step][:8], axis=1)
        if not cv2.imwrite(str(out), strip[..., ::-1]):
            raise OSError(f"could not write {out}")
        return out
    if out.suffix.lower() != ".mp4":
        raise ValueError(f"output must be .mp4 or .png, got {out.suffix}")
    with Mp4Writer(out, fps) as writer:
        for img in images:
            writer.write(img)
    return out
