"""Eye rotations from iris centres (avatar_core.track.fit.gaze), on the synthetic model with
known eye rotations: the true iris centres come from the full model's forward pass, projected
into the 640x480 webcam, with pixel noise."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from avatar_core.body.models import SMPLXModel
from avatar_core.body.skeleton import JOINT
from avatar_core.gaussians.animate import synthetic_package
from avatar_core.synth.model_writer import ensure_models
from avatar_core.track.fit import gaze
from avatar_core.track.fit.camera import WebcamCamera
from avatar_core.track.fit.fitter import neutral_params

CAMERA = WebcamCamera(640, 480, 60.0)


@pytest.fixture(scope="module")
def setup():
    files = ensure_models()
    package, model = synthetic_package(files.root, 0)
    return model, np.asarray(package.body.betas)


@pytest.fixture(scope="module")
def body(setup):
    """A webcam subject 1.1 m away, head turned and tilted a little."""
    model, _ = setup
    p = neutral_params(model)
    p["transl"] = np.array([0.02, -0.45, -1.1])
    p["global_orient"] = np.array([0.05, 0.1, 0.0])
    p["body_pose"][JOINT["neck"] - 1] = [0.1, 0.15, 0.0]
    p["body_pose"][JOINT["head"] - 1] = [0.05, 0.1, 0.05]
    return p


def look(pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """Eye axis-angle: +yaw turns the gaze to the person's left (+x), +pitch down (-y)."""
    return np.radians([pitch_deg, yaw_deg, 0.0])


def true_iris_px(setup, params: dict, reye: np.ndarray, leye: np.ndarray) -> np.ndarray:
    """[2, 2] px of the model's iris centres (person's right eye, left eye) with the given eye
    rotations, from the full model (not the solver's cut-down copy)."""
    model, betas = setup
    p = {k: torch.as_tensor(np.asarray(v, dtype=np.float64))[None] for k, v in params.items()}
    p.update(betas=torch.as_tensor(betas)[None], reye_pose=torch.as_tensor(reye)[None],
             leye_pose=torch.as_tensor(leye)[None])
    full = SMPLXModel(model.data, dtype=torch.float64, hand_pca=model.hand_pca,
                      flat_hand_mean=model.flat_hand_mean)
    with torch.no_grad():
        out = full(p)
    front = gaze.pupil_vertices(model)
    centres = []
    for eye in gaze.EYES:
        joint = out.joints[0, gaze.EYE_JOINT[eye]]
        centres.append(joint + gaze.IRIS_DEPTH * (out.vertices[0, front[eye]] - joint))
    return CAMERA.project(torch.stack(centres)).numpy()


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees((Rotation.from_rotvec(a).inv() * Rotation.from_rotvec(b))
                            .magnitude()))


def test_pupils_are_the_eyeballs_front_poles(setup):
    model, _ = setup
    front = gaze.pupil_vertices(model)
    data = model.data
    for eye, x_sign in (("right", -1), ("left", 1)):
        v, j = data.v_template[front[eye]], data.joint_template[gaze.EYE_JOINT[eye]]
        assert np.sign(v[0]) == x_sign  # the person's left eye is at +x
        assert data.weights[front[eye], gaze.EYE_JOINT[eye]] == pytest.approx(1.0)
        # In front of the eye's centre, one eyeball radius (~12 mm) away.
        assert v[2] - j[2] == pytest.approx(np.linalg.norm(v - j))
        assert 0.008 < np.linalg.norm(v - j) < 0.016


def test_signs_person_left_is_image_right_and_up_is_image_up(setup, body):
    rest = true_iris_px(setup, body, look(0, 0), look(0, 0))
    left = true_iris_px(setup, body, look(0, 15), look(0, 15))
    up = true_iris_px(setup, body, look(-10, 0), look(-10, 0))
    assert rest[0, 0] < rest[1, 0]  # the person's right eye is on the image's left
    assert (left[:, 0] > rest[:, 0] + 1).all()
    assert (up[:, 1] < rest[:, 1] - 1).all()


