"""Hands the hand landmark model declines: the pose model's points of the hand (pinky, index,
thumb) turn the wrist, the fingers hold their last confident state and then relax
(`observations.POSE_HAND_POINTS`, `SequenceFit`'s wrist groups)."""

from __future__ import annotations

import numpy as np
import pytest

from avatar_core.body.skeleton import JOINT
from avatar_core.gaussians.animate import synthetic_package
from avatar_core.motion.rig import model_rig
from avatar_core.synth.model_writer import ensure_models
from avatar_core.track.fit import correspondence as cor
from avatar_core.track.fit.camera import WebcamCamera
from avatar_core.track.fit.fitter import neutral_params
from avatar_core.track.fit.observations import (
    POSE_HAND_POINTS,
    from_track_result,
    pose_hand_seen,
    without_pose_hands,
)
from avatar_core.track.fit.sequence import SequenceFit, SequenceFitConfig
from avatar_core.track.fit.synthetic import synthetic_observations
from avatar_core.track.types import HandLandmarks, PoseLandmarks, TrackResult

CAMERA = WebcamCamera(640, 480, 60.0)
LEFT_ROWS = [cor.POSE_SLICE.start + i for i in POSE_HAND_POINTS["left"]]
RIGHT_ROWS = [cor.POSE_SLICE.start + i for i in POSE_HAND_POINTS["right"]]


def _result(left_hand: bool, right_visible: int = 3) -> TrackResult:
    pts = np.zeros((33, 3), np.float32)
    pts[:, 0] = np.linspace(100, 500, 33)
    pts[:, 1] = 240.0
    pts[15, :2], pts[16, :2] = (450, 300), (150, 300)  # the person's left on the image right
    vis = np.ones(33, np.float32)
    vis[list(POSE_HAND_POINTS["right"])[right_visible:]] = 0.0
    hands = ()
    if left_hand:
        hand = np.zeros((21, 3), np.float32)
        hand[:, 0], hand[:, 1] = np.linspace(440, 470, 21), np.linspace(300, 360, 21)
        hands = (HandLandmarks(points=hand, handedness="left", score=0.9),)
    return TrackResult(None, hands, PoseLandmarks(points=pts, visibility=vis, score=1.0), None,
                       image_size=(640, 480))


def test_pose_hand_points_are_used_only_where_the_hand_is_not():
    default = from_track_result(_result(left_hand=False))  # off unless asked for
    assert (default.weights[LEFT_ROWS + RIGHT_ROWS] == 0).all()
    obs = from_track_result(_result(left_hand=False), pose_hands=True)
    assert (obs.weights[LEFT_ROWS] > 0).all() and (obs.weights[RIGHT_ROWS] > 0).all()
    assert pose_hand_seen(obs, "left") and pose_hand_seen(obs, "right")
    obs = from_track_result(_result(left_hand=True), pose_hands=True)
    assert obs.seen["left_hand"]
    assert (obs.weights[LEFT_ROWS] == 0).all() and not pose_hand_seen(obs, "left")
    assert (obs.weights[RIGHT_ROWS] > 0).all()
    # One point alone cannot turn a wrist: none of them is used.
    obs = from_track_result(_result(left_hand=False, right_visible=1), pose_hands=True)
    assert (obs.weights[RIGHT_ROWS] == 0).all() and not pose_hand_seen(obs, "right")
    # BlazePose's guess of a hand below the image is no observation of it.
    below = _result(left_hand=False)
    below.pose.points[list(POSE_HAND_POINTS["right"]), 1] = 500.0
    obs = from_track_result(below, pose_hands=True)
    assert (obs.weights[RIGHT_ROWS] == 0).all() and (obs.weights[LEFT_ROWS] > 0).all()
    off = without_pose_hands(from_track_result(_result(left_hand=False), pose_hands=True))
    assert (off.weights[LEFT_ROWS + RIGHT_ROWS] == 0).all()


@pytest.fixture(scope="module")
def setup():
    files = ensure_models()
    package, model = synthetic_package(files.root, 0)
    return model, np.asarray(package.body.betas), model_rig(files, model)


def _params(model, rig, wrist_aa) -> dict[str, np.ndarray]:
    p = neutral_params(model)
    p["transl"] = np.array([0.0, -0.35, -0.9])
    body = p["body_pose"]
    body[JOINT["left_shoulder"] - 1] = [0.0, 0.2, -0.6]
    body[JOINT["left_elbow"] - 1] = [0.0, -1.3, 0.0]
    body[JOINT["left_wrist"] - 1] = wrist_aa
    p["left_hand_pose"] = (rig.gestures["fist"] - rig.hand_mean["right"]) * np.array([1, -1, -1])
    return p


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    from scipy.spatial.transform import Rotation

    return float(np.degrees((Rotation.from_rotvec(a).inv() * Rotation.from_rotvec(b))
                            .magnitude()))


def test_a_declined_hand_turns_its_wrist_with_the_pose_and_relaxes_its_fingers(setup):
    model, betas, rig = setup
    cfg = SequenceFitConfig(hold_s=0.5, relax_s=1.0, smoothing=False, gaze=False)
    first = _params(model, rig, np.array([0.0, 0.0, 0.3]))
    turned = _params(model, rig, np.array([0.0, 0.0, -0.5]))  # the wrist bends the other way
    wrist = JOINT["left_wrist"] - 1
    out = {}
    for pose_hands in (True, False):
        fit = SequenceFit(model, betas, dataclasses_replace(cfg, pose_hands=pose_hands))
        obs, _ = synthetic_observations(fit.fitter, first, CAMERA)
        fingers = fit.step(obs, 0.0).params["left_hand_pose"].copy()
        held_wrist = fit.current["body_pose"][wrist].copy()
        declined, _ = synthetic_observations(fit.fitter, turned, CAMERA, drop=("left_hand",))
        assert pose_hand_seen(declined, "left")
        held = fit.step(declined, 0.2).params
        for t in np.arange(0.3, 2.0, 0.1):  # frames go on (a gap > hold_s restarts cold)
            fit.step(declined, float(t))
        relaxed = fit.step(declined, 2.0).params
        out[pose_hands] = (fingers, held_wrist, held, relaxed)
    fingers, held_wrist, held, relaxed = out[True]
    # The fingers keep their last confident state, then ease to the relaxed hand ...
    np.testing.assert_allclose(held["left_hand_pose"], fingers)
    np.testing.assert_allclose(relaxed["left_hand_pose"], np.zeros((15, 3)), atol=1e-12)
    # ... while the wrist follows the pose's hand points.
    for params in (held, relaxed):
        assert _angle_deg(params["body_pose"][wrist], turned["body_pose"][wrist]) < 15.0
    assert _angle_deg(held_wrist, turned["body_pose"][wrist]) > 30.0
    # Without them the wrist only holds and relaxes with the hand.
    _, held_wrist_off, held_off, relaxed_off = out[False]
    np.testing.assert_allclose(held_off["body_pose"][wrist], held_wrist_off)
    np.testing.assert_allclose(relaxed_off["body_pose"][wrist],
                               neutral_params(model)["body_pose"][wrist], atol=1e-12)


def dataclasses_replace(cfg, **kw):
    import dataclasses

    return dataclasses.replace(cfg, **kw)
