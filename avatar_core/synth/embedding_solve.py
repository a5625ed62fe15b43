"""Fitting the landmark embedding from studio samples: per landmark, the offset in its anchor
joint's frame that best explains where MediaPipe put it, over every sample where it was seen.

    min_B  sum_s rho(|project(P_sk + R_sk B f_sk) - u_sk|) + ridge n_k |B|^2

(P_sk the model point at the true parameters, R_sk its anchor joint's world rotation, u_sk
the tracked pixel; f_sk = [1] for a constant offset, [theta_j, theta_parent(j), 1] for a
pose-dependent one; rho the fitter's pseudo-Huber, by iterative reweighting; Gauss-Newton).
The ridge keeps the along-the-ray part, which a few views barely see, small. Each landmark
gets no offset, a constant or a pose-dependent one, whichever has the lowest median error in
leave-one-identity-out cross-validation over the training identities: the data decide.
Plus the two z scales of the 3D cues (least squares through the origin).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..track.fit import correspondence as cor
from ..track.fit.camera import WebcamCamera, project_points
from ..track.fit.world_cues import DEPTH_PAIRS

HUBER_PX = 8.0
RIDGE_PX2_PER_M2 = 1000.0  # per sample: a 1 cm offset costs 0.1 px^2, 3 cm 0.9 px^2
MIN_SAMPLES = 40           # a landmark seen fewer times keeps offset 0
# A richer mode must beat the simpler one's cross-validated median by this fraction.
MIN_GAIN = 0.05
GAUSS_NEWTON_STEPS = 8


@dataclass
class Samples:
    """Studio samples, S frames in the fitter's layout (K rows)."""
    pixels: np.ndarray     # [S, K, 2] tracked px
    weights: np.ndarray    # [S, K] > 0 where tracked and usable
    points: np.ndarray     # [S, K, 3] model points at the true parameters (camera frame)
    rotations: np.ndarray  # [S, K, 3, 3] each row's anchor joint world rotation
    image_z: np.ndarray    # [S, K] MediaPipe's image z px (NaN: none)
    world: np.ndarray      # [S, 33, 3] BlazePose world landmarks m (NaN: none)
    camera: WebcamCamera
    poses: np.ndarray | None = None   # [S, 55, 3] true full axis-angle pose
    groups: np.ndarray | None = None  # [S] identity of each sample

    def __len__(self) -> int:
        return self.pixels.shape[0]

    def subset(self, keep: np.ndarray) -> Samples:
        return Samples(self.pixels[keep], self.weights[keep], self.points[keep],
                       self.rotations[keep], self.image_z[keep], self.world[keep], self.camera,
                       None if self.poses is None else self.poses[keep],
                       None if self.groups is None else self.groups[keep])


MODES = ("none", "constant", "pose")