@pytest.mark.parametrize("shared", [True, False])
def test_noise_free_rotations_are_recovered_exactly(setup, body, shared):
    model, betas = setup
    truth = look(-10, 15)  # 15 deg to the person's left, 10 deg up
    px = true_iris_px(setup, body, truth, truth)
    fit = gaze.gaze_solver(model).fit(body, px, CAMERA, betas, shared=shared)
    assert fit.reason is None and fit.used == (True, True) and fit.residual_px < 1e-3
    for name in ("leye_pose", "reye_pose"):
        assert angle_deg(fit.params[name], truth) < 0.01
        assert fit.params[name][2] == 0.0  # no roll
    assert gaze.fit_gaze(model, body, px, CAMERA, betas, shared=shared)["leye_pose"] == \
        pytest.approx(fit.params["leye_pose"])


def test_each_eye_gets_its_own_rotation_when_not_shared(setup, body):
    """Converging eyes (each turned 6 deg inward): row 0 drives reye_pose, row 1 leye_pose."""
    model, betas = setup
    reye, leye = look(0, 6), look(0, -6)  # the right eye (at -x) turns toward +x
    px = true_iris_px(setup, body, reye, leye)
    fit = gaze.gaze_solver(model).fit(body, px, CAMERA, betas, shared=False)
    assert angle_deg(fit.params["reye_pose"], reye) < 0.01
    assert angle_deg(fit.params["leye_pose"], leye) < 0.01
    # Shared, the two cancel out: a straight gaze (vergence is not modelled).
    both = gaze.gaze_solver(model).fit(body, px, CAMERA, betas, shared=True)
    assert angle_deg(both.params["reye_pose"], look(0, 0)) < 1.0


@pytest.mark.parametrize("pitch, yaw", [(-10, 15), (0, 0), (5, -20)])
def test_rotations_recovered_under_half_a_pixel_of_noise(setup, body, pitch, yaw):
    """0.5 px on an eye whose iris centre swings ~5 px per radian here (a 12 mm eyeball 1.1 m
    from a 640 px, 60 deg camera): measured mean errors 4.2-4.8 deg shared, 5.5-6.7 per eye."""
    model, betas = setup
    truth = look(pitch, yaw)
    px = true_iris_px(setup, body, truth, truth)
    solver = gaze.gaze_solver(model)
    rng = np.random.default_rng(7)
    errors = {True: [], False: []}
    for _ in range(40):
        noisy = px + rng.normal(0, 0.5, px.shape)
        for shared in (True, False):
            fit = solver.fit(body, noisy, CAMERA, betas, shared=shared)
            errors[shared] += [angle_deg(fit.params[n], truth) for n in ("leye_pose", "reye_pose")]
    shared, per_eye = np.mean(errors[True]), np.mean(errors[False])
    assert shared < 6.5 and per_eye < 8.5, (shared, per_eye)
    assert shared < per_eye  # one gaze for two eyes averages the noise


def test_rotation_beyond_the_limit_is_clamped(setup, body):
    model, betas = setup
    truth = look(0, 40)
    px = true_iris_px(setup, body, truth, truth)
    fit = gaze.gaze_solver(model).fit(body, px, CAMERA, betas)
    for name in ("leye_pose", "reye_pose"):
        rot = fit.params[name]
        assert np.degrees(np.linalg.norm(rot)) == pytest.approx(gaze.EYE_LIMIT_DEG, abs=0.01)
        assert rot[1] > 0 and abs(rot[0]) < 0.01  # still looking to the person's left
    assert fit.residual_px > 0.5  # the clamped eye cannot reach the iris


