"""The palm's rotation from hand landmarks (`fit/palm.py`) and the fitter's retry from it."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from avatar_core.body.skeleton import JOINT
from avatar_core.gaussians.animate import synthetic_package
from avatar_core.synth.model_writer import ensure_models
from avatar_core.track.fit import correspondence as cor
from avatar_core.track.fit.camera import WebcamCamera
from avatar_core.track.fit.fitter import HAND_Z_SCALE, FitConfig, FrameFitter, neutral_params
from avatar_core.track.fit.observations import from_landmarks
from avatar_core.track.fit.palm import (
    kabsch,
    palm_points,
    palm_rotation,
    rotation_angle_deg,
)
from avatar_core.track.fit.synthetic import as_mediapipe, synthetic_observations

CAMERA = WebcamCamera(640, 480, 60.0)
CAM = (CAMERA.focal, CAMERA.center)


@pytest.fixture(scope="module")
def model_and_betas():
    files = ensure_models()
    package, model = synthetic_package(files.root, 0)
    return model, np.asarray(package.body.betas)


@pytest.fixture(scope="module")
def fitter(model_and_betas):
    return FrameFitter(*model_and_betas)


def test_kabsch_recovers_a_known_rotation_like_scipy():
    rng = np.random.default_rng(0)
    for _ in range(20):
        a = rng.normal(size=(6, 3))
        true = Rotation.random(random_state=rng).as_matrix()
        b = 3.7 * a @ true.T + rng.normal(size=3)  # scaled and moved: only the shape counts
        got = kabsch(a, b)
        np.testing.assert_allclose(got, true, atol=1e-9)
        # The twin: scipy's align_vectors on the centred points.
        twin, _ = Rotation.align_vectors(b - b.mean(0), a - a.mean(0))
        np.testing.assert_allclose(got, twin.as_matrix(), atol=1e-9)
    # Noisy points: still the least-squares rotation scipy finds.
    a = rng.normal(size=(5, 3))
    b = a @ Rotation.from_rotvec([0.3, -1.2, 2.0]).as_matrix().T + rng.normal(0, 0.05, (5, 3))
    twin, _ = Rotation.align_vectors(b - b.mean(0), a - a.mean(0))
    np.testing.assert_allclose(kabsch(a, b), twin.as_matrix(), atol=1e-9)


def test_kabsch_never_returns_a_mirror():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(5, 3))
    mirrored = a * np.array([1.0, 1.0, -1.0])
    r = kabsch(a, mirrored)
    assert r is not None and np.isclose(np.linalg.det(r), 1.0)
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)


@pytest.mark.parametrize("case", ["nan", "inf", "collinear", "coincident", "two_points",
                                  "wrong_shape"])
def test_kabsch_degenerate_points_give_none(case):
    rng = np.random.default_rng(2)
    a = rng.normal(size=(5, 3))
    b = a.copy()
    if case == "nan":
        b[2, 1] = np.nan
    elif case == "inf":
        a[0, 0] = np.inf
    elif case == "collinear":
        b = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    elif case == "coincident":
        b = np.ones((5, 3))
    elif case == "two_points":
        a, b = a[:2], b[:2]
    else:
        b = b[:, :2]
    assert kabsch(a, b) is None


def _wrist_world(fitter, params, side):
    return fitter.world_rotation(fitter.pack(params), JOINT[f"{side}_wrist"])


def _posed(model, wrist_aa, side="right"):
    p = neutral_params(model)
    p["transl"] = np.array([0.0, -0.45, -1.1])
    body = p["body_pose"]
    sign = 1.0 if side == "right" else -1.0
    body[JOINT[f"{side}_shoulder"] - 1] = [0.0, -0.2 * sign, 0.6 * sign]
    body[JOINT[f"{side}_elbow"] - 1] = [0.0, 1.6 * sign, 0.0]
    body[JOINT[f"{side}_wrist"] - 1] = wrist_aa
    p[f"{side}_hand_pose"] = np.tile([0.0, 0.0, 0.3 * sign], (15, 1))  # fingers bent
    return p


@pytest.mark.parametrize("wrist_aa", [[0.0, 0.0, 0.0], [0.6, -0.4, 0.2], [-0.3, 1.2, 0.5]])
def test_palm_rotation_of_noiseless_model_landmarks(model_and_betas, fitter, wrist_aa):
    """The model's own hand keypoints, projected, with the true relative depth written as
    flat as MediaPipe's (/ HAND_Z_SCALE): the palm's rotation is the wrist's world rotation,
    exactly: each point lifted through its pixel ray to its depth."""
    model, _ = model_and_betas
    for side in ("left", "right"):
        params = _posed(model, np.array(wrist_aa) * (1 if side == "right" else [1, -1, -1]),
                        side)
        obs, _ = synthetic_observations(fitter, params, CAMERA)
        sl = cor.GROUP_SLICES[f"{side}_hand"]
        hand = np.concatenate([obs.pixels[sl], obs.depth[sl, None]], axis=1)
        rest = fitter.palm_hands[0 if side == "left" else 1][4]
        got = palm_rotation(hand, rest, HAND_Z_SCALE, CAMERA.focal, CAMERA.center)
        assert rotation_angle_deg(got, _wrist_world(fitter, params, side)) < 1e-3, side


def test_palm_rotation_degenerate_hands_give_none(fitter):
    rest = fitter.palm_hands[1][4]
    assert palm_rotation(np.full((21, 3), np.nan), rest, HAND_Z_SCALE, *CAM) is None
    assert palm_rotation(np.full((21, 3), 320.0), rest, HAND_Z_SCALE, *CAM) is None  # one pixel
    line = np.stack([np.arange(21.0), 2 * np.arange(21.0), np.zeros(21)], 1)
    assert palm_rotation(line, rest, HAND_Z_SCALE, *CAM) is None
    assert palm_rotation(np.zeros((20, 3)), rest, HAND_Z_SCALE, *CAM) is None
    hand = np.random.default_rng(0).normal(300, 30, (21, 3))
    assert palm_rotation(hand, rest, HAND_Z_SCALE, 0.0, (320, 240)) is None
    assert palm_rotation(hand, rest, HAND_Z_SCALE, np.nan, (320, 240)) is None
    assert palm_points(np.arange(63.0).reshape(21, 3), 2.0, *CAM).shape == (5, 3)


def test_fit_from_a_flipped_wrist_comes_back_with_the_palm_retry(model_and_betas):
    """A warm start with the right palm turned 180 deg about the forearm (the flip the
    landmarks' 2D alone cannot rule out): with the retry the fit returns to the true wrist;
    without it the local steps stay on the wrong side."""
    model, betas = model_and_betas
    truth = _posed(model, np.array([0.2, -0.3, 0.1]))
    errors = {}
    for retry in (180.0, 60.0):
        fitter = FrameFitter(model, betas, FitConfig(palm_retry_deg=retry))
        obs, _ = synthetic_observations(fitter, truth, CAMERA, 0.5, np.random.default_rng(4))
        start = {k: np.array(v) for k, v in truth.items()}
        elbow = JOINT["right_elbow"] - 1
        start["body_pose"][elbow] = (Rotation.from_rotvec(start["body_pose"][elbow])
                                     * Rotation.from_rotvec([np.pi, 0.0, 0.0])).as_rotvec()
        fit = fitter.fit(obs, CAMERA, start=start)
        errors[retry] = rotation_angle_deg(_wrist_world(fitter, fit.params, "right"),
                                           _wrist_world(fitter, truth, "right"))
        assert all(np.isfinite(v).all() for v in fit.params.values())
    assert errors[60.0] < 15.0 and errors[180.0] > 60.0, errors


def test_fit_with_degenerate_hand_landmarks_stays_finite(model_and_betas):
    model, betas = model_and_betas
    fitter = FrameFitter(model, betas)
    truth = _posed(model, np.zeros(3))
    mp = as_mediapipe(np.nan_to_num(np.full((cor.NUM_KEYPOINTS, 2), 300.0)))
    for hand in (np.full((21, 3), 300.0),                                  # one pixel
                 np.stack([np.arange(21.0) * 5, np.arange(21.0) * 5, np.zeros(21)], 1)):
        obs = from_landmarks((640, 480), right_hand=hand, pose=mp["pose"],
                             pose_visibility=mp["pose_visibility"])
        fit = fitter.fit(obs, CAMERA, start=truth)
        assert all(np.isfinite(v).all() for v in fit.params.values())
