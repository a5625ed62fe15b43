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

from avatar_core.body.skeleton import JOINT

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
                variants: dict[str, tuple[str, ...]] | None = None
                ) -> dict[str, dict[str, float]]:
    """Per variant: mean PSNR over the frames and the joint-angle errors of `drive`'s
    smoothed parameters (what drove the avatar) with the variant's parts from the truth."""
    from .protocol import joint_errors

    variants = variants or swap_variants()
    fitted = res.smooth[drive]
    psnr = {label: [] for label in variants}
    swapped = {label: [] for label in variants}
    for fit, truth in zip(fitted, res.truth, strict=True):
        with torch.no_grad():
            reference = actor.render(actor.pose(truth), score_cam, background=(0, 0, 0),
                                     supersample=1)
        for label, parts in variants.items():
            params = swap_parts(fit, truth, parts)
            swapped[label].append(params)
            with torch.no_grad():
                view = actor.render(actor.pose(params), score_cam, background=(0, 0, 0),
                                    supersample=1)
            psnr[label].append(frame_psnr(view, reference))
    out = {}
    for label in variants:
        p = np.asarray(psnr[label])
        out[label] = {"psnr": float(p[np.isfinite(p)].mean()),
                      **joint_errors(swapped[label], res.truth)}
    return out
