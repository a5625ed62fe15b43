"""The capture rig of the software studio, after the MVFGA paper's.

17 cameras: 15 on a 150-degree arc in front of the subject, alternating between head and
chest height (the centre one at head height), and 2 behind. Each is a 1920x1080 camera
(focal length in pixels at that size); the dataset image is a centred square crop of the
sensor (or the full frame) scaled to the chosen resolution, so intrinsics scale exactly.
Every camera is perturbed a little from its nominal placement (position, orientation, focal
length, principal point), as a real rig is after calibration; the perturbed camera *is* the
exact calibration that the dataset stores.

World frame: the body model's (metres, y up, the subject faces +z). Camera names: front
cameras ``cam00``..``cam14`` from the subject's right (-x) to their left (+x), then the rear
ones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..render.camera import Camera, look_at

__all__ = ["RigCamera", "StudioConfig", "studio_rig"]

SENSOR_WIDTH, SENSOR_HEIGHT = 1920, 1080


@dataclass(frozen=True)
class StudioConfig:
    """Nominal rig geometry; lengths in metres, angles in degrees, focal in 1080p pixels."""

    num_cameras: int = 17
    arc_deg: float = 150.0
    radius: float = 1.5
    target: tuple[float, float, float] = (0.0, 0.40, 0.0)  # upper chest of the synthetic body
    head_height: float = 0.62
    chest_height: float = 0.32
    rear_azimuth_deg: float = 155.0  # rear cameras at +-this azimuth
    focal_px: float = 1480.0  # ~40 deg vertical field of view on the 1080-pixel side
    crop: str = "square"  # "square": centred 1080x1080; "full": the whole 16:9 frame
    fps: float = 25.0
    # Calibration jitter (standard deviations).
    position_jitter: float = 0.005
    rotation_jitter_deg: float = 0.3
    focal_jitter: float = 0.005  # relative
    principal_jitter_px: float = 4.0  # in 1080p pixels

    def __post_init__(self) -> None:
        if self.num_cameras < 1:
            raise ValueError("the rig needs at least one camera")
        if self.crop not in ("square", "full"):
            raise ValueError(f"crop must be 'square' or 'full', got {self.crop!r}")
        if not (0.0 < self.arc_deg <= 360.0 and self.radius > 0.0 and self.focal_px > 0.0):
            raise ValueError("arc_deg, radius and focal_px must be positive")


@dataclass(frozen=True)
class RigCamera:
    name: str
    role: str  # "front" | "rear"
    camera: Camera


def _layout(n: int) -> tuple[int, int]:
    """(front, rear) counts: two rear cameras from 8 up, one from 4 up (17 -> 15 + 2)."""
    rear = 2 if n >= 8 else 1 if n >= 4 else 0
    return n - rear, rear


def _sensor_camera(eye: np.ndarray, target: np.ndarray, focal: float, principal: np.ndarray
                   ) -> Camera:
    cam = look_at(eye, target, width=SENSOR_WIDTH, height=SENSOR_HEIGHT)
    K = np.array([[focal, 0.0, principal[0]], [0.0, focal, principal[1]], [0.0, 0.0, 1.0]])
    return Camera(K, cam.R, cam.t, SENSOR_WIDTH, SENSOR_HEIGHT)


def _jittered(cam: Camera, cfg: StudioConfig, rng: np.random.Generator) -> Camera:
    """Small rotation about the camera centre and a shifted centre; K is jittered elsewhere."""
    centre = cam.center + rng.normal(0.0, cfg.position_jitter, 3)
    delta = Rotation.from_rotvec(np.deg2rad(rng.normal(0.0, cfg.rotation_jitter_deg, 3)))
    R = delta.as_matrix() @ cam.R
    return Camera(cam.K, R, -R @ centre, cam.width, cam.height)


def _to_image(cam: Camera, cfg: StudioConfig, resolution: int) -> Camera:
    if cfg.crop == "square":
        x0 = (SENSOR_WIDTH - SENSOR_HEIGHT) // 2
        return cam.cropped(x0, 0, SENSOR_HEIGHT, SENSOR_HEIGHT).resized(resolution, resolution)
    width = int(round(resolution * SENSOR_WIDTH / SENSOR_HEIGHT))
    return cam.resized(width, resolution)


def studio_rig(resolution: int = 512, config: StudioConfig | None = None, *, seed: int = 0,
               jitter: bool = True) -> list[RigCamera]:
    """The calibrated rig: image height `resolution` (square images unless crop='full')."""
    cfg = config or StudioConfig()
    if resolution < 8:
        raise ValueError(f"resolution must be at least 8 pixels, got {resolution}")
    rng = np.random.default_rng([seed, 1717])
    target = np.asarray(cfg.target, dtype=np.float64)
    n_front, n_rear = _layout(cfg.num_cameras)
    half = cfg.arc_deg / 2.0
    azimuths = np.linspace(-half, half, n_front) if n_front > 1 else np.zeros(1)
    rear = [cfg.rear_azimuth_deg, -cfg.rear_azimuth_deg][:n_rear] if n_rear == 2 else [180.0]
    # Alternate heights so that the centre camera films the face level.
    specs = [("front", az, cfg.head_height if (i - n_front // 2) % 2 == 0 else cfg.chest_height)
             for i, az in enumerate(azimuths)]
    specs += [("rear", az, cfg.head_height) for az in rear[:n_rear]]
    out = []
    for i, (role, az, height) in enumerate(specs):
        a = math.radians(az)
        eye = np.array([target[0] + cfg.radius * math.sin(a), height,
                        target[2] + cfg.radius * math.cos(a)])
        focal = cfg.focal_px * (1.0 + (rng.normal(0.0, cfg.focal_jitter) if jitter else 0.0))
        principal = np.array([SENSOR_WIDTH / 2.0, SENSOR_HEIGHT / 2.0])
        if jitter:
            principal = principal + rng.normal(0.0, cfg.principal_jitter_px, 2)
        cam = _sensor_camera(eye, target, focal, principal)
        if jitter:
            cam = _jittered(cam, cfg, rng)
        out.append(RigCamera(f"cam{i:02d}", role, _to_image(cam, cfg, resolution)))
    return out