def test_missing_or_unusable_irises_leave_the_eyes_unchanged(setup, body):
    model, betas = setup
    solver = gaze.gaze_solver(model)
    before = dict(body, leye_pose=np.array([0.1, 0.2, 0.0]), reye_pose=np.array([0.1, 0.2, 0.0]))
    truth = look(5, -10)
    px = true_iris_px(setup, body, truth, truth)
    off_frame = np.array([[-20.0, 100.0], [700.0, 100.0]])
    behind = dict(before, transl=np.array([0.0, -0.45, 1.0]))  # the subject behind the camera
    turned_away = dict(before, global_orient=np.array([0.0, math.pi, 0.0]))
    for params, iris, why in ((before, np.full((2, 2), np.nan), "no iris"),
                              (before, off_frame, "no usable iris"),
                              (behind, px, "no usable iris"),
                              (turned_away, px, "no usable iris")):
        fit = solver.fit(params, iris, CAMERA, betas)
        assert fit.reason is not None and fit.reason.startswith(why), fit.reason
        assert fit.used == (False, False)
        for name in ("leye_pose", "reye_pose"):
            np.testing.assert_array_equal(fit.params[name], before[name])
    # Defaults: no eye rotation in the params -> zeros.
    fit = solver.fit(body, np.full((2, 2), np.nan), CAMERA, betas)
    np.testing.assert_array_equal(fit.params["reye_pose"], np.zeros(3))


def test_one_seen_eye_drives_both_when_shared(setup, body):
    model, betas = setup
    truth = look(-5, 12)
    px = true_iris_px(setup, body, truth, truth)
    px[1] = np.nan  # the person's left eye not seen
    solver = gaze.gaze_solver(model)
    fit = solver.fit(body, px, CAMERA, betas, shared=True)
    assert fit.used == (True, False)
    assert angle_deg(fit.params["leye_pose"], truth) < 0.01
    apart = solver.fit(body, px, CAMERA, betas, shared=False)
    assert angle_deg(apart.params["reye_pose"], truth) < 0.01
    np.testing.assert_array_equal(apart.params["leye_pose"], np.zeros(3))  # unchanged


def test_a_model_without_eyeballs_gets_no_gaze(setup, body):
    model, betas = setup
    weights = model.data.weights.copy()
    for eye in gaze.EYES:  # the eyeballs skinned to the head instead
        weights[:, JOINT["head"]] += weights[:, gaze.EYE_JOINT[eye]]
        weights[:, gaze.EYE_JOINT[eye]] = 0.0
    eyeless = SMPLXModel(dataclasses.replace(model.data, weights=weights))
    assert "no eyeball" in gaze.pupil_vertices(eyeless)
    px = true_iris_px(setup, body, look(0, 10), look(0, 10))
    fit = gaze.gaze_solver(eyeless).fit(body, px, CAMERA, betas)
    assert fit.reason is not None and "no eyeball" in fit.reason
    assert gaze.fit_gaze(eyeless, body, px, CAMERA, betas)["leye_pose"] == pytest.approx(0.0)


def test_sequence_fit_turns_the_eyes_onto_the_tracked_irises(setup, body):
    """The stream wiring: `Observations.iris` (from `Tracker(iris=True)`) drives leye / reye
    after the body fit; without irises the eyes stay at rest."""
    from avatar_core.track.fit.sequence import SequenceFit, SequenceFitConfig
    from avatar_core.track.fit.synthetic import synthetic_observations

    model, betas = setup
    sequence_fit = SequenceFit(model, betas, SequenceFitConfig(smoothing=False))
    eyes = look(8.0, 15.0)
    obs, _ = synthetic_observations(sequence_fit.fitter, body, CAMERA, 0.3,
                                    np.random.default_rng(2), drop=("left_hand", "right_hand"))
    plain = sequence_fit.step(obs, 0.0)
    np.testing.assert_array_equal(plain.params["leye_pose"], 0.0)
    obs.iris = true_iris_px(setup, body, eyes, eyes)
    out = sequence_fit.step(obs, 1 / 30)
    for name in ("leye_pose", "reye_pose"):
        err = math.degrees(np.linalg.norm(out.params[name] - eyes))
        assert err < 4.0, (name, out.params[name], eyes)
    assert out.fit.stats["gaze_px"] < 1.0
