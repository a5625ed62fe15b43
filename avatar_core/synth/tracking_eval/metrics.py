"""Evaluation quantities of parameter sets and the per-clip metrics (detection, parameter
recovery, AKD, TJE)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from avatar_core.body import lbs
from avatar_core.body.skeleton import JOINT, LEFT_HAND_JOINTS, RIGHT_HAND_JOINTS
from avatar_core.metrics.keypoints import body_keypoints, project_keypoints
from avatar_core.metrics.temporal import keypoint_tje
from avatar_core.render.camera import Camera

HAND_SIDES = ("left", "right")
NUM_FACE_HANDS = 68 + 2 * 21  # the fitter's layout: face 68, hands 21 + 21, then pose 33
LH, RH = 68, 68 + 21  # the wrists' rows in that layout
GROUPS = ("face", "left_hand", "right_hand", "pose")
TJE_SKIP_S = 0.5  # jitter is measured after the cold start has settled


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


def clip_metrics(truth: Posed, raw: Posed, smooth: Posed, gt_params,
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