def pose_features(s: Samples, joints: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """[S, K, 6] each row's anchor axis-angle and its parent's (0 without a parent)."""
    j = np.maximum(joints, 0)
    par = np.maximum(parents[j], 0)
    own = s.poses[:, j]
    up = s.poses[:, par] * ((parents[j] >= 0) & (joints >= 0))[None, :, None]
    return np.concatenate([own, up], axis=-1)


def local_offsets(offset: np.ndarray, basis: np.ndarray | None, feats: np.ndarray | None
                  ) -> np.ndarray:
    """[S, K, 3] (or [K, 3] without a basis) offsets in the anchors' frames."""
    if basis is None or feats is None:
        return offset
    return offset[None] + np.einsum("kab,skb->ska", basis, feats)


def embedded_points(s: Samples, offset: np.ndarray, basis: np.ndarray | None = None,
                    feats: np.ndarray | None = None) -> np.ndarray:
    """[S, K, 3] the model points moved by the embedding in their anchors' frames."""
    local = local_offsets(offset, basis, feats)
    if local.ndim == 2:
        return s.points + np.einsum("skab,kb->ska", s.rotations, local)
    return s.points + np.einsum("skab,skb->ska", s.rotations, local)


def pixel_errors(s: Samples, offset: np.ndarray, basis: np.ndarray | None = None,
                 feats: np.ndarray | None = None) -> np.ndarray:
    """[S, K] px distance of each tracked landmark from its embedded model point (NaN where
    not tracked)."""
    pts = embedded_points(s, offset, basis, feats).reshape(-1, 3)
    proj, _ = project_points(pts, s.camera)
    err = np.linalg.norm(proj.reshape(*s.pixels.shape) - s.pixels, axis=-1)
    return np.where(s.weights > 0, err, np.nan)


def _design(feats: np.ndarray, mode: str) -> np.ndarray:
    """[n, m] the regression inputs of a mode: [1] or [features, 1]."""
    ones = np.ones((feats.shape[0], 1))
    return ones if mode == "constant" else np.concatenate([feats, ones], axis=1)


def _fit_row(p, r, u, design, camera, ridge: float) -> np.ndarray:
    """[3, m] coefficients: offset = coef @ design row (Gauss-Newton, pseudo-Huber IRLS)."""
    n, m = design.shape
    coef = np.zeros((3, m))
    for _ in range(GAUSS_NEWTON_STEPS):
        o = design @ coef.T                                          # [n, 3]
        proj, d_proj = project_points(p + np.einsum("nab,nb->na", r, o), camera)
        res = proj - u
        w = 1.0 / np.sqrt(1.0 + (res ** 2).sum(-1) / HUBER_PX ** 2)
        jac = np.einsum("nai,nm->naim", d_proj @ r, design).reshape(n, 2, 3 * m)
        jtj = np.einsum("n,nap,naq->pq", w, jac, jac) + ridge * n * np.eye(3 * m)
        jtr = np.einsum("n,nap,na->p", w, jac, res) + ridge * n * coef.reshape(-1)
        step = np.linalg.solve(jtj, -jtr).reshape(3, m)
        coef = coef + step
        if np.abs(step).max() < 1e-7:
            break
    return coef


def _row_error(p, r, u, design, coef, camera) -> np.ndarray:
    proj, _ = project_points(p + np.einsum("nab,nb->na", r, design @ coef.T), camera)
    return np.linalg.norm(proj - u, axis=1)


def fit_offsets(s: Samples, anchors: np.ndarray, parents: np.ndarray,
                ridge: float = RIDGE_PX2_PER_M2, min_samples: int = MIN_SAMPLES
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str], dict]:
    """(offset [K, 3], pose basis [K, 3, 6], samples used [K], mode per row, the
    cross-validated median px error per row and mode)."""
    k_rows = s.pixels.shape[1]
    offset, basis = np.zeros((k_rows, 3)), np.zeros((k_rows, 3, 6))
    count, modes, cv = np.zeros(k_rows, dtype=np.int64), ["none"] * k_rows, {}
    feats = pose_features(s, anchors, parents)
    groups = np.zeros(len(s), dtype=np.int64) if s.groups is None else s.groups
    for k in range(k_rows):
        used = (s.weights[:, k] > 0) & np.isfinite(s.points[:, k]).all(-1)
        count[k] = int(used.sum())
        if anchors[k] < 0 or count[k] < min_samples:
            continue
        p, r, u, f, g = (s.points[used, k], s.rotations[used, k], s.pixels[used, k],
                         feats[used, k], groups[used])
        folds = np.unique(g)
        errors = {mode: [] for mode in MODES}
        for fold in folds if len(folds) > 1 else ():
            tr, te = g != fold, g == fold
            if tr.sum() < min_samples:
                continue
            errors["none"].append(_row_error(p[te], r[te], u[te], _design(f[te], "constant"),
                                             np.zeros((3, 1)), s.camera))
            for mode in ("constant", "pose"):
                coef = _fit_row(p[tr], r[tr], u[tr], _design(f[tr], mode), s.camera, ridge)
                errors[mode].append(_row_error(p[te], r[te], u[te], _design(f[te], mode), coef,
                                               s.camera))
        if not errors["none"]:  # one identity: no cross-validation, a constant offset
            scores = {"constant": 0.0}
        else:
            scores = {m: float(np.median(np.concatenate(e))) for m, e in errors.items()}
        cv[row_name(k)] = scores
        modes[k] = "none" if "none" in scores else "constant"
        for mode in MODES[MODES.index(modes[k]) + 1:]:  # richer only where it clearly wins
            if mode in scores and scores[mode] < (1.0 - MIN_GAIN) * scores[modes[k]]:
                modes[k] = mode
        if modes[k] == "none":
            continue
        coef = _fit_row(p, r, u, _design(f, modes[k]), s.camera, ridge)
        offset[k] = coef[:, -1]
        if modes[k] == "pose":
            basis[k] = coef[:, :6]
    return offset, basis, count, modes, cv


