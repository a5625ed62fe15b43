"""The webcam protocol: what a viewer sees when a webcam drives the avatar.

``evaluate_webcam(avatar, dataset)`` (``telesplat eval AVATAR DATASET --protocol webcam``)
takes a held-out take (the ``self_reenactment`` split; without one, ``novel_view``'s takes)
and, frame by frame:

1. the *webcam* camera's image (default: the centre front camera) goes through the live path
   of ``server/stream/tracking.py``: JPEG, ``decode_image``, the live ``Tracker`` (one thread per
   model, palm search every ``LIVE_PALM_INTERVAL`` frames, irises), ``SequenceFit`` on the
   avatar's body model and betas (One Euro smoothing, hold/relax), ``drive_params`` (no
   ``transl``: the avatar stays at its own place, as on the server). Two things the server
   cannot know are taken from the studio's calibration: the webcam's field of view and its
   orientation (the fitted ``global_orient`` is relative to the webcam; it is turned into the
   studio's world, as a viewer's avatar faces the way its performer faces the webcam);
2. the avatar is posed with those parameters and rendered at the *score* camera (default: the
   front camera nearest 30 deg from the webcam), scored against that camera's image exactly as
   :func:`avatar_core.metrics.evaluate.evaluate` scores a view;
3. beside it, the same avatar at the same camera driven by the true parameters (the capture's
   ``true_params.npz`` where it has one, else the fused dataset parameters, which the plain
   simulated trackers make equal to the truth) and by the simulated trackers + fusion (the
   dataset's parameters, fused), so avatar error and tracking error separate; and, as a
   diagnostic, the webcam's parameters with the true root orientation (``global_orient``, which
   a monocular fit of an upper body sees worst and which, without ``transl``, moves the whole
   upper body).

AKD is against the true body (body-model keypoints at the score camera); TJE per drive over
consecutive evaluated frames. Latency: the live path per frame (tracking = JPEG decode +
landmarks, fitting, posing, rendering; medians and p95 after the first frame, which warms
the models up).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from scipy.spatial.transform import Rotation

from ..body.fusion import FusionModels, fuse_sequence
from ..body.skeleton import JOINT, SMPLX_PARENTS
from ..dataset import Dataset, load_dataset
from ..dataset.preview import write_png
from ..gaussians.loading import LoadedAvatar, load_avatar, mano_models
from ..render.camera import Camera
from ..render.rasterize import rasterize
from ..render.types import RenderRequest
from .evaluate import (
    _at_size,
    _check_body_model,
    _output_row,
    _TemporalJitter,
    blank_excluded,
    estimate_background,
    evaluation_mask,
    image_scores,
)
from .keypoints import GROUPS, body_akd
from .report import _fmt, _json_safe, side_by_side, write_report

__all__ = ["DRIVES", "WebcamResult", "evaluate_webcam", "true_params_path", "webcam_cameras",
           "webcam_markdown", "write_webcam_result"]

DRIVES = ("true", "trackers", "webcam", "webcam_true_root")
DRIVE_LABELS = {"true": "true parameters", "trackers": "simulated trackers + fusion",
                "webcam": "webcam tracking (live config)",
                "webcam_true_root": "webcam tracking, true root orientation"}
# World-rotation errors (deg) of the joints the table names, against the truth.
ANGLE_JOINTS = {"deg_root": ("pelvis",), "deg_shoulders": ("left_shoulder", "right_shoulder"),
                "deg_elbows": ("left_elbow", "right_elbow"), "deg_neck_head": ("head",)}
METRICS = ("psnr", "ssim", "l1", "akd_face", "akd_hands", "akd_torso", *ANGLE_JOINTS, "tje")
STAGES = ("track", "fit", "pose", "render")
JPEG_QUALITY = 90        # what a browser / client sends the server
SCORE_ANGLE_DEG = 30.0   # default score camera: the front camera nearest this from the webcam
TRUE_PARAMS_NPZ = "true_params.npz"
OPENCV_FROM_MODEL = np.diag([1.0, -1.0, -1.0])  # track.fit.camera: y and z flipped

Progress = Callable[[int, int], None]


def true_params_path(dataset_root: str | Path, sequence: str) -> Path:
    """Where a noisy-tracker capture keeps a sequence's true SMPL-X parameters."""
    return Path(dataset_root) / "sequences" / sequence / TRUE_PARAMS_NPZ


