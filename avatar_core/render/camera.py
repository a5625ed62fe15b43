"""Pinhole cameras in the OpenCV convention, with gsplat's pixel-centre convention.

Coordinate frames
-----------------
* World: metres. Body models are y-up with +z toward the viewer, so a camera in front of
  the body sits at +z looking toward -z.
* Camera (OpenCV): x right, y down, z forward. Extrinsics map world to camera:
  ``x_cam = R @ x_world + t``.

Pixel convention (the one gsplat / 3DGS use)
--------------------------------------------
``project`` returns continuous pixel coordinates ``(u, v) = (K @ x_cam)[:2] / z`` with no
offset. Pixel ``(col j, row i)`` covers the square ``[j, j+1) x [i, i+1)`` and its *centre*
is at ``(j + 0.5, i + 0.5)``: gsplat projects means with ``K`` exactly like this and its
rasterizer evaluates each pixel at ``(j + 0.5, i + 0.5)`` (see
``gsplat/cuda/_torch_impl.py``: ``pixel_coords = stack([x, y]) + 0.5``). The image spans
``[0, W] x [0, H]``; a centred principal point is ``(W / 2, H / 2)``. (This differs from
OpenCV's own remap/undistort functions, which put pixel centres at integers.) With this
convention ``resized`` scales K exactly by ``diag(W'/W, H'/H, 1)`` and ``cropped`` shifts
the principal point by the crop origin.

Handedness check: a camera at +z looking at the origin with world up +y has ``x_cam =
x_world`` and ``y_cam = -y_world``, so world +x (the subject's left) appears on the image's
RIGHT and world +y at the TOP; the image is not mirrored.

Everything is numpy float64. ``world_to_camera`` and ``project`` also accept torch tensors
(computed in torch, on the tensor's device and dtype); torch is never imported here at
module level.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["Camera", "intrinsics_from_fov", "look_at", "orbit"]

_ORTHO_ATOL = 1e-6


def _is_torch(x: Any) -> bool:
    return type(x).__module__.split(".")[0] == "torch"


def _as_int_size(value: Any, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        if isinstance(value, (float, np.floating)) and float(value).is_integer():
            value = int(value)
        else:
            raise ValueError(f"{name} must be an integer, got {value!r}")
    value = int(value)
    if value <= 0:
        raise ValueError(f"{name} must be positive, got {value}")
    return value


def _as_int(value: Any, name: str) -> int:
    if isinstance(value, bool):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)) and float(value).is_integer():
        return int(value)
    raise ValueError(f"{name} must be an integer, got {value!r}")


def _frozen_array(x: Any, shape: tuple[int, ...], name: str) -> np.ndarray:
    if _is_torch(x):
        x = x.detach().cpu().numpy()
    try:
        arr = np.array(x, dtype=np.float64)  # always a copy
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric array of shape {shape}") from exc
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains non-finite values (NaN or inf)")
    arr.flags.writeable = False
    return arr


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera: intrinsics ``K``, world->camera ``R``, ``t``, image ``width x height``.

    Arrays are copied to read-only float64 on construction. Raises ``ValueError`` naming the
    problem for bad shapes, non-finite values, non-positive sizes, a non-rotation ``R``
    (orthonormal with det +1 within 1e-6), non-positive focal lengths, or a last row of
    ``K`` other than ``(0, 0, 1)``.
    """

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        K = _frozen_array(self.K, (3, 3), "K")
        R = _frozen_array(self.R, (3, 3), "R")
        t = _frozen_array(self.t, (3,), "t")
        width = _as_int_size(self.width, "width")
        height = _as_int_size(self.height, "height")
        if not np.allclose(K[2], (0.0, 0.0, 1.0), rtol=0.0, atol=1e-9):
            raise ValueError(f"K's last row must be (0, 0, 1), got {K[2].tolist()}")
        if K[1, 0] != 0.0:
            raise ValueError(f"K[1, 0] must be 0, got {K[1, 0]}")
        if K[0, 0] <= 0.0 or K[1, 1] <= 0.0:
            raise ValueError(f"focal lengths fx, fy must be positive, got {K[0, 0]}, {K[1, 1]}")
        ortho_err = float(np.max(np.abs(R @ R.T - np.eye(3))))
        if ortho_err > _ORTHO_ATOL:
            raise ValueError(f"R is not orthonormal (max |R R^T - I| = {ortho_err:.3g})")
        det = float(np.linalg.det(R))
        if abs(det - 1.0) > _ORTHO_ATOL:
            raise ValueError(f"R must be a proper rotation with det +1, got det {det:.6g}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "width", width)
        object.__setattr__(self, "height", height)

    # -- equality (arrays make the dataclass default unusable) ---------------------------
    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        return (
            self.width == other.width
            and self.height == other.height
            and np.array_equal(self.K, other.K)
            and np.array_equal(self.R, other.R)
            and np.array_equal(self.t, other.t)
        )

    def __hash__(self) -> int:
        return hash((self.K.tobytes(), self.R.tobytes(), self.t.tobytes(), self.width, self.height))

    def __repr__(self) -> str:
        return (
            f"Camera(width={self.width}, height={self.height}, fx={self.fx:.6g}, "
            f"fy={self.fy:.6g}, cx={self.cx:.6g}, cy={self.cy:.6g}, "
            f"center={np.round(self.center, 6).tolist()})"
        )

    # -- properties ----------------------------------------------------------------------
    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, ``-R^T t``, shape [3]."""
        return -self.R.T @ self.t

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)``."""
        return self.width, self.height

    # -- geometry ------------------------------------------------------------------------
    def world_to_camera(self, points: Any) -> Any:
        """``R @ p + t`` for points ``[..., 3]`` (numpy in, float64 numpy out; torch in,
        torch out on the input's device and dtype)."""
        if _is_torch(points):
            import torch

            R = torch.as_tensor(self.R.copy(), dtype=points.dtype, device=points.device)
            t = torch.as_tensor(self.t.copy(), dtype=points.dtype, device=points.device)
            return points @ R.T + t
        pts = np.asarray(points, dtype=np.float64)
        if pts.shape[-1:] != (3,):
            raise ValueError(f"points must have shape [..., 3], got {pts.shape}")
        return pts @ self.R.T + self.t

    def project(self, points: Any) -> tuple[Any, Any]:
        """Project world points ``[..., 3]`` to pixels.

        Returns ``(uv, z)``: ``uv [..., 2] = (K @ x_cam)[:2] / z`` in gsplat's convention
        (pixel ``(j, i)`` has its centre at ``(j + 0.5, i + 0.5)``; the image spans
        ``[0, W] x [0, H]``) and ``z [...]`` the camera-space depth. Nothing is clipped:
        points with ``z <= 0`` get meaningless (possibly inf/NaN) ``uv``; check ``z``.
        """
        xc = self.world_to_camera(points)
        z = xc[..., 2]
        if _is_torch(xc):
            import torch

            K = torch.as_tensor(self.K.copy(), dtype=xc.dtype, device=xc.device)
            uvw = xc @ K.T
            return uvw[..., :2] / z[..., None], z
        uvw = xc @ self.K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = uvw[..., :2] / z[..., None]
        return uv, z

    def viewmat(self) -> np.ndarray:
        """The 4x4 world->camera matrix ``[[R, t], [0, 1]]`` (gsplat's ``viewmats``)."""
        M = np.eye(4)
        M[:3, :3] = self.R
        M[:3, 3] = self.t
        return M

    def to_torch(self, device: Any = None, dtype: Any = None) -> tuple[Any, Any]:
        """``(viewmat [4, 4], K [3, 3])`` as torch tensors (float32 unless ``dtype`` given)."""
        import torch

        dtype = torch.float32 if dtype is None else dtype
        return (
            torch.as_tensor(self.viewmat(), dtype=dtype, device=device),
            torch.as_tensor(self.K.copy(), dtype=dtype, device=device),
        )

    # -- image-space edits ---------------------------------------------------------------
    def resized(self, width: int, height: int) -> Camera:
        """Same view rendered at ``width x height``: K's first row scales by ``width / W``
        and its second by ``height / H`` (exact in the pixel-centre-at-+0.5 convention)."""
        width = _as_int_size(width, "width")
        height = _as_int_size(height, "height")
        S = np.diag([width / self.width, height / self.height, 1.0])
        return Camera(S @ self.K, self.R, self.t, width, height)

    def cropped(self, x0: int, y0: int, width: int, height: int) -> Camera:
        """The window whose top-left pixel is ``(x0, y0)`` of this image, of size
        ``width x height``: the principal point moves by ``(-x0, -y0)``. The window may
        extend past the image (padding); sizes must be positive."""
        x0 = _as_int(x0, "x0")
        y0 = _as_int(y0, "y0")
        width = _as_int_size(width, "width")
        height = _as_int_size(height, "height")
        K = self.K.copy()
        K[0, 2] -= x0
        K[1, 2] -= y0
        return Camera(K, self.R, self.t, width, height)

    # -- serialisation -------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly dict of plain lists / ints (round-trips exactly)."""
        return {
            "K": self.K.tolist(),
            "R": self.R.tolist(),
            "t": self.t.tolist(),
            "width": self.width,
            "height": self.height,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Camera:
        missing = [k for k in ("K", "R", "t", "width", "height") if k not in d]
        if missing:
            raise ValueError(f"camera dict is missing keys {missing}")
        return cls(K=d["K"], R=d["R"], t=d["t"], width=d["width"], height=d["height"])


def intrinsics_from_fov(width: int, height: int, fov_y_deg: float) -> np.ndarray:
    """K [3, 3] with square pixels, vertical field of view ``fov_y_deg`` over the full image
    height, and the principal point at the image centre ``(W / 2, H / 2)``."""
    width = _as_int_size(width, "width")
    height = _as_int_size(height, "height")
    fov = float(fov_y_deg)
    if not (0.0 < fov < 180.0):
        raise ValueError(f"fov_y_deg must be in (0, 180), got {fov_y_deg}")
    f = 0.5 * height / math.tan(math.radians(fov) / 2.0)
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def _vec3(x: Any, name: str) -> np.ndarray:
    arr = np.asarray(x, dtype=np.float64)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be a finite 3-vector, got {x!r}")
    return arr


def look_at(
    eye: Any,
    target: Any,
    up: Any = (0.0, 1.0, 0.0),
    *,
    width: int,
    height: int,
    fov_y_deg: float = 30.0,
) -> Camera:
    """Camera at ``eye`` looking at ``target``; ``up`` (world, default +y) appears at the top
    of the image (the camera's y axis points down, so ``y_cam`` is along ``-up``)."""
    eye = _vec3(eye, "eye")
    target = _vec3(target, "target")
    up = _vec3(up, "up")
    forward = target - eye
    n = np.linalg.norm(forward)
    if n < 1e-12:
        raise ValueError("eye and target coincide")
    z = forward / n
    nu = np.linalg.norm(up)
    if nu < 1e-12:
        raise ValueError("up must be non-zero")
    x = np.cross(z, up / nu)  # right = forward x up (= down x forward)
    nx = np.linalg.norm(x)
    if nx < 1e-9:
        raise ValueError("viewing direction is parallel to up")
    x /= nx
    y = np.cross(z, x)  # down
    R = np.stack([x, y, z])
    t = -R @ eye
    return Camera(intrinsics_from_fov(width, height, fov_y_deg), R, t, width, height)


def orbit(
    target: Any,
    yaw_deg: float,
    pitch_deg: float,
    distance: float,
    *,
    width: int,
    height: int,
    fov_y_deg: float = 30.0,
) -> Camera:
    """Camera on a sphere of radius ``distance`` around ``target``, looking at it, with world
    +y up.

    yaw 0, pitch 0: on the +z axis of the target (front view of a body). yaw > 0 moves the
    camera toward +x (the subject's left); yaw 90 puts it on +x. pitch > 0 raises it above
    the target. The image x axis is always horizontal, so pitch +-90 (looking straight
    down/up) is well defined and continuous with smaller pitches (at pitch +90 with yaw 0
    the image top shows world -z). Agrees with ``look_at`` whenever |pitch| < 90.
    """
    target = _vec3(target, "target")
    d = float(distance)
    if not (math.isfinite(d) and d > 0.0):
        raise ValueError(f"distance must be positive, got {distance}")
    yaw = math.radians(float(yaw_deg))
    pitch = math.radians(float(pitch_deg))
    cy_, sy_ = math.cos(yaw), math.sin(yaw)
    cp, sp = math.cos(pitch), math.sin(pitch)
    direction = np.array([sy_ * cp, sp, cy_ * cp])  # target -> camera, unit
    eye = target + d * direction
    z = -direction
    x = np.array([cy_, 0.0, -sy_])  # forward x up, normalised; independent of pitch
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    t = -R @ eye
    return Camera(intrinsics_from_fov(width, height, fov_y_deg), R, t, width, height)
