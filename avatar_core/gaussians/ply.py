"""Export world-space Gaussians as a standard 3DGS .ply, which common splat viewers open.

Layout of the 3DGS reference implementation: x y z, nx ny nz (zeros), f_dc_0..2, f_rest_0..,
opacity (logit), scale_0..2 (log), rot_0..3 (w, x, y, z). f_rest is channel-major: all
red higher-order coefficients, then green, then blue.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..render.types import GaussianSet


def ply_arrays(gaussians: GaussianSet) -> dict[str, np.ndarray]:
    """Named per-Gaussian columns in 3DGS order."""
    g = {k: getattr(gaussians, k).detach().cpu().double().numpy()
         for k in ("means", "quats", "scales", "opacities", "sh")}
    n, k = g["sh"].shape[:2]
    cols: dict[str, np.ndarray] = {}
    for i, axis in enumerate("xyz"):
        cols[axis] = g["means"][:, i]
    for axis in ("nx", "ny", "nz"):
        cols[axis] = np.zeros(n)
    for c in range(3):
        cols[f"f_dc_{c}"] = g["sh"][:, 0, c]
    rest = g["sh"][:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (k - 1))  # [N, 3 (K - 1)]
    for i in range(rest.shape[1]):
        cols[f"f_rest_{i}"] = rest[:, i]
    op = np.clip(g["opacities"], 1e-7, 1 - 1e-7)
    cols["opacity"] = np.log(op / (1 - op))
    for i in range(3):
        cols[f"scale_{i}"] = np.log(np.maximum(g["scales"][:, i], 1e-30))
    quats = g["quats"] / np.maximum(np.linalg.norm(g["quats"], axis=1, keepdims=True), 1e-12)
    for i in range(4):
        cols[f"rot_{i}"] = quats[:, i]
    return cols


def export_ply(gaussians: GaussianSet, path: str | Path) -> Path:
    """Write a binary little-endian 3DGS .ply (float32 properties)."""
    path = Path(path)
    cols = ply_arrays(gaussians)
    n = len(cols["x"])
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property float {name}" for name in cols]
    header.append("end_header")
    data = np.stack([cols[k] for k in cols], axis=1).astype("<f4")  # [N, columns]
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(data.tobytes())
    return path
