"""Recovery of known parameters from synthetic renders, within stated tolerances.

The capture studio's textured actor (identity 0) is posed by library motions with known SMPL-X
parameters and rendered by a 640x480 webcam (60 deg horizontal field of view, the fitter's
camera) over a noisy background; the real `Tracker` (ONNX landmark models) and a `SequenceFit`
run over a few consecutive frames (tracking mode). `bench/track_eval.py` is the full version
and docs/tracking.md ("Synthetic renders with known parameters") has its numbers; the bounds
here are those measurements with margin. Renders, landmarks and fits are deterministic (one
thread everywhere), so a failure is a change in behaviour, not noise.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("onnxruntime")

from avatar_core.synth import tracking_eval as te  # noqa: E402
from avatar_core.track.models import ModelFetchError, fetch_models  # noqa: E402

FPS = 30.0
FRAMES = 4
# Bounds: a fresh measurement of these exact frames (after the #, issue 19) plus the stated
# margin. MediaPipe's face oval, ears and hips are left out of the fit
# (fit.observations.MISMATCHED_ROWS: they sit 10-26 px from the model keypoints they map to);
# with them the head was ~16 deg off and the torso AKD 21 px.
AKD_FACE_PX = 3.5     # mouth_open 2.29, peace 2.45 (51 static landmarks); + 1 px
HEAD_DEG = 12.0       # 5.42, 4.98; + 6.5 deg
JAW_DEG = 13.0        # 9.01; + 4 deg (true opening 20 deg)
AKD_TORSO_PX = 20.0   # mouth_open 9.99; x 2
AKD_HAND_PX = 16.0    # peace, right hand: 10.26; + 5.7 px
# The wrist's roll is poorly determined from one view. This bound was 45, the failing value
# of an earlier fit; now 15.6 measured + 10 deg.
WRIST_DEG = 26.0


@pytest.fixture(scope="module")
def scene():
    try:
        fetch_models()
    except ModelFetchError as exc:
        pytest.skip(f"cannot fetch the MediaPipe landmark models: {exc}")
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # deterministic reductions, and fair on a shared machine
    scene = te.make_scene("noise")
    tracker, sequence_fit = te.make_tracker_and_fit(scene)
    yield scene, tracker, sequence_fit
    tracker.close()
    torch.set_num_threads(threads)


def test_face_parameters_from_renders_of_an_open_mouth(scene):
    sc, tracker, sequence_fit = scene
    # mouth_open holds its pose (jaw 20 deg, lips parted) from 0.5 s to 1.5 s.
    r = te.run_clip(sc, "mouth_open", tracker, sequence_fit, FPS, FRAMES, start=0.6)
    m = r.metrics
    assert r.seen["face"].all() and r.seen["pose"].all(), r.seen
    assert m["akd_face"] < AKD_FACE_PX, m
    assert m["head_deg"] < HEAD_DEG, m
    assert m["jaw_deg"] < JAW_DEG, m
    assert m["akd_torso"] < AKD_TORSO_PX, m


def test_hand_parameters_from_renders_of_a_peace_sign(scene):
    sc, tracker, sequence_fit = scene
    # peace holds the raised right hand beside the chin from 0.7 s to 2.0 s.
    r = te.run_clip(sc, "peace", tracker, sequence_fit, FPS, FRAMES, start=1.0)
    m = r.metrics
    assert r.seen["face"].all(), r.seen
    assert m["akd_face"] < AKD_FACE_PX and m["head_deg"] < HEAD_DEG, m
    assert r.seen["right_hand"].all(), r.seen
    assert m["akd_right_hand"] < AKD_HAND_PX, m
    assert m["wrist_deg"] < WRIST_DEG, m
    assert np.isfinite(m["finger_deg"]), m
