"""`telesplat track build-embedding`: the learned landmark embedding, built in the studio.

Several synthetic identities (one family, one topology, their own betas) play library clips
in front of the webcam at several yaws and two framings (waist-up, head-and-shoulders); each
frame is rendered, tracked by the live tracker and paired with the true model points. The
offsets are fitted on the training identities and clips (`embedding_solve`) and validated
on identities and clips they never saw (per-landmark px error before / after, stored in the
asset's metadata). Seeded: the same spec gives the same asset.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..body.skeleton import SMPLX_PARENTS
from ..track.fit import correspondence as cor
from ..track.fit.camera import WebcamCamera
from ..track.fit.embedding import LandmarkEmbedding, anchor_joints
from ..track.fit.fitter import FrameFitter
from . import embedding_solve as solve
from .embedding_spec import FRAMINGS, BuildSpec
from .model_writer import synthetic_family


class _Studio:
    """One identity in front of the webcam: renders, tracks, and gives the truth."""

    def __init__(self, root: Path, identity: int, tracker, camera) -> None:
        from ..gaussians.animate import synthetic_package
        from ..motion.rig import model_rig
        from .actor import Actor
        from .model_writer import BodyModelFiles
        from .tracking_eval.scene import background

        files = BodyModelFiles(root)
        self.actor = Actor.load(files, identity)
        package, model = synthetic_package(root, identity)
        self.rig = model_rig(files, self.actor.model)
        self.fitter = FrameFitter(model, np.asarray(package.body.betas))
        self.tracker, self.camera = tracker, camera
        self.bg = background(camera.width, camera.height, "noise", seed=7 + identity)
        self.anchors = anchor_joints()

    def sample(self, clip: str, yaw_deg: float, framing: str, rng: np.random.Generator,
               supersample: int) -> dict[str, np.ndarray]:
        from ..motion.library import motion_sequence
        from ..track.fit.observations import all_landmarks
        from .tracking_eval.scene import render_frame, subject_transl

        track = motion_sequence([clip])
        p = track.sample(float(rng.uniform(0.15, 0.85)) * track.duration, self.rig)
        turn = Rotation.from_rotvec([0.0, math.radians(yaw_deg), 0.0])
        p["global_orient"] = (turn * Rotation.from_rotvec(p["global_orient"])).as_rotvec()
        p["transl"] = subject_transl(self.actor, self.camera, FRAMINGS[framing])
        p["betas"] = np.asarray(self.actor.betas, dtype=np.float64)
        self.tracker.reset()
        frame = render_frame(self.actor, p, self.camera, self.bg, 2 / 255, rng, supersample)
        result = self.tracker.track(frame)
        obs = all_landmarks(result)
        f = self.fitter
        x = f.pack({k: v for k, v in p.items() if k != "betas"})
        points, _ = f._keypoints(x, False)
        rw = f.kinematics.world_rotations(f.full_pose(x))
        rot = np.where((self.anchors >= 0)[:, None, None], rw[np.maximum(self.anchors, 0)],
                       np.eye(3))
        world = np.full((cor.NUM_POSE, 3), np.nan) if obs.world is None else obs.world
        return {"pixels": obs.pixels, "weights": obs.weights, "points": points,
                "rotations": rot, "image_z": obs.depth, "world": world,
                "params": x, "poses": f.full_pose(x)}


def collect(spec: BuildSpec, identities: Sequence[int], clips: Sequence[str], root: Path,
            progress: Callable[[], None] | None = None) -> tuple[solve.Samples, dict]:
    """Render and track every (identity, clip, yaw, framing) x frames_per_view; the samples
    and the raw arrays (with each frame's true free variables `params` and its `label`)."""
    from ..track.tracker import Tracker
    from .tracking_eval.scene import webcam_camera

    render_camera = webcam_camera()
    camera = WebcamCamera(render_camera.width, render_camera.height, 60.0)
    tracker = Tracker(threads=1, iris=False)
    rows, labels = [], []
    for identity in identities:
        studio = _Studio(root, identity, tracker, render_camera)
        for _, clip, yaw, framing in spec.jobs([identity], clips):
            rng = np.random.default_rng([spec.seed, identity, *clip.encode(),
                                         int(yaw) + 360, len(framing)])
            for _ in range(spec.frames_per_view):
                rows.append(studio.sample(clip, yaw, framing, rng, spec.supersample))
                labels.append((identity, clip, yaw, framing))
                if progress:
                    progress()
    stack = {k: np.stack([r[k] for r in rows]) for k in rows[0]}
    stack["label"] = np.array([f"{i}:{c}:{y:g}:{f}" for i, c, y, f in labels])
    return samples_from_arrays(stack, camera), stack


def samples_from_arrays(arrays: dict, camera: WebcamCamera, prefix: str = "") -> solve.Samples:
    a = {k[len(prefix):]: v for k, v in arrays.items() if k.startswith(prefix)}
    groups = np.array([int(str(lab).split(":")[0]) for lab in a["label"]])
    return solve.Samples(a["pixels"], a["weights"], a["points"], a["rotations"], a["image_z"],
                         a["world"], camera, a["poses"], groups)


def build_embedding(spec: BuildSpec, model_dir: Path | None = None,
                    progress: Callable[[], None] | None = None,
                    samples_out: Path | None = None, samples_in: Path | None = None
                    ) -> tuple[LandmarkEmbedding, dict]:
    """The embedding and its report (validation tables, z scales, counts); `samples_out`:
    also write the studio samples there (npz: train_* and held_* arrays) for benchmarks;
    `samples_in`: fit on such a file instead of filming (the spec is then only recorded)."""
    from .tracking_eval.scene import webcam_camera

    render_camera = webcam_camera()
    camera = WebcamCamera(render_camera.width, render_camera.height, 60.0)
    if samples_in is not None:
        with np.load(samples_in) as data:
            arrays = {k: data[k] for k in data.files}
        root = Path(str(arrays.pop("family")))
    else:
        root = synthetic_family(max(*spec.train_identities, *spec.held_out_identities, 0) + 1,
                       model_dir)
        _, raw = collect(spec, spec.train_identities, spec.train_clips, root, progress)
        arrays = {f"train_{k}": v for k, v in raw.items()}
        if spec.held_out_identities and spec.held_out_clips:
            _, raw = collect(spec, spec.held_out_identities, spec.held_out_clips, root,
                             progress)
            arrays.update({f"held_{k}": v for k, v in raw.items()})
    if samples_out is not None:
        Path(samples_out).parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(samples_out, family=str(root), **arrays)
    train = samples_from_arrays(arrays, camera, "train_")
    held = samples_from_arrays(arrays, camera, "held_") if "held_label" in arrays else None
    anchors = anchor_joints()
    parents = np.asarray(SMPLX_PARENTS)
    offset, basis, count, modes, cv = solve.fit_offsets(train, anchors, parents,
                                                        min_samples=spec.min_samples)
    f_train = solve.pose_features(train, anchors, parents)
    scales = solve.z_scales(train, offset, basis, f_train)
    report = {"spec": asdict(spec), "train_frames": len(train),
              "train_samples_per_row": {solve.row_name(k): int(c) for k, c in enumerate(count)
                                        if c},
              "mode_per_row": {solve.row_name(k): m for k, m in enumerate(modes) if count[k]},
              "cross_validated_median_px": cv, "z": scales,
              "train": solve.per_landmark_table(train, offset, basis, f_train)}
    if held is not None:
        f_held = solve.pose_features(held, anchors, parents)
        report["held_out_frames"] = len(held)
        report["held_out"] = solve.per_landmark_table(held, offset, basis, f_held)
        report["held_out_z"] = solve.z_scales(held, offset, basis, f_held)
    clip = lambda v: float(np.clip(v, 0.1, 10.0))  # noqa: E731
    emb = LandmarkEmbedding(anchors, offset, clip(scales["world_z_scale"]),
                            clip(scales["image_z_scale"]), report,
                            basis if np.abs(basis).max(initial=0) > 0 else None)
    return emb, report
