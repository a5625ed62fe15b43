"""Enrollment settings: the sizes of one run and the limits it refuses input by."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class EnrollConfig:
    """One enrollment run. Every limit here is listed in docs/security.md."""

    iterations: int = 3_000          # training iterations (monocular MVFGA, preset "enroll")
    resolution: int = 512            # longest side of the training images, px
    seed: int = 0
    fine_tune: bool = True           # per-frame pose/expression deltas trained with the Gaussians
    masks: bool = True               # selfie-segmentation masks + mask loss
    min_frames: int = 24             # usable frames below this: refused (too short)
    max_frames: int = 300            # frames kept for training (evenly subsampled above this)
    min_yaw_range_deg: float = 45.0  # the person must turn at least this much (max - min yaw)
    min_brightness: float = 0.12     # mean luma in [0, 1] below this: too dark
    blur_ratio: float = 0.35         # a frame sharper than this x the video's median is kept
    min_sharpness: float = 2e-4      # median Laplacian variance (luma in [0, 1]) below: blurred
    duplicate_threshold: float = 0.002  # mean abs luma change below this: a duplicate
    track_size: int = 256            # longest side the tracker sees, px
    fit_iterations: int = 200        # joint shape + per-frame pose fit (Adam steps)
    preflight_frames: int = 8        # tracked first to refuse nobody / two people early (0: off)

    def __post_init__(self) -> None:
        checks = (
            (self.iterations >= 1, "iterations", "must be >= 1"),
            (self.resolution >= 32, "resolution", "must be >= 32 px"),
            (self.min_frames >= 2, "min_frames", "must be >= 2"),
            (self.max_frames >= self.min_frames, "max_frames", "must be >= min_frames"),
            (0 <= self.min_yaw_range_deg <= 360, "min_yaw_range_deg", "must be in [0, 360]"),
            (0 <= self.min_brightness < 1, "min_brightness", "must be in [0, 1)"),
            (0 < self.blur_ratio <= 1, "blur_ratio", "must be in (0, 1]"),
            (self.min_sharpness >= 0, "min_sharpness", "must be >= 0"),
            (self.duplicate_threshold >= 0, "duplicate_threshold", "must be >= 0"),
            (self.track_size >= 64, "track_size", "must be >= 64 px"),
            (self.fit_iterations >= 0, "fit_iterations", "must be >= 0"),
            (self.preflight_frames >= 0, "preflight_frames", "must be >= 0"),
        )
        for ok, name, what in checks:
            if not ok:
                raise ValueError(f"EnrollConfig.{name} {what}, got {getattr(self, name)!r}")
