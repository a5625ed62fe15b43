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


# -- the fingers' hinge prior (`fit/hand_prior.py`) ------------------------------------------


def test_hinge_rows_are_the_complement_of_the_flexion_axis(fitter):
    from avatar_core.track.fit.hand_prior import BASES, HINGES, hinge_rows

    kin = fitter.kinematics
    for side in ("left", "right"):
        rows = hinge_rows(kin.j_shape, kin.parents, side)
        assert len(rows) == len(HINGES) + len(BASES)
        j = kin.j_shape
        wrist = j[JOINT[f"{side}_wrist"]]
        normal = np.cross(j[JOINT[f"{side}_index1"]] - wrist, j[JOINT[f"{side}_pinky1"]] - wrist)
        for name in HINGES:
            k = JOINT[f"{side}_{name}"]
            dirs = rows[k]
            np.testing.assert_allclose(dirs @ dirs.T, np.eye(2), atol=1e-12)
            children = np.flatnonzero(kin.parents == k)  # end joints: the bone from the parent
            bone = j[children[0]] - j[k] if len(children) else j[k] - j[kin.parents[k]]
            bone /= np.linalg.norm(bone)
            axis = np.cross(bone, normal)
            axis /= np.linalg.norm(axis)
            np.testing.assert_allclose(dirs @ axis, 0.0, atol=1e-12)
            # A bend about the axis costs nothing; a twist of 0.3 rad shows as 0.3.
            assert np.abs(dirs @ (0.9 * axis)).max() < 1e-12
            assert np.isclose(np.linalg.norm(dirs @ (0.9 * axis + 0.3 * bone)), 0.3)
        for name in BASES:
            assert rows[JOINT[f"{side}_{name}"]].shape == (1, 3)


def test_hinge_rows_of_a_degenerate_hand_are_empty_not_nan(fitter):
    from avatar_core.track.fit.hand_prior import hinge_matrix, hinge_rows

    collapsed = np.ones_like(fitter.kinematics.j_shape)
    assert hinge_rows(collapsed, fitter.kinematics.parents, "right") == {}
    assert hinge_matrix({}, {}, 7).shape == (0, 7)


def test_library_gestures_bend_about_the_hinges(model_and_betas, fitter):
    """The synthetic rig's gestures (fist, claw, peace...) bend the finger joints about
    these axes to within ~6 deg: off-axis at most ~10% of the bend."""
    from avatar_core.motion.rig import model_rig
    from avatar_core.track.fit.hand_prior import hinge_rows

    model, _ = model_and_betas
    rig = model_rig(ensure_models(), model)
    rows = hinge_rows(fitter.kinematics.j_shape, fitter.kinematics.parents, "right")
    for name, pose in rig.gestures.items():
        p = neutral_params(model)
        p["right_hand_pose"] = pose - rig.hand_mean["right"]
        full = fitter.full_pose(fitter.pack(p))
        for k, dirs in rows.items():
            bend = np.linalg.norm(full[k])
            assert np.linalg.norm(dirs @ full[k]) <= 0.1 * bend + 0.01, (name, k)
    # The fitter's residual is the same map on the full pose (mean hand included), weighted.
    x = fitter.pack(neutral_params(model))
    residual = fitter.hinge_jacobian @ x + fitter.hinge_offset
    full = fitter.full_pose(x)
    left = hinge_rows(fitter.kinematics.j_shape, fitter.kinematics.parents, "left")
    want = np.concatenate([d @ full[k] for k, d in (*left.items(), *rows.items())])
    np.testing.assert_allclose(residual, np.sqrt(fitter.config.finger_hinge_weight) * want,
                               atol=1e-12)


def test_hinge_prior_keeps_noiseless_fingers(model_and_betas):
    """On the model's own landmarks a fist and a peace sign are recovered as well with the
    prior as without (the true poses satisfy it)."""
    from avatar_core.motion.rig import model_rig
    from avatar_core.track.fit.synthetic import synthetic_observations as observe

    model, betas = model_and_betas
    rig = model_rig(ensure_models(), model)
    truth = _posed(model, np.array([0.2, -0.3, 0.1]))
    truth["right_hand_pose"] = rig.gestures["peace"] - rig.hand_mean["right"]
    errors = {}
    for weight in (0.0, 10.0):
        fitter = FrameFitter(model, betas, FitConfig(finger_hinge_weight=weight))
        obs, _ = observe(fitter, truth, CAMERA, 0.5, np.random.default_rng(5))
        fit = fitter.fit(obs, CAMERA, start=truth)
        fit = fitter.fit(obs, CAMERA, start=fit.params)
        got = fitter.full_pose(fitter.pack(fit.params))
        want = fitter.full_pose(fitter.pack(truth))
        rows = list(range(40, 55))  # the right hand's joints
        errors[weight] = np.mean([rotation_angle_deg(Rotation.from_rotvec(got[k]).as_matrix(),
                                                     Rotation.from_rotvec(want[k]).as_matrix())
                                  for k in rows])
    assert errors[10.0] < errors[0.0] + 1.0 and errors[10.0] < 8.0, errors


def test_sequence_offers_only_palm_rotations_stable_across_frames(model_and_betas):
    """`SequenceFit` passes a palm rotation to the retry only when the same hand's previous
    frame (at most `palm_gap_s` before) agrees within `palm_stable_deg`: the first frame of a
    hand, a one-frame flip and a hand seen again after a gap are not offered."""
    from avatar_core.track.fit.sequence import SequenceFit, SequenceFitConfig

    model, betas = model_and_betas
    fit = SequenceFit(model, betas, SequenceFitConfig(palm_stable_deg=30.0, palm_gap_s=0.1))
    truth = _posed(model, np.array([0.2, -0.3, 0.1]))
    obs, _ = synthetic_observations(fit.fitter, truth, CAMERA)
    sl = cor.GROUP_SLICES["right_hand"]
    flipped, _ = synthetic_observations(fit.fitter, truth, CAMERA)
    flipped.depth[sl] = -flipped.depth[sl]  # the palm seen from the back
    fps = 30.0
    assert "right" not in fit._stable_palms(obs, CAMERA, 0.0)          # first sight
    assert "right" in fit._stable_palms(obs, CAMERA, 1 / fps)          # agrees
    assert "right" not in fit._stable_palms(flipped, CAMERA, 2 / fps)  # a one-frame flip
    assert "right" not in fit._stable_palms(obs, CAMERA, 3 / fps)      # back: not yet
    assert "right" in fit._stable_palms(obs, CAMERA, 4 / fps)
    assert "right" not in fit._stable_palms(obs, CAMERA, 1.0)          # after a gap
    off = SequenceFit(model, betas, SequenceFitConfig(fit=FitConfig(palm_retry_deg=180.0)))
    assert off._stable_palms(obs, CAMERA, 0.0) == {} and off._stable_palms(obs, CAMERA, 0.03) == {}
