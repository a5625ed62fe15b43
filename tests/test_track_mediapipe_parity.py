"""Landmarks on real photographs against MediaPipe's own graphs, within stated bounds.

scikit-image's astronaut and cameraman and matplotlib's Grace Hopper, each as shipped, rotated
25 and 90 deg, letterboxed to 16:9 and upscaled 2x; MediaPipe's CPU graphs (the `mediapipe`
package, the `mediapipe-parity` extra) and avatar_core.track's pipelines run on the same
pictures with the same .tflite models (ours converted to ONNX). No photograph shows a bare
hand, so hands are compared on two renders of the studio's actor. `bench/track_parity.py`
prints the full table; docs/tracking.md ("Parity with MediaPipe on photographs") has the
measured values the bounds below are set from (after the #). Skips where mediapipe is not
importable or the models cannot be fetched.
"""

from __future__ import annotations

import pytest

pytest.importorskip("onnxruntime")

from avatar_core.track.models import ModelFetchError, fetch_models  # noqa: E402
from bench import track_parity as tp  # noqa: E402

# Pose: the crops agree to float32 rounding of the ROI, but a landmark whose heatmap window
# peaks near the 0.5 refinement threshold, or whose raw point sits on a heatmap cell edge,
# jumps when the crop moves by a fraction of a pixel (docs/tracking.md).
POSE_MEDIAN_PX = 1.0      # worst picture 0.41 (cameraman): most landmarks agree exactly
POSE_MEAN_PX = 4.0        # 2.51 (grace_hopper upscaled); 0.14-1.98 at 1x
POSE_MAX_PX = 40.0        # 28.3 (one landmark of 33 at the refinement threshold)
POSE_OVER_2PX = 14        # landmarks > 2 px off per picture: at most 10 of 33
POSE_VISIBILITY = 0.01    # 0.0052
FACE_MEAN_PX = 0.1        # 0.02
FACE_MAX_PX = 0.5         # 0.05
HAND_MEAN_PX = 0.1        # 0.00
HAND_MAX_PX = 0.5         # 0.01


@pytest.fixture(scope="module")
def comparisons():
    why = tp.reference_available()
    if why:
        pytest.skip(why)
    try:
        fetch_models()
    except ModelFetchError as exc:
        pytest.skip(f"cannot fetch the MediaPipe landmark models: {exc}")
    ours = tp.Ours(threads=1)
    return [c for case, rgb in tp.cases() for c in tp.compare(case, rgb, ours)]


def _of(comparisons, kind):
    return [c for c in comparisons if c.kind == kind]


def test_the_same_targets_are_found(comparisons):
    """Detection agrees picture by picture: the detectors see the same letterboxed input."""
    mismatched = [(c.case, c.kind, c.found_ours, c.found_reference) for c in comparisons
                  if c.found_ours != c.found_reference]
    assert not mismatched
    # The bounds below are not vacuous: every photograph has a body, most a face, the renders
    # three hands between them.
    assert all(c.found_reference == 1 for c in _of(comparisons, "pose"))
    assert sum(c.found_reference for c in _of(comparisons, "face")) >= 12
    assert sum(c.found_reference for c in _of(comparisons, "hands")) >= 3


def test_pose_landmarks_match_mediapipe(comparisons):
    for c in _of(comparisons, "pose"):
        assert c.median_px < POSE_MEDIAN_PX, (c.case, c.median_px)
        assert c.mean_px < POSE_MEAN_PX, (c.case, c.mean_px)
        assert c.max_px < POSE_MAX_PX, (c.case, c.max_px)
        assert c.count_over(2.0) <= POSE_OVER_2PX, (c.case, c.count_over(2.0))
        assert c.visibility_error < POSE_VISIBILITY, (c.case, c.visibility_error)


def test_face_landmarks_match_mediapipe(comparisons):
    for c in _of(comparisons, "face"):
        if c.distances.size:
            assert c.mean_px < FACE_MEAN_PX and c.max_px < FACE_MAX_PX, (c.case, c.max_px)


def test_hand_landmarks_match_mediapipe(comparisons):
    for c in _of(comparisons, "hands"):
        if c.distances.size:
            assert c.mean_px < HAND_MEAN_PX and c.max_px < HAND_MAX_PX, (c.case, c.max_px)
