"""Tracking on renders with known parameters: the real Tracker + FitSession on the textured
synthetic actor, against the SMPL-X parameters that posed it.

    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python bench/track_eval.py \
        [--clips smile,mouth_open,...] [--fps 30] [--max-frames N] \
        [--contact docs/track_synthetic.png] [--json out.json]

Each clip of the motion library is played on identity 0 of the synthetic family (the
capture studio's `Actor`: textured, hair, collar), placed in front of a 640x480 pinhole webcam
(60 deg horizontal field of view, at the model-space origin looking down -z: the fitter's own
camera model) framing head to waist, over a static noisy background with per-frame sensor
noise. The frames go, in order, through `Tracker` (tracking mode, one ONNX thread) and one
`FitSession` per clip (warm starts; the session's own One Euro smoothing gives the smoothed
output, its unsmoothed composition the raw one). The fitter is given the true betas.

Reported per clip and overall:

* detection rate per group: face and pose over all frames, each hand over the frames in which
  all its 21 true keypoints are inside the image;
* parameter recovery (frames where the group was detected): head rotation in the world and
  the jaw rotation (geodesic, deg); the expression-driven landmark error: the 51 static face
  landmarks in the head's frame (so head pose is factored out), fitted vs true, in mm, next to
  how far the true expression moved them from the neutral face; elbow flexion difference and
  wrist rotation in the world (deg); finger joints (mean geodesic over 15 joints, deg) next to
  the error of simply keeping the model's mean hand;
* AKD (px) of face (51 static landmarks), each hand (wrist, 15 finger joints, 5 tips) and torso
  (12 upper-body joints, `avatar_core.metrics.keypoints`), fitted vs true parameters, same
  camera, over the frames where that group was detected;
* keypoint TJE (px, `keypoint_tje`) of all those keypoints over the clip, without and with the
  session's One Euro smoothing;
* tracking + fitting time per frame (render time excluded).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from avatar_core.body import lbs  # noqa: E402
from avatar_core.body.skeleton import JOINT, LEFT_HAND_JOINTS, RIGHT_HAND_JOINTS  # noqa: E402
from avatar_core.metrics.keypoints import body_keypoints, project_keypoints  # noqa: E402
from avatar_core.metrics.temporal import keypoint_tje  # noqa: E402
from avatar_core.render.camera import Camera, look_at  # noqa: E402

WIDTH, HEIGHT, FOV_X_DEG = 640, 480, 60.0
CLIPS = ("smile", "mouth_open", "jaw_left", "shake_head", "thumbs_up", "peace", "heart",
         "clapping", "talk_animated")
HAND_SIDES = ("left", "right")
NUM_FACE_HANDS = 68 + 2 * 21  # the fitter's layout: face 68, hands 21 + 21, then pose 33
LH, RH = 68, 68 + 21  # the wrists' rows in that layout
GROUPS = ("face", "left_hand", "right_hand", "pose")
TJE_SKIP_S = 0.5  # jitter is measured after the cold start has settled


# ----------------------------------------------------------------------------- the scene


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
    from avatar_core.synth.actor import Actor
    from avatar_core.synth.body_demo import ensure_models, model_rig

    files = ensure_models()
    actor = Actor.load(files, 0)
    camera = webcam_camera()
    return Scene(actor, model_rig(files, actor.model), camera, subject_transl(actor, camera),
                 background(camera.width, camera.height, background_kind), files.root)


def clip_params(scene: Scene, name: str, fps: float, start: float = 0.0,
                max_frames: int | None = None) -> list[dict[str, np.ndarray]]:
    """The true SMPL-X parameters of a library motion sampled at `fps`, placed in the view."""
    from avatar_core.synth.motions import motion_sequence

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


# ----------------------------------------------------------------------------- evaluation


def _batch(params: list[dict[str, np.ndarray]], betas: np.ndarray) -> dict[str, torch.Tensor]:
    keys = [k for k in params[0] if k != "betas"]
    out = {k: torch.as_tensor(np.stack([np.asarray(p[k], dtype=np.float64) for p in params]))
           for k in keys}
    out["betas"] = torch.as_tensor(np.asarray(betas, dtype=np.float64))[None].expand(
        len(params), -1)
    return out


@dataclass
class Posed:
    """Evaluation quantities of a batch of parameter sets (float64 numpy)."""

    uv: dict[str, np.ndarray]       # group -> [T, K, 2] px: face, left_hand, right_hand, torso
    visible: dict[str, np.ndarray]  # group -> [T, K] inside the image
    rotations: np.ndarray           # [T, 55, 3, 3] world rotation of every joint
    full_pose: np.ndarray           # [T, 55, 3] local axis-angle (hand mean included)
    face_local: np.ndarray          # [T, 51, 3] face landmarks in the head joint's frame (m)


def evaluate_params(actor, params: list[dict[str, np.ndarray]], camera: Camera,
                    chunk: int = 32) -> Posed:
    parts: list[Posed] = []
    for s in range(0, len(params), chunk):
        with torch.no_grad():
            out = actor.model(_batch(params[s:s + chunk], actor.betas))
            kp = body_keypoints(out, fingertips=True)
            hands = kp["hands"]  # [B, 16 left + 16 right + 5 left tips + 5 right tips, 3]
            groups = {"face": kp["face"], "torso": kp["torso"],
                      "left_hand": torch.cat([hands[:, :16], hands[:, 32:37]], 1),
                      "right_hand": torch.cat([hands[:, 16:32], hands[:, 37:42]], 1)}
            uv, vis = {}, {}
            for g, pts in groups.items():
                u, v = project_keypoints(pts, camera)
                uv[g], vis[g] = u.numpy(), v.numpy()
            rot = lbs.global_rotations(lbs.rodrigues(out.full_pose), actor.model.parents)
            head = JOINT["head"]
            rel = out.landmarks - out.joints[:, head:head + 1]
            local = torch.einsum("bji,bkj->bki", rot[:, head], rel)  # R^T (x - p)
        parts.append(Posed(uv, vis, rot.numpy(), out.full_pose.numpy(), local.numpy()))
    cat = np.concatenate
    return Posed({g: cat([p.uv[g] for p in parts]) for g in parts[0].uv},
                 {g: cat([p.visible[g] for p in parts]) for g in parts[0].visible},
                 cat([p.rotations for p in parts]), cat([p.full_pose for p in parts]),
                 cat([p.face_local for p in parts]))


def geodesic_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (deg) of a^T b for rotation matrices [..., 3, 3]."""
    cos = (np.einsum("...ij,...ij->...", a, b) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def aa_to_matrix(aa: np.ndarray) -> np.ndarray:
    flat = torch.as_tensor(np.asarray(aa, dtype=np.float64).reshape(-1, 3))
    return lbs.rodrigues(flat).numpy().reshape(*np.shape(aa)[:-1], 3, 3)


def _mean(values) -> float:
    v = np.asarray(values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    return float(v.mean()) if len(v) else float("nan")


@dataclass
class ClipResult:
    name: str
    frames: int
    seen: dict[str, np.ndarray]        # group -> [T] bool
    in_view: dict[str, np.ndarray]     # hand -> [T] bool (all true keypoints in the image)
    ms: list[float]                    # tracking + fitting per frame
    track_ms: list[float]
    metrics: dict[str, float] = field(default_factory=dict)
    frames_bgr: list[np.ndarray] = field(default_factory=list)
    fitted_px: list[np.ndarray] = field(default_factory=list)  # fitter layout [K, 2]
    # Per frame, fitter layout [K, 2]: tracked landmark - the true model keypoint (NaN unused)
    offsets: list[np.ndarray] = field(default_factory=list)
    swapped: dict[str, np.ndarray] = field(default_factory=dict)  # hand -> [T] wrong side


def clip_metrics(truth: Posed, raw: Posed, smooth: Posed, gt_params, fit_params,
                 seen: dict[str, np.ndarray], in_view: dict[str, np.ndarray],
                 neutral_face: Posed, swapped: dict[str, np.ndarray],
                 skip: int = 0) -> dict[str, float]:
    m: dict[str, float] = {}
    t = len(gt_params)
    # A hand counts as detected when it is reported on its own side.
    right = {g: seen[g] & ~swapped[g] for g in swapped}
    for g in GROUPS:
        if g.endswith("hand"):
            m[f"det_{g}"] = (float(right[g][in_view[g]].mean()) if in_view[g].any()
                             else float("nan"))
            m[f"in_view_{g}"] = float(in_view[g].mean())
        else:
            m[f"det_{g}"] = float(seen[g].mean())
    reported = sum(int(seen[g].sum()) for g in swapped)
    m["hand_reports"] = reported
    m["wrong_side"] = (sum(int(swapped[g].sum()) for g in swapped) / reported if reported
                       else float("nan"))
    # AKD per group over the frames where the group was detected (hands: on their own side).
    akd_rows = {"face": seen["face"], "left_hand": right["left_hand"],
                "right_hand": right["right_hand"], "torso": seen["pose"]}
    for g, rows in akd_rows.items():
        d = np.linalg.norm(raw.uv[g] - truth.uv[g], axis=-1)  # [T, K]
        use = truth.visible[g] & rows[:, None] & np.isfinite(d)
        m[f"akd_{g}"] = float(d[use].mean()) if use.any() else float("nan")
        m[f"akd_n_{g}"] = int(rows.sum())
    # Head and jaw.
    seen = {**seen, **right}
    f = seen["face"]
    head, jaw = JOINT["head"], JOINT["jaw"]
    m["head_deg"] = _mean(geodesic_deg(raw.rotations[f, head], truth.rotations[f, head]))
    m["jaw_deg"] = _mean(geodesic_deg(aa_to_matrix(raw.full_pose[f, jaw]),
                                      aa_to_matrix(truth.full_pose[f, jaw])))
    m["jaw_true_max_deg"] = float(np.degrees(np.linalg.norm(truth.full_pose[:, jaw], axis=-1)
                                             ).max())
    m["expr_mm"] = 1e3 * _mean(np.linalg.norm(raw.face_local[f] - truth.face_local[f], axis=-1))
    m["expr_motion_mm"] = 1e3 * _mean(np.linalg.norm(neutral_face.face_local[f]
                                                     - truth.face_local[f], axis=-1))
    # Arms and hands.
    p = seen["pose"]
    elbows, wrists, fingers, fingers_base = [], [], [], []
    for side, joints in (("left", LEFT_HAND_JOINTS), ("right", RIGHT_HAND_JOINTS)):
        e = JOINT[f"{side}_elbow"]
        flex = [np.degrees(np.linalg.norm(q.full_pose[p, e], axis=-1)) for q in (raw, truth)]
        elbows.append(np.abs(flex[0] - flex[1]))
        h = seen[f"{side}_hand"]
        w = JOINT[f"{side}_wrist"]
        wrists.append(geodesic_deg(raw.rotations[h, w], truth.rotations[h, w]))
        jt = list(joints)
        gt_r = aa_to_matrix(truth.full_pose[h][:, jt])
        fingers.append(geodesic_deg(aa_to_matrix(raw.full_pose[h][:, jt]), gt_r).ravel())
        # The model's mean hand (hand_pose 0): the true full pose less the true hand_pose.
        base = truth.full_pose[h][:, jt] - np.asarray(
            [gp[f"{side}_hand_pose"] for gp in gt_params])[h]
        fingers_base.append(geodesic_deg(aa_to_matrix(base), gt_r).ravel())
    m["elbow_deg"] = _mean(np.concatenate(elbows))
    m["wrist_deg"] = _mean(np.concatenate(wrists))
    m["finger_deg"] = _mean(np.concatenate(fingers))
    m["finger_mean_hand_deg"] = _mean(np.concatenate(fingers_base))
    # Jitter: every keypoint, the whole clip, raw vs smoothed.
    if t - skip >= 3:
        cut = lambda q: Posed({g: v[skip:] for g, v in q.uv.items()},  # noqa: E731
                              {g: v[skip:] for g, v in q.visible.items()}, q.rotations,
                              q.full_pose, q.face_local)
        truth, raw, smooth = cut(truth), cut(raw), cut(smooth)
        for label, pred in (("raw", raw), ("smooth", smooth)):
            uv_p = np.concatenate([pred.uv[g] for g in ("face", "left_hand", "right_hand",
                                                        "torso")], 1)
            uv_t = np.concatenate([truth.uv[g] for g in ("face", "left_hand", "right_hand",
                                                         "torso")], 1)
            vis = np.concatenate([truth.visible[g] for g in ("face", "left_hand", "right_hand",
                                                             "torso")], 1)
            vis &= np.isfinite(uv_p).all(-1)
            m[f"tje_{label}"] = keypoint_tje(np.nan_to_num(uv_p), np.nan_to_num(uv_t), vis)
            fv = truth.visible["face"] & np.isfinite(pred.uv["face"]).all(-1)
            m[f"tje_face_{label}"] = keypoint_tje(np.nan_to_num(pred.uv["face"]),
                                                  truth.uv["face"], fv)
    return m


# Landmarks that `--ignore` can take out of the fit (fitter-layout rows), for ablations.
IGNORABLE = {"contour": list(range(17)),
             "ears": [NUM_FACE_HANDS + 7, NUM_FACE_HANDS + 8],
             "hips": [NUM_FACE_HANDS + 23, NUM_FACE_HANDS + 24]}


def run_clip(scene: Scene, name: str, tracker, session, fps: float,
             max_frames: int | None = None, start: float = 0.0, sensor_noise: float = 2 / 255,
             keep_frames: bool = False, ignore: tuple[str, ...] = (), log=None) -> ClipResult:
    """Render, track and fit one clip in order; `ignore`: landmark classes (`IGNORABLE`)
    given weight 0 in the fit."""
    from avatar_core.track.fit.camera import WebcamCamera
    from avatar_core.track.fit.observations import from_track_result
    from avatar_core.track.fit.synthetic import project_params

    gt = clip_params(scene, name, fps, start, max_frames)
    tracker.reset()
    session.reset()
    rng = np.random.default_rng([11, *name.encode()])
    wcam = WebcamCamera(scene.camera.width, scene.camera.height, FOV_X_DEG)
    seen = {g: np.zeros(len(gt), bool) for g in GROUPS}
    raw_params, smooth_params, ms, track_ms = [], [], [], []
    res = ClipResult(name, len(gt), seen, {}, ms, track_ms)
    res.swapped = {g: np.zeros(len(gt), bool) for g in ("left_hand", "right_hand")}
    render_s = 0.0
    for i, params in enumerate(gt):
        r0 = time.perf_counter()
        frame = render_frame(scene.actor, params, scene.camera, scene.bg, sensor_noise, rng)
        render_s += time.perf_counter() - r0
        t0 = time.perf_counter()
        result = tracker.track(frame)
        t1 = time.perf_counter()
        obs = from_track_result(result)
        for cls in ignore:
            obs.weights[IGNORABLE[cls]] = 0.0
        out = session.step(obs, i / fps)
        ms.append((time.perf_counter() - t0) * 1e3)
        track_ms.append((t1 - t0) * 1e3)
        for g in GROUPS:
            seen[g][i] = bool(out.seen.get(g))
        raw_params.append({k: np.array(v) for k, v in session.current.items()})
        true_px = project_params(session.fitter, {k: v for k, v in params.items()
                                                  if k != "betas"}, wcam)
        offset = np.where((obs.weights > 0)[:, None], obs.pixels - true_px, np.nan)
        for side, own, other in (("left_hand", LH, RH), ("right_hand", RH, LH)):
            if seen[side][i]:  # labelled on the wrong side: its wrist is nearer the other's
                wrist = obs.pixels[own]
                res.swapped[side][i] = (np.linalg.norm(wrist - true_px[other])
                                        < np.linalg.norm(wrist - true_px[own]))
                if res.swapped[side][i]:  # the offset table is about landmark definitions
                    offset[own:own + 21] = np.nan
        res.offsets.append(offset)
        smooth_params.append({k: np.array(v) for k, v in out.params.items()})
        if keep_frames:
            res.frames_bgr.append(frame)
            res.fitted_px.append(project_params(session.fitter, raw_params[-1], wcam))
    cam = scene.camera
    truth = evaluate_params(scene.actor, gt, cam)
    raw = evaluate_params(scene.actor, raw_params, cam)
    smooth = evaluate_params(scene.actor, smooth_params, cam)
    neutral = evaluate_params(scene.actor, [
        {**p, "expression": np.zeros_like(p["expression"]), "jaw_pose": np.zeros(3)}
        for p in gt], cam)
    res.in_view = {g: truth.visible[g].all(-1) for g in ("left_hand", "right_hand")}
    res.metrics = clip_metrics(truth, raw, smooth, gt, raw_params, seen, res.in_view, neutral,
                               res.swapped, skip=int(round(TJE_SKIP_S * fps)))
    res.metrics["ms"] = float(np.mean(ms))
    res.metrics["ms_median"] = float(np.median(ms))
    res.metrics["track_ms"] = float(np.mean(track_ms))
    res.metrics["render_s"] = render_s / max(len(gt), 1)
    if log:
        log(f"{name}: {len(gt)} frames, render {res.metrics['render_s']:.2f} s/frame, "
            f"track+fit {res.metrics['ms']:.0f} ms/frame")
    return res


def make_tracker_and_session(scene: Scene, smoothing: bool = True):
    import numpy as _np

    from avatar_core.gaussians.animate import synthetic_package
    from avatar_core.track.fit.session import FitSession, SessionConfig
    from avatar_core.track.tracker import Tracker

    tracker = Tracker(threads=1, iris=True)
    package, model = synthetic_package(scene.model_dir, 0)
    session = FitSession(model, _np.asarray(package.body.betas),
                         SessionConfig(fov_x_deg=FOV_X_DEG, smoothing=smoothing))
    return tracker, session


# ----------------------------------------------------------------------------- reporting

FACE_COLOUR, POSE_COLOUR = (0, 230, 255), (255, 160, 0)
HAND_COLOUR = {"left_hand": (255, 0, 255), "right_hand": (0, 0, 255)}
POSE_DRAW_EDGES = [(11, 12), (11, 13), (13, 15), (12, 14), (14, 16), (11, 23), (12, 24),
                   (23, 24)]


def draw_fit(frame: np.ndarray, fitted_px: np.ndarray, seen: dict[str, bool],
             label: str) -> np.ndarray:
    from avatar_core.track.draw import HAND_EDGES
    from avatar_core.track.fit import correspondence as cor

    img = frame.copy()

    def pt(p):
        return int(round(float(p[0]))), int(round(float(p[1])))

    pose = fitted_px[cor.POSE_SLICE]
    for a, b in POSE_DRAW_EDGES:
        if np.isfinite(pose[[a, b]]).all():
            cv2.line(img, pt(pose[a]), pt(pose[b]), POSE_COLOUR, 2, cv2.LINE_AA)
    for g in ("left_hand", "right_hand"):
        if not seen.get(g):
            continue
        hand = fitted_px[cor.GROUP_SLICES[g]]
        for a, b in HAND_EDGES:
            cv2.line(img, pt(hand[a]), pt(hand[b]), HAND_COLOUR[g], 2, cv2.LINE_AA)
    if seen.get("face"):
        for q in fitted_px[cor.FACE_SLICE]:
            cv2.circle(img, pt(q), 2, FACE_COLOUR, -1, cv2.LINE_AA)
    cv2.putText(img, label, (10, 36), cv2.FONT_HERSHEY_SIMPLEX, 1.1, (255, 255, 255), 5,
                cv2.LINE_AA)
    cv2.putText(img, label, (10, 36), cv2.FONT_HERSHEY_SIMPLEX, 1.1, (0, 0, 0), 2, cv2.LINE_AA)
    return img


def contact_sheet(results: list[ClipResult], out: Path, cols: int = 3,
                  scale: float = 0.5) -> Path:
    tiles = []
    for r in results:
        if not r.frames_bgr:
            continue
        i = len(r.frames_bgr) // 2  # the clips hold their key pose in the middle
        seen = {g: bool(r.seen[g][i]) for g in GROUPS}
        hands = "+".join(s[0].upper() + (" (wrong side)" if r.swapped[f"{s}_hand"][i] else "")
                         for s in HAND_SIDES if seen[f"{s}_hand"]) or "none"
        img = draw_fit(r.frames_bgr[i], r.fitted_px[i], seen, f"{r.name}, hands: {hands}")
        tiles.append(cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA))
    while len(tiles) % cols:
        tiles.append(np.full_like(tiles[0], 255))
    rows = [np.concatenate(tiles[k:k + cols], 1) for k in range(0, len(tiles), cols)]
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), np.concatenate(rows, 0))
    return out


