"""Which part of a fit costs what: the fitted parameters with one part's values replaced
by the truth ("only this part true"), or every part but one ("all true but this part"),
rendered at the protocol's score camera and scored like a drive (PSNR, joint angles).

Nothing is refitted: a swap answers how much of the picture's error sits in that part's
parameters as fitted, not what the fit would do if it knew them.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from avatar_core.body.skeleton import JOINT, SMPLX_PARENTS
from avatar_core.metrics.webcam import world_rotations

# Part -> (parameter names, body_pose joints). Together they cover every fitted parameter
# but `transl` and `betas` (the avatar is driven without `transl`; betas are the actor's).
PARTS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "root": (("global_orient",), ()),
    "spine": ((), ("spine1", "spine2", "spine3")),
    "collars": ((), ("left_collar", "right_collar")),
    "arms": ((), ("left_shoulder", "right_shoulder", "left_elbow", "right_elbow")),
    "wrists": ((), ("left_wrist", "right_wrist")),
    "head": ((), ("neck", "head")),
    "hands": (("left_hand_pose", "right_hand_pose"), ()),
    "face": (("jaw_pose", "expression", "leye_pose", "reye_pose"), ()),
}
# A frame rendered exactly like the truth has infinite PSNR; each frame's is capped here so
# that a mean over frames stays finite (60 dB: an RMS error of 1/1000).
PSNR_CAP_DB = 60.0


def swap_parts(fitted: dict[str, np.ndarray], truth: dict[str, np.ndarray],
               parts) -> dict[str, np.ndarray]:
    """A copy of `fitted` with the parameters of `parts` (names in `PARTS`) from `truth`."""
    unknown = [p for p in parts if p not in PARTS]
    if unknown:
        raise ValueError(f"unknown part(s) {unknown}; known: {', '.join(PARTS)}")
    out = {k: np.array(v, dtype=np.float64) for k, v in fitted.items()}
    for part in parts:
        names, joints = PARTS[part]
        for name in names:
            out[name] = np.array(truth[name], dtype=np.float64).reshape(out[name].shape)
        rows = [JOINT[j] - 1 for j in joints]
        if rows:
            out["body_pose"][rows] = np.asarray(truth["body_pose"])[rows]
    return out


def _turn_onto(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[3, 3] the least rotation taking direction `a` onto `b` (a swing: no turn about
    either; scipy's answer for a single pair)."""
    return Rotation.align_vectors(b[None], a[None])[0].as_matrix()


def with_arm_directions(params: dict[str, np.ndarray], directions_from: dict[str, np.ndarray],
                        rest_joints: np.ndarray) -> dict[str, np.ndarray]:
    """A copy of `params` whose upper arms and forearms point where `directions_from`'s do
    in the world, each turned there by the least rotation, so that the twist about each bone
    stays `params`' own. Everything above the shoulders stays `params`'.
    rest_joints: [J, 3] the body model's joints at rest (the bones' rest offsets)."""
    world, target = world_rotations(params), world_rotations(directions_from)
    out = {k: np.array(v, dtype=np.float64) for k, v in params.items()}
    local = out["body_pose"].reshape(-1, 3)
    for side in ("left", "right"):
        shoulder, elbow, wrist = (JOINT[f"{side}_{j}"] for j in ("shoulder", "elbow", "wrist"))
        upper = rest_joints[elbow] - rest_joints[shoulder]   # [3] at rest
        fore = rest_joints[wrist] - rest_joints[elbow]
        at_shoulder = _turn_onto(world[shoulder] @ upper, target[shoulder] @ upper) \
            @ world[shoulder]
        at_elbow = at_shoulder @ Rotation.from_rotvec(local[elbow - 1]).as_matrix()
        at_elbow = _turn_onto(at_elbow @ fore, target[elbow] @ fore) @ at_elbow
        local[shoulder - 1] = Rotation.from_matrix(
            world[SMPLX_PARENTS[shoulder]].T @ at_shoulder).as_rotvec()
        local[elbow - 1] = Rotation.from_matrix(at_shoulder.T @ at_elbow).as_rotvec()
    out["body_pose"] = local.reshape(np.shape(params["body_pose"]))
    return out


def arm_split_variants(fitted: dict[str, np.ndarray], truth: dict[str, np.ndarray],
                       rest_joints: np.ndarray) -> dict[str, dict[str, np.ndarray]]:
    """label -> parameters: the arms' world directions (what the landmarks show) apart from
    their twist about each bone, with the rest of the body as fitted or from the truth."""
    rest_true = swap_parts(fitted, truth, [p for p in PARTS if p != "arms"])
    return {
        "fitted": fitted,
        "arm directions true, twist fitted": with_arm_directions(fitted, truth, rest_joints),
        "all true but arms": rest_true,
        "all true but arm directions (twist true)": with_arm_directions(truth, fitted,
                                                                        rest_joints),
        "all true but arm twist (directions true)": with_arm_directions(rest_true, truth,
                                                                        rest_joints),
    }


def swap_variants(parts=tuple(PARTS)) -> dict[str, tuple[str, ...]]:
    """label -> the parts taken from the truth: none, each part alone, all but each part."""
    out = {"fitted": ()}
    out.update({f"only {p} true": (p,) for p in parts})
    out.update({f"all true but {p}": tuple(q for q in PARTS if q != p) for p in parts})
    return out


def frame_psnr(pred, truth) -> float:
    """PSNR (dB) over the pixels either render covers, capped at `PSNR_CAP_DB`."""
    keep = (pred.alpha > 1e-3) | (truth.alpha > 1e-3)
    if not keep.any():
        return float("nan")
    mse = float(((pred.rgb - truth.rgb) ** 2)[keep].mean())
    return PSNR_CAP_DB if mse <= 10 ** (-PSNR_CAP_DB / 10) else -10.0 * math.log10(mse)


def score_swaps(actor, res, drive: str, score_cam,
                variants: dict[str, tuple[str, ...]] | None = None, arm_split: bool = False
                ) -> dict[str, dict[str, float]]:
    """Per variant: mean PSNR over the frames and the joint-angle errors of `drive`'s
    smoothed parameters (what drove the avatar) with the variant's parts from the truth;
    with `arm_split` also `arm_split_variants` (the arms' directions apart from their twist)."""
    from .protocol import joint_errors

    variants = variants or swap_variants()
    psnr, swapped = {}, {}
    for fit, truth in zip(res.smooth[drive], res.truth, strict=True):
        with torch.no_grad():
            reference = actor.render(actor.pose(truth), score_cam, background=(0, 0, 0),
                                     supersample=1)
        frame = {label: swap_parts(fit, truth, parts) for label, parts in variants.items()}
        if arm_split:
            frame.update({label: params for label, params in
                          arm_split_variants(fit, truth, actor.rest_joints).items()
                          if label not in frame})
        for label, params in frame.items():
            swapped.setdefault(label, []).append(params)
            with torch.no_grad():
                view = actor.render(actor.pose(params), score_cam, background=(0, 0, 0),
                                    supersample=1)
            psnr.setdefault(label, []).append(frame_psnr(view, reference))
    out = {}
    for label, values in psnr.items():
        p = np.asarray(values)
        out[label] = {"psnr": float(p[np.isfinite(p)].mean()),
                      **joint_errors(swapped[label], res.truth)}
    return out
