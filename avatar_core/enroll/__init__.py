"""Enrollment: one person, one fixed camera, one video -> a drivable avatar package.

Stages (each its own module): decode (``video``, or the ``frames`` stand-in) -> ``selection``
(quality, duplicates) -> ``tracking`` (the live tracker per frame) -> ``checks`` (refusals
before training) -> ``shape_fit`` (one shape, per-frame poses) -> ``dataset`` (one camera,
selfie masks) -> ``training`` (MVFGA, preset ``enroll``) -> the package. docs/enroll.md.
"""

from .config import EnrollConfig
from .errors import EnrollmentRefused
from .pipeline import enroll, enroll_video
from .result import EnrollResult, FrameCounts

__all__ = ["EnrollConfig", "EnrollResult", "EnrollmentRefused", "FrameCounts", "enroll",
           "enroll_video"]
