"""Fitting the landmark embedding from studio samples: per landmark, the offset in its anchor
joint's frame that best explains where MediaPipe put it, over every sample where it was seen.

    min_o  sum_s rho(|project(P_sk + R_sk o) - u_sk|) + ridge n_k |o|^2

(P_sk the model point at the true parameters, R_sk its anchor joint's world rotation, u_sk
the tracked pixel; rho the fitter's pseudo-Huber, by iterative reweighting; Gauss-Newton on
3 unknowns per landmark). The ridge keeps the along-the-ray part, which a few views barely
see, small. Plus the two z scales of the 3D cues (least squares through the origin).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..track.fit import correspondence as cor
from ..track.fit.camera import WebcamCamera, project_points
from ..track.fit.world_cues import DEPTH_PAIRS

HUBER_PX = 8.0
RIDGE_PX2_PER_M2 = 1000.0  # per sample: a 1 cm offset costs 0.1 px^2, 3 cm 0.9 px^2
MIN_SAMPLES = 12           # a landmark seen fewer times keeps offset 0
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

    def __len__(self) -> int:
        return self.pixels.shape[0]

    def subset(self, keep: np.ndarray) -> Samples:
        return Samples(self.pixels[keep], self.weights[keep], self.points[keep],
                       self.rotations[keep], self.image_z[keep], self.world[keep], self.camera)


def embedded_points(s: Samples, offset: np.ndarray) -> np.ndarray:
    """[S, K, 3] the model points moved by `offset` [K, 3] in their anchors' frames."""
    return s.points + np.einsum("skab,kb->ska", s.rotations, offset)


def pixel_errors(s: Samples, offset: np.ndarray) -> np.ndarray:
    """[S, K] px distance of each tracked landmark from its embedded model point (NaN where
    not tracked)."""
    pts = embedded_points(s, offset).reshape(-1, 3)
    proj, _ = project_points(pts, s.camera)
    err = np.linalg.norm(proj.reshape(*s.pixels.shape) - s.pixels, axis=-1)
    return np.where(s.weights > 0, err, np.nan)


def fit_offsets(s: Samples, anchors: np.ndarray, ridge: float = RIDGE_PX2_PER_M2,
                min_samples: int = MIN_SAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """(offset [K, 3], samples used [K]) per row with an anchor and a model point."""
    k_rows = s.pixels.shape[1]
    offset, count = np.zeros((k_rows, 3)), np.zeros(k_rows, dtype=np.int64)
    for k in range(k_rows):
        used = (s.weights[:, k] > 0) & np.isfinite(s.points[:, k]).all(-1)
        count[k] = int(used.sum())
        if anchors[k] < 0 or count[k] < min_samples:
            continue
        p, r, u = s.points[used, k], s.rotations[used, k], s.pixels[used, k]
        o = np.zeros(3)
        for _ in range(GAUSS_NEWTON_STEPS):
            proj, d_proj = project_points(p + r @ o, s.camera)
            res = proj - u                                            # [n, 2]
            w = 1.0 / np.sqrt(1.0 + (res ** 2).sum(-1) / HUBER_PX ** 2)  # pseudo-Huber IRLS
            jac = d_proj @ r                                          # [n, 2, 3]
            jtj = np.einsum("n,nai,naj->ij", w, jac, jac) + ridge * count[k] * np.eye(3)
            jtr = np.einsum("n,nai,na->i", w, jac, res) + ridge * count[k] * o
            step = np.linalg.solve(jtj, -jtr)
            o = o + step
            if np.abs(step).max() < 1e-6:
                break
        offset[k] = o
    return offset, count


def z_scales(s: Samples, offset: np.ndarray) -> dict[str, float]:
    """BlazePose's world and image z against the model's depth differences over
    `world_cues.DEPTH_PAIRS`: the slope (model = slope x MediaPipe, through the origin) and
    the correlation of each."""
    depth = -embedded_points(s, offset)[..., 2]                            # [S, K]
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


def per_landmark_table(s: Samples, offset: np.ndarray) -> dict[str, dict[str, float]]:
    """Row name -> mean px error before (offset 0) / after, and the samples it rests on, for
    the rows seen in `s`."""
    before = pixel_errors(s, np.zeros_like(offset))
    after = pixel_errors(s, offset)
    out = {}
    for k in range(offset.shape[0]):
        seen = np.isfinite(before[:, k]) & np.isfinite(after[:, k])
        if seen.any():
            out[row_name(k)] = {"before_px": float(before[seen, k].mean()),
                                "after_px": float(after[seen, k].mean()),
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
