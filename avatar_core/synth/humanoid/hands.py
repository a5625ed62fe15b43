"""Named right-hand poses (fist, point, pinch, counting gestures, ...) fitted on the rest
hand by forward kinematics."""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from avatar_core.body.skeleton import JOINT

from .primitives import _unit


def _fk_hand(rest: np.ndarray, tips: np.ndarray, rotvecs: np.ndarray) -> tuple[np.ndarray,
                                                                                np.ndarray]:
    """Posed right-hand joints [16, 3] (wrist first) and fingertips [5, 3] for [15, 3] poses."""
    rot = Rotation.from_rotvec(rotvecs).as_matrix()
    pos = [rest[0]]
    out_tips = []
    for f in range(5):
        gp, pp = np.eye(3), rest[0]
        for i in range(3):
            k = 1 + 3 * f + i
            parent = 0 if i == 0 else k - 1
            pp = pp + gp @ (rest[k] - rest[parent])
            gp = gp @ rot[k - 1]
            pos.append(pp)
        out_tips.append(pp + gp @ (tips[f] - rest[3 + 3 * f]))
    return np.asarray(pos), np.asarray(out_tips)


def _hand_poses(joints: np.ndarray, tips: np.ndarray) -> dict[str, np.ndarray]:
    """Right-hand gestures as [15, 3] axis-angles. The right hand points along -x with the
    palm toward -y, so flexion toward the palm is a positive rotation about +z and spreading
    toward the thumb a positive rotation about +y."""
    rest = joints[[JOINT["right_wrist"], *range(40, 55)]]  # [16, 3]
    t_dir = _unit(rest[14] - rest[13])
    t_flex = _unit(np.cross(t_dir, [0.0, -1.0, 0.0]))

    def fingers(curls, spreads=(0.0, 0.0, 0.0, 0.0)):
        pose = np.zeros((15, 3))
        for f in range(4):
            c1, c2, c3 = curls[f]
            r1 = Rotation.from_rotvec([0, 0, c1]) * Rotation.from_rotvec([0, spreads[f], 0])
            pose[3 * f] = r1.as_rotvec()
            pose[3 * f + 1] = [0, 0, c2]
            pose[3 * f + 2] = [0, 0, c3]
        return pose

    def thumb(pose, opp, f1, f2):
        r1 = Rotation.from_rotvec(t_flex * f1) * Rotation.from_rotvec([0.0, -opp, 0.0])
        pose[12] = r1.as_rotvec()
        pose[13] = t_flex * f2
        pose[14] = t_flex * 0.8 * f2
        return pose

    def fit_thumb(pose, target_fn, x0=(0.6, 0.3, 0.4)):
        def resid(q):
            pj, pt = _fk_hand(rest, tips, thumb(pose.copy(), *q))
            return np.concatenate([pt[4] - target_fn(pj, pt), 0.002 * np.asarray(q)])

        q = least_squares(resid, x0, bounds=([-0.5, -0.6, -0.3], [1.6, 1.6, 1.6])).x
        return thumb(pose, *q)

    fist_c = [(1.35, 1.55, 0.75)] * 4
    below = np.array([0.0, -0.012, 0.0])
    out = {"flat": np.zeros((15, 3))}
    out["relaxed"] = thumb(fingers([(0.12, 0.22, 0.10), (0.16, 0.28, 0.12), (0.26, 0.38, 0.16),
                                    (0.21, 0.33, 0.14)], (0.04, 0.0, -0.08, -0.04)),
                           0.10, 0.10, 0.15)
    fist = fingers(fist_c)
    out["fist"] = fit_thumb(fist, lambda pj, pt: 0.5 * (pj[2] + pj[5]) + below * 1.3)
    out["point"] = fit_thumb(fingers([(0.0, 0.0, 0.0)] + fist_c[1:]),
                             lambda pj, pt: pj[5] + below * 1.3)
    out["thumbs_up"] = thumb(fingers(fist_c), -0.15, -0.2, 0.0)
    peace = fingers([(0.0, 0.0, 0.0), (0.0, 0.0, 0.0)] + fist_c[2:], (0.16, -0.12, 0.0, 0.0))
    out["peace"] = fit_thumb(peace, lambda pj, pt: 0.5 * (pj[8] + pj[11]) + below * 1.3)
    ok = fingers([(0.75, 1.0, 0.6), (0.05, 0.08, 0.04), (0.10, 0.10, 0.05),
                  (0.08, 0.10, 0.05)], (0.05, -0.05, -0.25, -0.15))
    out["ok"] = fit_thumb(ok, lambda pj, pt: pt[0])
    out["spread"] = thumb(fingers([(0.0, 0.0, 0.0)] * 4, (0.28, 0.04, -0.45, -0.20)),
                          -0.35, -0.25, 0.0)
    out["claw"] = thumb(fingers([(0.15, 1.25, 1.0), (0.15, 1.25, 1.0), (0.15, 1.25, 1.0),
                                 (0.15, 1.25, 1.0)], (0.1, 0.0, -0.15, -0.07)), 0.5, 0.3, 0.9)
    pinch = fingers([(0.85, 0.9, 0.45), (0.40, 0.70, 0.35), (0.55, 0.85, 0.45),
                     (0.48, 0.78, 0.40)])
    out["pinch"] = fit_thumb(pinch, lambda pj, pt: pt[0])
    out.update(_more_poses(rest, tips, fingers, thumb, fit_thumb, fist_c))
    return out


