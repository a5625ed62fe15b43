"""Fitting landmarks -> SMPL-X, on the body model's own keypoints with known parameters.

The landmarks are the synthetic model's keypoints for known parameters, projected into a
640x480 webcam (60 deg horizontal field of view) and written in MediaPipe's layouts, plus
Gaussian pixel noise; the fit must reproject onto them and recover the observable angles.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from avatar_core.body import lbs
from avatar_core.body.skeleton import JOINT
from avatar_core.gaussians.animate import synthetic_package
from avatar_core.metrics.temporal import keypoint_tje
from avatar_core.motion.rig import model_rig
from avatar_core.synth.model_writer import ensure_models
from avatar_core.track.fit import correspondence as cor
from avatar_core.track.fit.camera import WebcamCamera
from avatar_core.track.fit.fitter import FrameFitter, neutral_params
from avatar_core.track.fit.observations import empty_observations, from_landmarks
from avatar_core.track.fit.one_euro import OneEuroFilter
from avatar_core.track.fit.sequence import SequenceFit, SequenceFitConfig, drive_params
from avatar_core.track.fit.synthetic import project_params, synthetic_observations

CAMERA = WebcamCamera(640, 480, 60.0)
NOISE_PX = 1.0


@pytest.fixture(scope="module")
def setup():
    files = ensure_models()
    package, model = synthetic_package(files.root, 0)
    betas = np.asarray(package.body.betas)
    return model, betas, model_rig(files, model)


@pytest.fixture(scope="module")
def fitter(setup):
    model, betas, _ = setup
    return FrameFitter(model, betas)


def known_params(model, rig, phase: float = 0.0) -> dict[str, np.ndarray]:
    """A webcam-like frame: head turned, jaw open, an expression, arms up, gestures."""
    p = neutral_params(model)
    p["transl"] = np.array([0.02, -0.45, -1.1])
    p["global_orient"] = np.array([0.05, 0.1 + 0.1 * phase, 0.0])
    body = p["body_pose"]
    body[JOINT["neck"] - 1] = [0.1, 0.15 + 0.2 * phase, 0.0]
    body[JOINT["head"] - 1] = [0.05, 0.1, 0.05]
    body[JOINT["left_shoulder"] - 1] = [0.0, 0.2, -0.5 + 0.2 * phase]
    body[JOINT["left_elbow"] - 1] = [0.0, -1.2, 0.0]
    body[JOINT["right_shoulder"] - 1] = [0.0, -0.2, 0.6]
    body[JOINT["right_elbow"] - 1] = [0.0, 1.0 + 0.3 * phase, 0.0]
    p["jaw_pose"] = np.array([0.2 + 0.1 * phase, 0.0, 0.0])
    p["expression"][:3] = [0.8, 0.0, 0.5 * phase]
    p["right_hand_pose"] = rig.gestures["peace"] - rig.hand_mean["right"]
    p["left_hand_pose"] = (rig.gestures["fist"] - rig.hand_mean["right"]) * np.array([1, -1, -1])
    return p


def world_rotations(fitter: FrameFitter, params: dict) -> np.ndarray:
    """[55, 3, 3] world rotation of every joint."""
    p = {k: torch.as_tensor(np.asarray(v, dtype=np.float64))[None] for k, v in params.items()}
    p["betas"] = fitter.betas
    model = fitter.keypoints.model
    with torch.no_grad():
        pr = model._normalize(p, {k: s for k, s in model.param_spec().items()
                                  if k != "vertex_offsets"}, model.family)
        rot = lbs.rodrigues(model.full_pose(pr))
        return lbs.global_rotations(rot, model.parents)[0].numpy()


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = (np.trace(a.T @ b) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1))))


def akd(fitter, params, clean, group) -> float:
    proj = project_params(fitter, params, CAMERA)
    sl = cor.GROUP_SLICES[group]
    ok = np.isfinite(clean[sl]).all(1)
    return float(np.linalg.norm(proj[sl][ok] - clean[sl][ok], axis=1).mean())


def test_one_euro_filter_smooths_noise_and_follows_a_ramp():
    rng = np.random.default_rng(0)
    t = np.arange(200) / 30.0
    noisy = rng.normal(0, 1.0, 200)
    f = OneEuroFilter(min_cutoff=1.0, beta=0.0)
    out = np.array([f(np.array(x), ti) for x, ti in zip(noisy, t, strict=True)])
    assert out[20:].std() < 0.5 * noisy[20:].std()
    ramp = OneEuroFilter(min_cutoff=1.0, beta=1.0)
    followed = [ramp(np.array(10.0 * ti), ti) for ti in t]
    assert abs(followed[-1] - 10.0 * t[-1]) < 0.5  # fast motion: little lag
    assert f(np.array([5.0]), 0.0)[0] == 5.0  # time going back: a restart, passes through


def test_correspondence_tables_are_consistent(fitter):
    assert len(cor.FACE_MP_TO_IBUG68) == 68
    assert all(0 <= i < 468 for ids in cor.FACE_MP_TO_IBUG68 for i in ids)
    assert len(cor.HAND_MP_TO_SMPLX) == 21 and len(cor.POSE_MP_TO_SMPLX) == 33
    avail = fitter.keypoints.available.numpy()
    assert avail[cor.FACE_SLICE].all()  # 51 static + 17 contour landmarks
    assert avail[cor.LEFT_HAND_SLICE].all() and avail[cor.RIGHT_HAND_SLICE].all()
    assert avail[cor.POSE_SLICE].sum() == 19  # nose, eyes, ears, arms, hands, hips


def test_fit_recovers_known_parameters(setup, fitter):
    model, _, rig = setup
    gt = known_params(model, rig)
    obs, clean = synthetic_observations(fitter, gt, CAMERA, NOISE_PX, np.random.default_rng(1))
    fit = fitter.fit(obs, CAMERA)
    # Warm refinement, as the next frame of a still subject would get.
    fit = fitter.fit(obs, CAMERA, start=fit.params)
    errors = {g: akd(fitter, fit.params, clean, g) for g in cor.GROUP_SLICES}
    assert errors["face"] < 1.5 and errors["pose"] < 2.5, errors
    assert errors["left_hand"] < 3.0 and errors["right_hand"] < 3.0, errors
    gt_rot, fit_rot = world_rotations(fitter, gt), world_rotations(fitter, fit.params)
    head = angle_deg(gt_rot[JOINT["head"]], fit_rot[JOINT["head"]])
    assert head < 5.0, head
    jaw = abs(np.degrees(np.linalg.norm(fit.params["jaw_pose"]) - np.linalg.norm(gt["jaw_pose"])))
    assert jaw < 5.0, jaw
    # Elbow flexion toward the camera is the depth ambiguity of a single view: only the
    # forearm's foreshortening tells it, so the bound is loose.
    for elbow in ("left_elbow", "right_elbow"):
        flex = [np.degrees(np.linalg.norm(p["body_pose"][JOINT[elbow] - 1]))
                for p in (gt, fit.params)]
        assert abs(flex[0] - flex[1]) < 45.0, (elbow, flex)  # measured 39.7, 3.0
    assert np.linalg.norm(fit.params["transl"] - gt["transl"]) < 0.1


def test_smoothing_lowers_jitter_on_a_noisy_sequence(setup):
    model, betas, rig = setup
    n, fps = 12, 30.0
    gts = [known_params(model, rig, phase=i / n) for i in range(n)]
    tracks, clean = {}, None
    for smoothing in (False, True):
        sequence_fit = SequenceFit(model, betas, SequenceFitConfig(smoothing=smoothing))
        rng = np.random.default_rng(5)
        keypoints, truth = [], []
        for i, gt in enumerate(gts):
            obs, kp = synthetic_observations(sequence_fit.fitter, gt, CAMERA, 2.0, rng)
            out = sequence_fit.step(obs, i / fps)
            keypoints.append(project_params(sequence_fit.fitter, out.params, CAMERA))
            truth.append(kp)
        tracks[smoothing], clean = np.stack(keypoints), np.stack(truth)
    sl = slice(cor.FACE_SLICE.start, cor.POSE_SLICE.stop)
    vis = np.isfinite(clean[:, sl]).all(-1)
    tje = {s: keypoint_tje(np.nan_to_num(tracks[s][2:, sl]), np.nan_to_num(clean[2:, sl]),
                           vis[2:]) for s in tracks}
    assert tje[True] < tje[False], tje


def test_lost_track_holds_then_relaxes(setup):
    model, betas, rig = setup
    sequence_fit = SequenceFit(model, betas,
                               SequenceFitConfig(hold_s=0.5, relax_s=1.0, smoothing=False))
    gt = known_params(model, rig)
    obs, _ = synthetic_observations(sequence_fit.fitter, gt, CAMERA, 0.0)
    fitted = sequence_fit.step(obs, 0.0).params
    nothing = empty_observations((640, 480))
    held = sequence_fit.step(nothing, 0.3)
    assert held.fit is None and not any(held.seen.values())
    np.testing.assert_allclose(held.params["jaw_pose"], fitted["jaw_pose"])
    half = sequence_fit.step(nothing, 1.0).params  # 0.5 s into the relaxation: half way
    np.testing.assert_allclose(half["jaw_pose"], 0.5 * fitted["jaw_pose"], atol=1e-9)
    relaxed = sequence_fit.step(nothing, 2.0).params
    for name, value in sequence_fit.neutral.items():
        if name != "transl":
            np.testing.assert_allclose(relaxed[name], value, atol=1e-12, err_msg=name)


def test_degenerate_inputs_give_finite_params_or_no_detection(setup):
    model, betas, rig = setup
    sequence_fit = SequenceFit(model, betas)
    nan_face = np.full((468, 3), np.nan)
    obs = from_landmarks((640, 480), face=nan_face, left_hand=np.full((21, 3), np.nan))
    assert not any(obs.seen.values())
    out = sequence_fit.step(obs, 0.0)
    assert out.fit is None and all(np.isfinite(v).all() for v in out.params.values())
    # One hand only (cold start on a hand), then the face without hands.
    gt = known_params(model, rig)
    only_hand, _ = synthetic_observations(sequence_fit.fitter, gt, CAMERA, 1.0,
                                          drop=("face", "pose", "left_hand"))
    out = sequence_fit.step(only_hand, 0.1)
    assert out.seen == {"face": False, "left_hand": False, "right_hand": True, "pose": False}
    assert all(np.isfinite(v).all() for v in out.params.values())
    face_only, _ = synthetic_observations(sequence_fit.fitter, gt, CAMERA, 1.0,
                                          drop=("left_hand", "right_hand", "pose"))
    out = sequence_fit.step(face_only, 0.2)
    assert out.fit is not None and out.fit.reprojection_px["face"] < 3.0
    sent = drive_params(out.params)
    assert "transl" not in sent and sent["body_pose"].shape == (21, 3)


def test_hands_go_to_the_nearer_pose_wrist_not_their_label():
    from avatar_core.track.fit.observations import hand_sides
    from avatar_core.track.types import HandLandmarks, PoseLandmarks, TrackResult

    def hand(x, label, score=0.9):
        pts = np.zeros((21, 3), np.float32)
        pts[:, 0], pts[:, 1] = x, 200.0  # point 0 is the wrist
        return HandLandmarks(points=pts, handedness=label, score=score)

    pose_pts = np.zeros((33, 3), np.float32)
    pose_pts[15, :2], pose_pts[16, :2] = (400, 200), (100, 200)  # person's left on image right
    vis = np.ones(33, np.float32)
    pose = PoseLandmarks(points=pose_pts, visibility=vis, score=1.0)
    both_wrong = TrackResult(None, (hand(110, "left"), hand(390, "right")), pose, None,
                             image_size=(640, 480))
    sides = hand_sides(both_wrong)
    assert sides["left"][0, 0] == 390 and sides["right"][0, 0] == 110
    one = hand_sides(TrackResult(None, (hand(395, "right"),), pose, None))
    assert list(one) == ["left"]
    # Without the body's wrists the labels decide; of two "left" hands the better one is kept.
    unseen = PoseLandmarks(points=pose_pts, visibility=np.zeros(33, np.float32), score=1.0)
    labelled = hand_sides(TrackResult(None, (hand(110, "left", 0.6), hand(390, "left", 0.95)),
                                      unseen, None))
    assert list(labelled) == ["left"] and labelled["left"][0, 0] == 390
    assert hand_sides(TrackResult(None, (), pose, None)) == {}


def test_pipelined_tracking_keeps_every_frame_in_order_and_fits_like_serial(setup):
    """`tracked_frames` overlaps the landmarks of frame i + 1 with the fit of frame i; the
    output must equal the serial loop's, frame for frame."""
    from avatar_core.track.fit.observations import from_track_result
    from avatar_core.track.fit.synthetic import as_mediapipe
    from avatar_core.track.fit.video import tracked_frames
    from avatar_core.track.types import (
        FaceLandmarks,
        HandLandmarks,
        PoseLandmarks,
        RotatedRect,
        TrackResult,
    )

    model, betas, rig = setup
    fitter = FrameFitter(model, betas)
    rng = np.random.default_rng(11)

    class ScriptedTracker:  # "tracks" frame i as the model's keypoints for phase i / 8
        def track(self, frame):
            i = int(frame[0, 0, 0])
            px = project_params(fitter, known_params(model, rig, i / 8), CAMERA)
            mp = as_mediapipe(px + rng.normal(0, 1.0, px.shape))
            roi = RotatedRect(320, 240, 100, 100)
            pose = PoseLandmarks(mp["pose"], mp["pose_visibility"], 1.0)
            hands = (HandLandmarks(mp["left_hand"], "left", 1.0),
                     HandLandmarks(mp["right_hand"], "right", 1.0))
            return TrackResult(FaceLandmarks(np.nan_to_num(mp["face"]), 1.0, roi), hands,
                               pose, None, image_size=(640, 480))

    frames = [(np.full((4, 4, 3), i, np.uint8), i / 30) for i in range(6)]
    results = [ScriptedTracker().track(f) for f, _ in frames]  # fixed inputs for both runs
    replay = iter(results)

    class ReplayTracker:
        def track(self, frame):
            return next(replay)

    piped = list(tracked_frames(frames, SequenceFit(model, betas), ReplayTracker()))
    serial_fit = SequenceFit(model, betas)
    serial = [drive_params(serial_fit.step(from_track_result(r), t).params)
              for r, (_, t) in zip(results, frames, strict=True)]
    assert [f.t for f in piped] == [t for _, t in frames]
    for got, want in zip(piped, serial, strict=True):
        for name in want:
            np.testing.assert_allclose(got.params[name], want[name], atol=1e-12, err_msg=name)
    assert all(f.seen["face"] and f.fit_ms > 0 for f in piped)
    assert list(tracked_frames([], SequenceFit(model, betas), ReplayTracker())) == []


@pytest.mark.parametrize("case", ["far_off_frame", "collapsed", "half_inf", "tiny_face"])
def test_extreme_landmarks_give_finite_params(setup, case):
    """Landmarks far outside the frame, all on one pixel, half infinite, or a face a pixel
    wide: the fit returns finite parameters (or says the group is not seen), never NaN."""
    model, betas, _ = setup
    rng = np.random.default_rng(3)
    face = {"far_off_frame": rng.normal(0, 1e7, (468, 3)) + 1e9,
            "collapsed": np.full((468, 3), 320.0),
            "half_inf": np.where(np.arange(468)[:, None] % 2, np.inf, 300.0) * np.ones((468, 3)),
            "tiny_face": 320.0 + rng.normal(0, 0.01, (468, 3))}[case]
    sequence_fit = SequenceFit(model, betas)
    for i in range(2):  # a cold fit, then a warm one from it
        out = sequence_fit.step(from_landmarks((640, 480), face=face,
                                               left_hand=np.full((21, 3), -1e8)), i / 30)
        assert all(np.isfinite(v).all() for v in out.params.values()), case