@dataclass
class WebcamResult:
    avatar: str
    dataset: str
    sequences: list[str]
    webcam_camera: str
    score_camera: str
    image_size: list[int]                  # [H, W] scored at
    num_frames: int
    frame_stride: int
    drives: dict[str, dict[str, float | None]]   # drive -> METRICS
    latency_ms: dict[str, dict[str, float]]      # stage -> median, p95
    seen: dict[str, float]                 # landmark group -> fraction of frames seen
    truth: str                             # where the true parameters came from
    notes: dict[str, str] = field(default_factory=dict)
    images: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return _json_safe(asdict(self))


# -- cameras and parameters ----------------------------------------------------------------


@dataclass
class WebcamFrame:
    """One frame of the webcam protocol: the webcam's parameters (the root in the studio's
    world, as scored), the truth, what the tracker observed, and the webcam."""

    key: Any
    webcam: dict[str, np.ndarray]
    truth: dict[str, np.ndarray]
    observations: Any   # track.fit.observations.Observations
    camera: Camera


def _view_dir(cam: Camera) -> np.ndarray:
    return cam.R[2]  # the optical axis in the world (R: world -> camera, OpenCV)


def webcam_cameras(ds: Dataset, webcam: str | None = None, score: str | None = None
                   ) -> tuple[str, str]:
    """(webcam, score) camera names; defaults in the module docstring."""
    cams = ds.cameras
    front = [n for n, c in cams.items() if getattr(c, "role", None) == "front"] or list(cams)
    for name in (webcam, score):
        if name is not None and name not in cams:
            raise ValueError(f"unknown camera {name!r}; the dataset has {sorted(cams)}")
    webcam = webcam or front[len(front) // 2]
    if score is None:
        axis = _view_dir(cams[webcam].camera)
        others = [n for n in front if n != webcam] or [n for n in cams if n != webcam]
        if not others:
            raise ValueError("the webcam protocol needs a second camera to score at")

        def off(n: str) -> float:
            cos = float(np.clip(axis @ _view_dir(cams[n].camera), -1.0, 1.0))
            return abs(math.degrees(math.acos(cos)) - SCORE_ANGLE_DEG)
        score = min(others, key=off)
    if score == webcam:
        raise ValueError("the score camera must differ from the webcam")
    return webcam, score


def _take(ds: Dataset) -> tuple[str, list[str]]:
    for split in ("self_reenactment", "novel_view"):
        if split in ds.splits and ds.splits[split].sequences:
            return split, list(ds.splits[split].sequences)
    raise ValueError(f"dataset {ds.root} has no self_reenactment or novel_view take")


def _truth(ds: Dataset, seq: str, tracked: dict[str, np.ndarray]) -> tuple[dict, str]:
    path = true_params_path(ds.root, seq)
    if not path.is_file():
        return tracked, "the fused dataset parameters (no true_params.npz)"
    with np.load(path) as raw:
        arrays = {k: np.asarray(raw[k], dtype=np.float64) for k in raw.files}
    return fuse_sequence(arrays, ds.sequences[seq], None)[0], "true_params.npz"


def _webcam_to_world(webcam: Camera) -> Rotation:
    """The fit's camera frame (x right, y up, z toward the camera) to the studio's world."""
    return Rotation.from_matrix(webcam.R.T @ OPENCV_FROM_MODEL)


def _world_orient(global_orient: np.ndarray, webcam: Camera) -> np.ndarray:
    """The fitted root rotation (relative to the webcam) in the studio's world."""
    return (_webcam_to_world(webcam) * Rotation.from_rotvec(global_orient)).as_rotvec()


def webcam_orient(global_orient: np.ndarray, webcam: Camera) -> np.ndarray:
    """A root in the studio's world (rotation vector) relative to the webcam, in the fit's
    camera frame: `_world_orient`'s inverse."""
    return (_webcam_to_world(webcam).inv() * Rotation.from_rotvec(global_orient)).as_rotvec()


def _fov_x_deg(cam: Camera) -> float:
    return math.degrees(2 * math.atan(0.5 * cam.width / cam.K[0, 0]))


def _live_tracking(loaded: LoadedAvatar, webcam: Camera, fit_config=None):
    """The server's tracker and fit (server/stream/tracking.py SessionTracker._ensure), with the
    webcam's own field of view. Raises RuntimeError with the reason when it cannot run."""
    try:
        from ..track.fit.sequence import SequenceFit, live_config
        from ..track.tracker import LIVE_PALM_INTERVAL, Tracker

        tracker = Tracker(threads=1, palm_interval=LIVE_PALM_INTERVAL, iris=True)
    except (ImportError, RuntimeError, OSError, ValueError) as exc:
        raise RuntimeError(f"webcam tracking is not available: {exc} (the MediaPipe "
                           "models: telesplat track fetch-models)") from exc
    betas = np.asarray(loaded.package.body.betas, dtype=np.float64)
    config = live_config(fov_x_deg=_fov_x_deg(webcam))
    if fit_config is not None:
        config.fit = fit_config
    fit = SequenceFit(loaded.animator.body_model, betas if betas.size else None, config)
    return tracker, fit


def _jpeg(rgb: np.ndarray) -> bytes:
    bgr = (np.clip(rgb[..., ::-1], 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes()


# -- the evaluation ------------------------------------------------------------------------


@dataclass
class _Scorer:
    """Pose, render and score one drive's frames at the score camera."""

    loaded: LoadedAvatar
    camera: Camera
    request: RenderRequest
    stride: int
    records: dict[str, list[dict[str, float]]] = field(default_factory=dict)
    jitter: dict[str, _TemporalJitter] = field(default_factory=dict)
    pose_ms: list[float] = field(default_factory=list)
    render_ms: list[float] = field(default_factory=list)

    def score(self, drive: str, key, params: Mapping[str, np.ndarray], truth_out,
              gt: np.ndarray, keep: np.ndarray, truth: Mapping[str, np.ndarray]) -> np.ndarray:
        t0 = time.perf_counter()
        posed = self.loaded.animator.pose(dict(params))
        t1 = time.perf_counter()
        render = rasterize(posed.gaussians, self.camera, self.request).rgb
        t2 = time.perf_counter()
        if drive == "webcam":
            self.pose_ms.append((t1 - t0) * 1e3)
            self.render_ms.append((t2 - t1) * 1e3)
        pred = render.clamp(0.0, 1.0).cpu().numpy().astype(np.float32)
        bg = self.request.background
        gt_b, pred_b = blank_excluded(gt, keep, bg), blank_excluded(pred, keep, bg)
        rec = {k: v for k, v in image_scores(pred_b, gt_b, keep).items() if v is not None}
        batch = {k: np.asarray(v)[None] for k, v in params.items()}
        driven_out = self.loaded.animator.body_model(batch)
        rec.update({f"akd_{g}": v for g, v in
                    body_akd(driven_out, truth_out, self.camera).items()})
        rec.update(joint_angle_errors(params, truth))
        self.records.setdefault(drive, []).append(rec)
        self.jitter.setdefault(drive, _TemporalJitter(self.stride)).add(key, pred_b, gt_b, keep)
        return pred


def world_rotations(params: Mapping[str, np.ndarray]) -> np.ndarray:
    """[22, 3, 3] world rotations of the body joints (root and body_pose; no hands)."""
    local = np.concatenate([np.asarray(params["global_orient"], dtype=np.float64).reshape(1, 3),
                            np.asarray(params["body_pose"], dtype=np.float64).reshape(-1, 3)])
    rot = Rotation.from_rotvec(local[:22]).as_matrix()
    out = rot.copy()
    for j in range(1, 22):
        out[j] = out[SMPLX_PARENTS[j]] @ rot[j]
    return out


def joint_angle_errors(params: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray]
                       ) -> dict[str, float]:
    """`ANGLE_JOINTS` -> mean world-rotation error (deg) of its joints."""
    a, b = world_rotations(params), world_rotations(truth)
    out = {}
    for key, joints in ANGLE_JOINTS.items():
        errs = []
        for name in joints:
            r = a[JOINT[name]].T @ b[JOINT[name]]
            errs.append(math.degrees(math.acos(float(np.clip((np.trace(r) - 1) / 2, -1, 1)))))
        out[key] = float(np.mean(errs))
    return out


def _stats(values: list[float]) -> dict[str, float]:
    if not values:
        return {"median": float("nan"), "p95": float("nan")}
    return {"median": float(np.median(values)), "p95": float(np.percentile(values, 95))}


def _summary(scorer: _Scorer) -> dict[str, dict[str, float | None]]:
    out = {}
    for drive in DRIVES:
        recs = scorer.records.get(drive, [])
        row: dict[str, float | None] = {}
        for k in METRICS[:-1]:
            vals = [r[k] for r in recs if k in r and np.isfinite(r[k])]
            row[k] = float(np.mean(vals)) if vals else None
        pairs = [v for vs in scorer.jitter[drive].pairs.values() for v in vs] \
            if drive in scorer.jitter else []
        row["tje"] = float(np.mean(pairs)) if pairs else None
        out[drive] = row
    return out


def evaluate_webcam(avatar: str | Path | LoadedAvatar, dataset: str | Path | Dataset, *,
                    webcam_camera: str | None = None, score_camera: str | None = None,
                    frame_stride: int = 1, max_frames: int | None = None,
                    size: int | None = None, out_dir: str | Path | None = None,
                    max_images: int = 4, model_dir: Path | None = None,
                    progress: Progress | None = None, fit_config=None,
                    on_frame: Callable[[WebcamFrame], None] | None = None) -> WebcamResult:
    """The webcam protocol (module docstring); writes ``webcam.json`` / ``webcam.md`` and
    ``images/`` (ground truth | webcam-driven render | error) with ``out_dir``. `fit_config`:
    the live fit's `FitConfig` (default: as the server runs it), e.g. with the learned
    landmark embedding and the 3D cues. `on_frame`: called with each frame's
    :class:`WebcamFrame` (diagnostics: bench/webcam_root.py)."""
    if frame_stride < 1 or (max_frames is not None and max_frames < 1) or max_images < 0:
        raise ValueError("frame_stride and max_frames must be at least 1, max_images >= 0")
    ds = dataset if isinstance(dataset, Dataset) else load_dataset(dataset)
    _check_body_model(ds.meta["body_model"])
    split, sequences = _take(ds)
    webcam_name, score_name = webcam_cameras(ds, webcam_camera, score_camera)
    src_frames = ds.source(split).sequences
    frames = [(s, f) for s in sequences for f in range(0, src_frames[s], frame_stride)]
    frames = frames[:max_frames]
    loaded = avatar if isinstance(avatar, LoadedAvatar) else load_avatar(str(avatar), model_dir)
    webcam_cam = ds.cameras[webcam_name].camera
    tracker, sequence_fit = _live_tracking(loaded, webcam_cam, fit_config)
    from ..track.fit.observations import from_track_result
    from ..track.fit.sequence import GROUPS as TRACK_GROUPS
    from ..track.fit.sequence import drive_params
    from ..track.image import decode_image

    src = ds.source(split)  # the split's views may live in another dataset
    first = src.view(frames[0][0], frames[0][1], score_name)
    score_cam = _at_size(first, evaluation_mask(first), size)[2]
    scorer = _Scorer(loaded, score_cam, RenderRequest(background=estimate_background(first)),
                     frame_stride)
    fusion = FusionModels(loaded.animator.body_model, mano_models(loaded))
    betas = np.asarray(loaded.package.body.betas, dtype=np.float64)
    track_ms: list[float] = []
    fit_ms: list[float] = []
    seen = dict.fromkeys(TRACK_GROUPS, 0)
    images: list[str] = []
    truth_source = ""
    cache: dict[str, tuple[dict, dict]] = {}
    fps = float(ds.meta.get("fps") or 30.0)
    try:
        with torch.no_grad():
            rasterize(loaded.animator.pose({}).gaussians, score_cam, scorer.request)  # warm-up
            for i, (seq, frame) in enumerate(frames):
                if seq not in cache:
                    raw = src.params(seq)
                    tracked = fuse_sequence(raw, src.sequences[seq], fusion, strict=True)[0]
                    truth, truth_source = _truth(src, seq, tracked)
                    cache[seq] = (truth, tracked)
                    sequence_fit.reset()
                    tracker.reset()
                truth, tracked = cache[seq]
                t0 = time.perf_counter()
                image = decode_image(_jpeg(src.view(seq, frame, webcam_name).rgb))
                result = tracker.track(image)
                t1 = time.perf_counter()
                observations = from_track_result(result)
                fitted = sequence_fit.step(observations, frame / fps)
                t2 = time.perf_counter()
                if i:  # the first frame warms the models up
                    track_ms.append((t1 - t0) * 1e3)
                    fit_ms.append((t2 - t1) * 1e3)
                seen.update({g: seen[g] + bool(fitted.seen.get(g)) for g in seen})
                webcam = drive_params(fitted.params)
                webcam["global_orient"] = _world_orient(webcam["global_orient"], webcam_cam)
                if betas.size:
                    webcam["betas"] = betas
                view = src.view(seq, frame, score_name)
                gt, keep, _ = _at_size(view, evaluation_mask(view), size)
                true_row = {k: v[frame] for k, v in truth.items()}
                truth_out = _output_row(loaded.animator.body_model(
                    {k: np.asarray(v)[None] for k, v in true_row.items()}), 0)
                key = view.key
                scorer.score("true", key, true_row, truth_out, gt, keep, true_row)
                scorer.score("trackers", key, {k: v[frame] for k, v in tracked.items()},
                             truth_out, gt, keep, true_row)
                pred = scorer.score("webcam", key, webcam, truth_out, gt, keep, true_row)
                if on_frame is not None:
                    on_frame(WebcamFrame(key, webcam, true_row, observations, webcam_cam))
                # the root is what a monocular fit of an upper body sees worst: this row
                # shows how much of the webcam's error is the rest (a diagnostic, not live)
                scorer.score("webcam_true_root", key,
                             {**webcam, "global_orient": true_row["global_orient"]},
                             truth_out, gt, keep, true_row)
                if out_dir is not None and len(images) < max_images and \
                        i % max(1, len(frames) // max(max_images, 1)) == 0:
                    name = f"images/{seq}_{frame:05d}_{score_name}.png"
                    write_png(Path(out_dir) / name, side_by_side(gt, pred, keep))
                    images.append(name)
                if progress:
                    progress(i + 1, len(frames))
    finally:
        tracker.close()
    latency = {"track": _stats(track_ms), "fit": _stats(fit_ms),
               "pose": _stats(scorer.pose_ms[1:]), "render": _stats(scorer.render_ms[1:])}
    total = [sum(t) for t in zip(track_ms, fit_ms, scorer.pose_ms[1:], scorer.render_ms[1:],
                                 strict=True)]
    latency["live path"] = _stats(total)
    result = WebcamResult(
        avatar=loaded.package.name, dataset=ds.name, sequences=sequences,
        webcam_camera=webcam_name, score_camera=score_name,
        image_size=[score_cam.height, score_cam.width], num_frames=len(frames),
        frame_stride=frame_stride, drives=_summary(scorer), latency_ms=latency,
        seen={g: n / len(frames) for g, n in seen.items()}, truth=truth_source,
        notes={"split": f"the take of the {split!r} split",
               "webcam": f"{webcam_name} at {webcam_cam.width}x{webcam_cam.height}, JPEG "
                         f"quality {JPEG_QUALITY}, field of view {_fov_x_deg(webcam_cam):.1f} "
                         "deg (from the calibration)",
               "akd": "body-model keypoints at the score camera, against the true body",
               "latency": "ms per frame after the first; track = JPEG decode + landmarks, "
                          "live path = track + fit + pose + render, each frame on one "
                          "thread (the server overlaps them across sessions)"},
        images=images)
    if out_dir is not None:
        write_webcam_result(result, out_dir)
    return result


def webcam_markdown(result: WebcamResult) -> str:
    h, w = result.image_size
    lines = [f"# {result.avatar}: webcam protocol on {result.dataset}", "",
             f"Take {', '.join(result.sequences)}: {result.num_frames} frames (stride "
             f"{result.frame_stride}); webcam {result.webcam_camera}, scored at "
             f"{result.score_camera} ({w}x{h}); truth: {result.truth}.", "",
             "| drive | PSNR (dB) | SSIM | L1 | AKD face / hands / torso (px) "
             "| root / shoulders / elbows / neck-head (deg) | TJE |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for drive, row in result.drives.items():
        akd = " / ".join(_fmt(row.get(f"akd_{g}"), f"akd_{g}") for g in GROUPS)
        angles = " / ".join("n/a" if row.get(k) is None else f"{row[k]:.1f}"
                            for k in ANGLE_JOINTS)
        lines.append(f"| {DRIVE_LABELS.get(drive, drive)} | {_fmt(row.get('psnr'), 'psnr')} "
                     f"| {_fmt(row.get('ssim'), 'ssim')} | {_fmt(row.get('l1'), 'l1')} "
                     f"| {akd} | {angles} | {_fmt(row.get('tje'), 'tje')} |")
    lines += ["", "| live path stage | median ms | p95 ms |", "|---|---:|---:|"]
    lines += [f"| {stage} | {v['median']:.1f} | {v['p95']:.1f} |"
              for stage, v in result.latency_ms.items()]
    seen = ", ".join(f"{g} {100 * v:.0f}%" for g, v in result.seen.items())
    lines += ["", f"Frames with each landmark group seen: {seen}."]
    lines += ["", "## Notes", ""] + [f"- **{k}**: {v}" for k, v in result.notes.items()]
    if result.images:
        lines += ["", "## Images (ground truth | webcam-driven | |error|)", ""]
        lines += [f"![{Path(p).stem}]({p})" for p in result.images]
    return "\n".join(lines) + "\n"


def write_webcam_result(result: WebcamResult, out_dir: str | Path) -> tuple[Path, Path]:
    """``webcam.json`` and ``webcam.md`` in ``out_dir``."""
    return write_report(out_dir, "webcam", result.to_dict(), webcam_markdown(result))