def z_scales(s: Samples, offset: np.ndarray, basis: np.ndarray | None = None,
             feats: np.ndarray | None = None) -> dict[str, float]:
    """BlazePose's world and image z against the model's depth differences over
    `world_cues.DEPTH_PAIRS`: the slope (model = slope x MediaPipe, through the origin) and
    the correlation of each."""
    depth = -embedded_points(s, offset, basis, feats)[..., 2]              # [S, K]
    base = cor.POSE_SLICE.start
    out = {}
    for name in ("world", "image"):
        xs, ys = [], []
        for lm, ref in DEPTH_PAIRS:
            k, r = base + lm, base + ref
            ok = (s.weights[:, k] > 0) & (s.weights[:, r] > 0)
            if name == "world":
                mp = s.world[:, lm, 2] - s.world[:, ref, 2]
                model = depth[:, k] - depth[:, r]
            else:
                mp = s.image_z[:, k] - s.image_z[:, r]
                model = s.camera.focal * (depth[:, k] / depth[:, r] - 1.0)
            ok &= np.isfinite(mp) & np.isfinite(model)
            xs.append(mp[ok])
            ys.append(model[ok])
        x, y = np.concatenate(xs), np.concatenate(ys)
        slope = float(x @ y / max(float(x @ x), 1e-12)) if x.size else 1.0
        corr = float(np.corrcoef(x, y)[0, 1]) if x.size > 2 else float("nan")
        out[f"{name}_z_scale"], out[f"{name}_z_corr"] = slope, corr
        out[f"{name}_z_pairs"] = int(x.size)
    return out


def per_landmark_table(s: Samples, offset: np.ndarray, basis: np.ndarray | None = None,
                       feats: np.ndarray | None = None) -> dict[str, dict[str, float]]:
    """Row name -> mean and median px error before (offset 0) / after, and the samples it
    rests on, for the rows seen in `s`."""
    before = pixel_errors(s, np.zeros_like(offset))
    after = pixel_errors(s, offset, basis, feats)
    out = {}
    for k in range(offset.shape[0]):
        seen = np.isfinite(before[:, k]) & np.isfinite(after[:, k])
        if seen.any():
            out[row_name(k)] = {"before_px": float(before[seen, k].mean()),
                                "after_px": float(after[seen, k].mean()),
                                "before_median_px": float(np.median(before[seen, k])),
                                "after_median_px": float(np.median(after[seen, k])),
                                "samples": int(seen.sum())}
    return out


POSE_NAMES = {0: "nose", 2: "left_eye", 5: "right_eye", 7: "left_ear", 8: "right_ear",
              11: "left_shoulder", 12: "right_shoulder", 13: "left_elbow",
              14: "right_elbow", 15: "left_wrist", 16: "right_wrist", 23: "left_hip",
              24: "right_hip"}


def row_name(k: int) -> str:
    """A readable name of a fitter-layout row."""
    for group, sl in cor.GROUP_SLICES.items():
        if sl.start <= k < sl.stop:
            i = k - sl.start
            if group == "pose":
                return f"pose:{POSE_NAMES.get(i, i)}"
            if group == "face":
                return f"face:ibug{i}"
            return f"{group}:{cor.HAND_MP_TO_SMPLX[i]}"
    raise IndexError(k)
