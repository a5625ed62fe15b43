"""Forward-only numba twins of :func:`projection.project_gaussians` and :func:`sh.sh_to_rgb`.

Used by the cpu backend when no gradient is needed (streaming): the torch versions spend most
of their time in per-op overhead on ~150 small tensor ops, these fuse each into one parallel
loop over the Gaussians. Same formulas (float64 inside, float32 out); tests check them
against the torch versions, which remain the reference and carry the gradients.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .contract import (
    EIG_FLOOR,
    EPS2D,
    FAR_PLANE,
    FRUSTUM_MARGIN,
    MAX_BOUND_PX,
    MAX_SCREEN_PX,
    MAX_SIGMA_PX,
    NEAR_PLANE,
    RADIUS_SIGMAS,
    SH_COEFF_MAX,
)
from .sh import SH_C0, SH_C1, SH_C2, SH_C3

__all__ = ["project_np", "sh_rgb_np"]

_QUAT_EPS = 1e-12


@njit(parallel=True, cache=True)
def _project_kernel(means, quats, scales, opacities, viewmat, K, width, height, near, far,
                    eps2d, max_sigma, antialiased, means2d, conics, depths, radii, opac_out):
    R = viewmat[:3, :3].astype(np.float64)
    t = viewmat[:3, 3].astype(np.float64)
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    margin_x, margin_y = FRUSTUM_MARGIN * tan_fovx, FRUSTUM_MARGIN * tan_fovy
    lim_x_pos, lim_x_neg = (width - cx) / fx + margin_x, cx / fx + margin_x
    lim_y_pos, lim_y_neg = (height - cy) / fy + margin_y, cy / fy + margin_y
    lim = 1.0 + max(abs(lim_x_pos), abs(lim_x_neg), abs(lim_y_pos), abs(lim_y_neg))
    f_max = max(abs(fx), abs(fy))
    for g in prange(means.shape[0]):
        # scalar code only: no temporary arrays (allocations) and no BLAS calls per Gaussian
        px, py, pz = float(means[g, 0]), float(means[g, 1]), float(means[g, 2])
        xc = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]  # camera space
        yc = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
        z = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
        zp = z if z > 0.0 else 1.0
        mx = (K[0, 0] * xc + K[0, 1] * yc + K[0, 2] * z) / zp
        my = (K[1, 1] * yc + K[1, 2] * z) / zp
        s0, s1, s2 = float(scales[g, 0]), float(scales[g, 1]), float(scales[g, 2])
        bound = f_max / zp * lim * max(abs(s0), abs(s1), abs(s2))
        # the sanity rules of projection._sane_rows (written so that NaN culls)
        ok = (near < z < far) and abs(mx) <= MAX_SCREEN_PX and abs(my) <= MAX_SCREEN_PX \
            and bound <= MAX_BOUND_PX
        means2d[g, 0] = mx if ok else K[0, 2]  # the stand-in (0, 0, 1) of the torch version
        means2d[g, 1] = my if ok else K[1, 2]
        depths[g] = z if ok else 0.0
        radii[g] = 0
        conics[g, 0] = conics[g, 1] = conics[g, 2] = 0.0
        opac_out[g] = opacities[g]
        if not ok:
            if antialiased:
                opac_out[g] = 0.0
            continue
        # rotation (zero quaternion -> identity) times scales, into camera space
        w, x, y, zq = (np.float64(quats[g, 0]), np.float64(quats[g, 1]), np.float64(quats[g, 2]),
                       np.float64(quats[g, 3]))
        nq = math.sqrt(w * w + x * x + y * y + zq * zq)
        inv = 1.0 / nq if nq > _QUAT_EPS else 0.0
        w, x, y, zq = w * inv, x * inv, y * inv, zq * inv
        q00, q01, q02 = (1 - 2 * (y * y + zq * zq)) * s0, 2 * (x * y - w * zq) * s1, \
            2 * (x * zq + w * y) * s2
        q10, q11, q12 = 2 * (x * y + w * zq) * s0, (1 - 2 * (x * x + zq * zq)) * s1, \
            2 * (y * zq - w * x) * s2
        q20, q21, q22 = 2 * (x * zq - w * y) * s0, 2 * (y * zq + w * x) * s1, \
            (1 - 2 * (x * x + y * y)) * s2
        u = min(max(xc / z, -lim_x_neg), lim_x_pos)  # Jacobian at the clamped mean
        v = min(max(yc / z, -lim_y_neg), lim_y_pos)
        c00 = c01 = c11 = 0.0
        for k in range(3):  # column k of Mc = R (Rq S), then of J Mc (rows T0, T1)
            qk0, qk1, qk2 = (q00, q10, q20) if k == 0 else (q01, q11, q21) if k == 1 \
                else (q02, q12, q22)
            m0 = R[0, 0] * qk0 + R[0, 1] * qk1 + R[0, 2] * qk2
            m1 = R[1, 0] * qk0 + R[1, 1] * qk1 + R[1, 2] * qk2
            m2 = R[2, 0] * qk0 + R[2, 1] * qk1 + R[2, 2] * qk2
            t0 = (fx / z) * (m0 - u * m2)
            t1 = (fy / z) * (m1 - v * m2)
            c00 += t0 * t0
            c01 += t0 * t1
            c11 += t1 * t1
        det_orig = c00 * c11 - c01 * c01
        c00 += eps2d
        c11 += eps2d
        det = c00 * c11 - c01 * c01
        ca, cb, cc = np.float32(c11 / det), np.float32(-c01 / det), np.float32(c00 / det)
        # positive definite as stored (float32), as the torch version demands
        if not (det > 0.0 and math.isfinite(det) and ca > 0.0 and cc > 0.0
                and float(ca) * float(cc) - float(cb) * float(cb) > 0.0):
            if antialiased:
                opac_out[g] = 0.0
            continue
        conics[g, 0], conics[g, 1], conics[g, 2] = ca, cb, cc
        if antialiased:
            opac_out[g] = opacities[g] * math.sqrt(max(det_orig / det, 0.0))
        b = 0.5 * (c00 + c11)
        lam = b + math.sqrt(max(b * b - det, EIG_FLOOR))
        if not lam <= max_sigma * max_sigma:  # also NaN: culled before any int conversion
            continue
        r = math.ceil(RADIUS_SIGMAS * math.sqrt(max(lam, 0.0)))
        mx, my = means2d[g, 0], means2d[g, 1]
        if r > 0 and mx + r > 0 and mx - r < width and my + r > 0 and my - r < height:
            radii[g] = r


def project_np(means, quats, scales, opacities, viewmat, K, width, height, near=NEAR_PLANE,
               antialiased=False, far=FAR_PLANE, eps2d=EPS2D, max_sigma_px=MAX_SIGMA_PX):
    """numpy in (float32 or float64), -> ``(means2d [N, 2], conics [N, 3], depths [N],
    radii [N] int32, opacities [N])``, float32; the conventions of ``project_gaussians``."""
    n = means.shape[0]
    means2d = np.empty((n, 2), np.float32)
    conics = np.empty((n, 3), np.float32)
    depths = np.empty(n, np.float32)
    radii = np.empty(n, np.int32)
    opac = np.empty(n, np.float32)
    _project_kernel(means, quats, scales, opacities, np.asarray(viewmat, np.float64),
                    np.asarray(K, np.float64), width, height, near, far, eps2d,
                    float(max_sigma_px), bool(antialiased), means2d, conics, depths, radii, opac)
    return means2d, conics, depths, radii, opac


@njit(cache=True, inline="always")
def _c(x):
    """An SH coefficient clamped to +-SH_COEFF_MAX, float64 (as sh_to_rgb)."""
    return min(max(float(x), -SH_COEFF_MAX), SH_COEFF_MAX)


@njit(parallel=True, cache=True)
def _sh_kernel(degree, sh, means, campos, radii, out):
    C2, C3 = SH_C2, SH_C3
    for g in prange(means.shape[0]):
        if radii[g] <= 0:
            continue
        x = float(means[g, 0]) - campos[0]
        y = float(means[g, 1]) - campos[1]
        z = float(means[g, 2]) - campos[2]
        nd = math.sqrt(x * x + y * y + z * z)
        inv = 1.0 / nd if nd > 1e-12 else 0.0
        x, y, z = x * inv, y * inv, z * inv
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        for c in range(3):
            v = SH_C0 * _c(sh[g, 0, c])
            if degree > 0:
                v += SH_C1 * (-y * _c(sh[g, 1, c]) + z * _c(sh[g, 2, c]) - x * _c(sh[g, 3, c]))
            if degree > 1:
                v += (C2[0] * xy * _c(sh[g, 4, c]) + C2[1] * yz * _c(sh[g, 5, c])
                      + C2[2] * (2.0 * zz - xx - yy) * _c(sh[g, 6, c])
                      + C2[3] * xz * _c(sh[g, 7, c])
                      + C2[4] * (xx - yy) * _c(sh[g, 8, c]))
            if degree > 2:
                v += (C3[0] * y * (3.0 * xx - yy) * _c(sh[g, 9, c])
                      + C3[1] * xy * z * _c(sh[g, 10, c])
                      + C3[2] * y * (4.0 * zz - xx - yy) * _c(sh[g, 11, c])
                      + C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * _c(sh[g, 12, c])
                      + C3[4] * x * (4.0 * zz - xx - yy) * _c(sh[g, 13, c])
                      + C3[5] * z * (xx - yy) * _c(sh[g, 14, c])
                      + C3[6] * x * (xx - 3.0 * yy) * _c(sh[g, 15, c]))
            out[g, c] = max(v + 0.5, 0.0)


def sh_rgb_np(degree, sh, means, campos, radii, out):
    """``out[:, :3] = max(SH(normalize(mean - campos)) + 0.5, 0)`` for Gaussians with
    ``radii > 0`` (others untouched); ``sh [N, K >= (degree + 1)^2, 3]``, each coefficient
    clamped to ``+-SH_COEFF_MAX`` (as ``sh_to_rgb``)."""
    _sh_kernel(int(degree), sh, means, np.asarray(campos, np.float64), radii, out)
