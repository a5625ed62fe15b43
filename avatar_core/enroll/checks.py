"""The refusals that need the tracker: nobody, two people, too few usable frames, no turn.
Each raised before anything is written or trained."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .config import EnrollConfig
from .errors import EnrollmentRefused

MIN_TRACKED_FRACTION = 0.25   # of the frames checked: fewer tracked is "no person"
TWO_FACES_FRACTION = 0.3      # of the frames with a face: more with two is "two people"


def check_people(tracked: int, checked: int, faces: Sequence[int]) -> None:
    if checked == 0 or tracked < MIN_TRACKED_FRACTION * checked:
        raise EnrollmentRefused(
            "no_person", f"No person was found in the video ({tracked} of {checked} frames "
            "tracked).", "Stand in front of the camera, head to waist in view, facing it.")
    with_face = [n for n in faces if n > 0]
    two = sum(n >= 2 for n in with_face)
    if with_face and two > TWO_FACES_FRACTION * len(with_face):
        raise EnrollmentRefused(
            "two_people", f"Two or more people are in the video ({two} of {len(with_face)} "
            "frames with a face show more than one).",
            "Record alone: only the person to enroll in view.")


def check_length(usable: int, total: int, config: EnrollConfig) -> None:
    if usable < config.min_frames:
        raise EnrollmentRefused(
            "too_short", f"Only {usable} usable frames of {total} (at least "
            f"{config.min_frames} needed).",
            "Record longer (20-60 s), turning slowly, in good light.")


def check_turn(yaws_deg: Sequence[float], config: EnrollConfig) -> float:
    """The range of the person's turn (deg); refused below ``min_yaw_range_deg``."""
    span = float(np.ptp(yaws_deg)) if len(yaws_deg) else 0.0
    if span < config.min_yaw_range_deg:
        raise EnrollmentRefused(
            "never_turns", f"The person turns only {span:.0f} degrees (at least "
            f"{config.min_yaw_range_deg:.0f} needed).",
            "Turn slowly to one side until you face sideways, then to the other.")
    return span