def _more_poses(rest, tips, fingers, thumb, fit_thumb, fist_c) -> dict[str, np.ndarray]:
    """Counting gestures (three, four, L) and the halves of two-hand gestures (heart_half,
    cupped). `fingers`, `thumb` and `fit_thumb` are `_hand_poses`' builders for the right hand,
    whose fingers point along -x (`along`), thumb side +z (`side`), palm toward -y (`palm`)."""
    along = _unit(rest[4] - rest[0])  # wrist -> middle knuckle
    side, palm = np.array([0.0, 0.0, 1.0]), np.array([0.0, -1.0, 0.0])
    t_len = float(np.linalg.norm(np.diff([*rest[13:16], tips[4]], axis=0), axis=1).sum())
    straight = (0.0, 0.0, 0.0)
    out = {}
    # Index, middle and ring up; the thumb holds the curled pinky down.
    three = fingers([straight, straight, fist_c[2], straight], (0.14, 0.0, 0.0, -0.12))
    out["three"] = fit_thumb(three, lambda pj, pt: pj[8] + 0.016 * palm)
    # Four fingers up and spread a little; the thumb folded across the palm toward the ring
    # finger's knuckle (as far as it reaches: it stops about 1 cm off the palm).
    four = fingers([straight] * 4, (0.14, 0.0, -0.22, -0.10))
    out["four"] = fit_thumb(four, lambda pj, pt: pj[10] + 0.012 * palm, x0=(1.0, 0.6, 0.3))
    # Thumb abducted in the palm plane, about a right angle from the straight index.
    out["L"] = thumb(fingers([straight] + fist_c[1:], (0.05, 0.0, 0.0, 0.0)), -0.85, -0.05, 0.0)
    # Fingers together and hooked toward the palm (the heart's upper lobe); the thumb straight
    # and raised off the palm so its tip closes the heart at the bottom.
    heart = fingers([(0.55, 0.85, 0.5), (0.55, 0.85, 0.5), (0.6, 0.85, 0.5), (0.58, 0.85, 0.5)],
                    (-0.06, 0.0, 0.12, 0.06))
    out["heart_half"] = fit_thumb(
        heart, lambda pj, pt: pj[13] + t_len * _unit(palm + 0.5 * side - 0.2 * along),
        x0=(0.2, 0.8, 0.0))
    # Slightly curved and together; the thumb tip beside the index tip, equally deep below the
    # palm, so that all five tips lie near one plane and can press against the other hand's.
    cupped = fingers([(0.22, 0.30, 0.15), (0.22, 0.30, 0.15), (0.26, 0.32, 0.16),
                      (0.24, 0.31, 0.15)], (-0.05, 0.0, 0.10, 0.05))
    out["cupped"] = fit_thumb(cupped, lambda pj, pt: pt[0] + 0.025 * side - 0.035 * along,
                              x0=(0.3, 0.5, 0.2))
    return out