def _fmt(x: float, digits: int = 1) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"


def _pct(x: float) -> str:
    return "-" if not np.isfinite(x) else f"{100 * x:.0f}%"


def overall(results: list[ClipResult]) -> dict[str, float]:
    """Frame-weighted means over clips (each metric over the clips where it is defined,
    weighted by the frames it was computed on)."""
    out: dict[str, float] = {}
    keys = results[0].metrics.keys()
    for k in keys:
        vals, wts = [], []
        for r in results:
            v = r.metrics.get(k, float("nan"))
            if np.isfinite(v):
                if k.startswith("akd_") and not k.startswith("akd_n_"):
                    g = k[4:]
                    w = r.metrics.get(f"akd_n_{g}", 0)
                elif k.startswith("det_") and k.endswith("hand"):
                    w = int(r.in_view[k[4:]].sum())
                elif k == "wrong_side":
                    w = r.metrics["hand_reports"]
                else:
                    w = r.frames
                if w:
                    vals.append(v)
                    wts.append(w)
        out[k] = float(np.average(vals, weights=wts)) if vals else float("nan")
    out["frames"] = sum(r.frames for r in results)
    return out


def tables(results: list[ClipResult]) -> str:
    rows = [(r.name, r.frames, r.metrics) for r in results]
    rows.append(("**all**", sum(r.frames for r in results), overall(results)))
    lines = ["| clip | frames | face | left hand (in view) | right hand (in view) | "
             "hands on the wrong side | pose | AKD face | AKD L hand | AKD R hand | AKD torso |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, n, m in rows:
        lines.append(
            f"| {name} | {n} | {_pct(m['det_face'])} | {_pct(m['det_left_hand'])} "
            f"({_pct(m['in_view_left_hand'])}) | {_pct(m['det_right_hand'])} "
            f"({_pct(m['in_view_right_hand'])}) | {_pct(m['wrong_side'])} | "
            f"{_pct(m['det_pose'])} | "
            f"{_fmt(m['akd_face'], 2)} | {_fmt(m['akd_left_hand'])} | "
            f"{_fmt(m['akd_right_hand'])} | {_fmt(m['akd_torso'])} |")
    lines += ["", "| clip | head deg | jaw deg (true max) | expr. landmarks mm (expr. motion) | "
                  "elbow flex deg | wrist deg | fingers deg (mean hand) | TJE px raw | "
                  "TJE px One Euro | TJE face raw / One Euro | track / +fit ms | FPS |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, _, m in rows:
        lines.append(
            f"| {name} | {_fmt(m['head_deg'])} | {_fmt(m['jaw_deg'])} "
            f"({_fmt(m['jaw_true_max_deg'])}) | {_fmt(m['expr_mm'])} "
            f"({_fmt(m['expr_motion_mm'])}) | {_fmt(m['elbow_deg'])} | "
            f"{_fmt(m['wrist_deg'])} | {_fmt(m['finger_deg'])} "
            f"({_fmt(m['finger_mean_hand_deg'])}) | {_fmt(m.get('tje_raw', np.nan), 2)} | "
            f"{_fmt(m.get('tje_smooth', np.nan), 2)} | "
            f"{_fmt(m.get('tje_face_raw', np.nan), 2)} / "
            f"{_fmt(m.get('tje_face_smooth', np.nan), 2)} | {_fmt(m['track_ms'], 0)} / "
            f"{_fmt(m['ms'], 0)} | "
            f"{_fmt(1e3 / m['ms'])} |")
    return "\n".join(lines)


# Landmark classes for the offset table: (name, fitter-layout rows).
def _offset_classes() -> list[tuple[str, list[int]]]:
    from avatar_core.track.fit import correspondence as cor

    f, lh, rh, p = (cor.FACE_SLICE.start, cor.LEFT_HAND_SLICE.start,
                    cor.RIGHT_HAND_SLICE.start, cor.POSE_SLICE.start)
    return [("face contour (iBUG 0-16)", [f + k for k in range(17)]),
            ("face brows, nose, eyes (17-47)", [f + k for k in range(17, 48)]),
            ("face mouth (48-67)", [f + k for k in range(48, 68)]),
            ("hand wrists", [lh, rh]),
            ("hand finger joints", [s + k for s in (lh, rh) for k in range(1, 21)
                                    if k % 4]),
            ("hand fingertips", [s + k for s in (lh, rh) for k in (4, 8, 12, 16, 20)]),
            ("pose nose + eyes", [p + 0, p + 2, p + 5]), ("pose ears", [p + 7, p + 8]),
            ("pose shoulders", [p + 11, p + 12]), ("pose elbows", [p + 13, p + 14]),
            ("pose wrists", [p + 15, p + 16]), ("pose hips", [p + 23, p + 24])]


def offset_table(results: list[ClipResult]) -> str:
    """How far the tracked landmarks lie from the true model keypoints they are matched to
    (the fitter's correspondences), before any fitting: a bias here is a landmark-definition
    mismatch the fit cannot undo. dx is signed outward (away from the midline: the subject's
    left is the image's right) for points with a side, y down."""
    from avatar_core.track.fit import correspondence as cor

    off = np.concatenate([np.stack(r.offsets) for r in results if r.offsets])  # [N, K, 2]
    lines = ["| landmarks | frames x points | mean abs px | mean dx out px | mean dy px |",
             "|---|---:|---:|---:|---:|"]
    side = np.zeros(cor.NUM_KEYPOINTS)
    side[cor.FACE_SLICE.start:cor.FACE_SLICE.start + 8] = -1.0  # iBUG 0-7: the right cheek
    side[cor.FACE_SLICE.start + 9:cor.FACE_SLICE.start + 17] = 1.0
    for sl, s in ((cor.LEFT_HAND_SLICE, 1.0), (cor.RIGHT_HAND_SLICE, -1.0)):
        side[sl] = s
    for k, name in enumerate(cor.POSE_MP_TO_SMPLX):
        if name and ("left" in name or name.endswith((":leye", ":lear"))):
            side[cor.POSE_SLICE.start + k] = 1.0
        elif name and ("right" in name or name.endswith((":reye", ":rear"))):
            side[cor.POSE_SLICE.start + k] = -1.0
    for name, rows in _offset_classes():
        d = off[:, rows]  # [N, R, 2]
        ok = np.isfinite(d).all(-1)
        if not ok.any():
            lines.append(f"| {name} | 0 | - | - | - |")
            continue
        out_x = (d[..., 0] * side[rows][None])[ok]
        lines.append(f"| {name} | {int(ok.sum())} | {np.linalg.norm(d[ok], axis=-1).mean():.1f} "
                     f"| {out_x.mean() if side[rows].any() else float('nan'):.1f} "
                     f"| {d[..., 1][ok].mean():.1f} |")
    return "\n".join(lines).replace("| nan |", "| - |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--clips", default=",".join(CLIPS))
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--max-frames", type=int, default=None)
    parser.add_argument("--background", choices=("noise", "plain"), default="noise")
    parser.add_argument("--contact", type=Path, default=None)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--ignore", default="",
                        help="ablation: landmark classes left out of the fit, comma-separated "
                             f"({', '.join(IGNORABLE)})")
    args = parser.parse_args()
    torch.set_num_threads(1)
    log = lambda msg: print(msg, file=sys.stderr, flush=True)  # noqa: E731
    t0 = time.perf_counter()
    scene = make_scene(args.background)
    tracker, session = make_tracker_and_session(scene)
    log(f"setup {time.perf_counter() - t0:.1f} s; subject transl {np.round(scene.transl, 3)}; "
        f"load {os.getloadavg()[0]:.2f}")
    results = [run_clip(scene, name.strip(), tracker, session, args.fps, args.max_frames,
                        keep_frames=args.contact is not None,
                        ignore=tuple(c for c in args.ignore.split(",") if c), log=log)
               for name in args.clips.split(",") if name.strip()]
    print(tables(results))
    print()
    print(offset_table(results))
    print(f"\nload average after: {os.getloadavg()[0]:.2f}; "
          f"median track+fit {statistics.median([x for r in results for x in r.ms]):.0f} ms")
    if args.contact:
        log(f"wrote {contact_sheet(results, args.contact)}")
    if args.json:
        args.json.write_text(json.dumps({r.name: r.metrics for r in results}, indent=1))


if __name__ == "__main__":
    main()
