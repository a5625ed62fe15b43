"""Enrollment: one person, one fixed camera, one video -> a drivable avatar package.

Stages (each its own module): frames (decode, when ``video`` is absent) -> selection (quality,
duplicates) -> tracking (the live tracker per frame) -> checks (refusals before training) ->
shape fit (one shape, per-frame poses) -> masks (selfie segmentation) -> dataset (one camera)
-> training (MVFGA, preset ``enroll``) -> package.
"""

from .config import EnrollConfig
from .errors import EnrollmentRefused
from .result import EnrollResult, FrameCounts

__all__ = ["EnrollConfig", "EnrollResult", "EnrollmentRefused", "FrameCounts", "enroll",
           "enroll_video"]


def enroll(*args, **kwargs):  # noqa: ANN002, ANN003 - filled by pipeline.enroll
    from .pipeline import enroll as _enroll
    return _enroll(*args, **kwargs)


def enroll_video(*args, **kwargs):  # noqa: ANN002, ANN003
    from .pipeline import enroll_video as _enroll_video
    return _enroll_video(*args, **kwargs)
