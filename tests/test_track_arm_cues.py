"""The arm's cues beyond 2D landmarks: the elbows' hinge prior (`fit/elbow_prior.py`) and
BlazePose's world bone directions (`fit/world_cues.direction_residuals`)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from avatar_core.body.skeleton import JOINT
from avatar_core.gaussians.animate import synthetic_package
from avatar_core.motion.library import _ARMS, mirrored
from avatar_core.synth.model_writer import ensure_models
from avatar_core.track.fit import correspondence as cor
from avatar_core.track.fit import elbow_prior, world_cues
from avatar_core.track.fit.camera import WebcamCamera
from avatar_core.track.fit.fitter import FitConfig, FrameFitter, _Problem, neutral_params
from avatar_core.track.fit.observations import empty_observations
from avatar_core.track.fit.synthetic import synthetic_observations
from tests.fit_jacobian import assert_objective_jacobian

CAMERA = WebcamCamera(640, 480, 60.0)
POSE = cor.POSE_SLICE.start


@pytest.fixture(scope="module")
def model_and_betas():
    package, model = synthetic_package(ensure_models().root, 0)
    return model, np.asarray(package.body.betas)


@pytest.fixture(scope="module")
def cued(model_and_betas):
    """A fitter with both cues on."""
    return FrameFitter(*model_and_betas, FitConfig(elbow_hinge_weight=10.0,
                                                   elbow_extension_deg=5.0,
                                                   world_direction_weight=10.0))


def _arm_pose(model, shoulder, elbow, side="right"):
    p = neutral_params(model)
    p["transl"] = np.array([0.0, -0.45, -1.1])
    p["body_pose"][JOINT[f"{side}_shoulder"] - 1] = shoulder
    p["body_pose"][JOINT[f"{side}_elbow"] - 1] = elbow
    return p


def test_elbow_axes_are_orthonormal_to_the_forearm(cued):
    axes = elbow_prior.elbow_axes(cued.kinematics.j_shape)
    assert set(axes) == {JOINT["left_elbow"], JOINT["right_elbow"]}
    j = cued.kinematics.j_shape
    for k, (axis, sideways) in axes.items():
        side = "left" if k == JOINT["left_elbow"] else "right"
        bone = j[JOINT[f"{side}_wrist"]] - j[k]
        bone /= np.linalg.norm(bone)
        np.testing.assert_allclose([np.linalg.norm(axis), np.linalg.norm(sideways)], 1.0)
        assert abs(axis @ bone) < 1e-9 and abs(sideways @ bone) < 1e-9
        assert abs(axis @ sideways) < 1e-9
        # Flexing about the axis moves the forearm toward the front (+z).
        assert np.cross(axis, bone)[2] > 0.9


def test_elbow_axes_of_a_degenerate_arm_are_empty_not_nan(cued):
    collapsed = np.ones_like(cued.kinematics.j_shape)
    assert elbow_prior.elbow_axes(collapsed) == {}
    forward = cued.kinematics.j_shape.copy()
    forward[JOINT["left_wrist"]] = forward[JOINT["left_elbow"]] + [0.0, 0.0, 0.25]
    assert set(elbow_prior.elbow_axes(forward)) == {JOINT["right_elbow"]}


def test_the_motion_librarys_elbows_keep_to_the_hinge(cued):
    """The key arm poses of the motion library (both sides) bend their elbows about the axis
    (within 3 deg), forward: the prior holds the truth of the studio takes."""
    axes = elbow_prior.elbow_axes(cued.kinematics.j_shape)
    right = {name: {"right_elbow": pose[2]} for name, pose in _ARMS.items()}
    for name, joints in right.items():
        for side_joints in (joints, mirrored(joints)):
            (joint, aa), = side_joints.items()
            axis, sideways = axes[JOINT[joint]]
            aa = np.asarray(aa)
            assert abs(sideways @ aa) < math.radians(3.0), (name, joint)
            assert axis @ aa > 0.0, (name, joint)


def test_the_elbow_rows_weigh_the_sideways_bend_and_stop_a_backward_bend(model_and_betas, cued):
    model, _ = model_and_betas
    axes = elbow_prior.elbow_axes(cued.kinematics.j_shape)
    axis, sideways = axes[JOINT["right_elbow"]]
    elbow = -0.5 * axis + 0.3 * sideways  # bent 29 deg backward and 17 deg sideways
    x = cued.pack(_arm_pose(model, [0.0, 0.0, 0.0], elbow))
    plain = FrameFitter(*model_and_betas, FitConfig())
    rows = cued.hinge_jacobian[len(plain.hinge_jacobian):]
    assert rows.shape[0] == 2
    np.testing.assert_allclose(sorted(np.abs(rows @ x)), [0.0, math.sqrt(10.0) * 0.3],
                               atol=1e-12)
    term = cued._hinge_term(x, jacobian=True)
    over = 0.5 - math.radians(5.0)
    assert term is not None and np.isclose(term.residuals, 10.0 * over).any()
    # Bent forward: no active row.
    x = cued.pack(_arm_pose(model, [0.0, 0.0, 0.0], 1.2 * axis))
    assert cued._hinge_term(x, jacobian=False) is None


def test_direction_pairs_need_both_landmarks_and_a_bone(model_and_betas, cued):
    obs = empty_observations((640, 480))
    weight = np.ones(cor.NUM_KEYPOINTS)
    assert world_cues.direction_pairs(obs, weight, 10.0) is None  # no world landmarks
    obs.world = np.zeros((33, 3))
    obs.world[13] = [0.0, 0.3, 0.0]  # left elbow below the left shoulder (y down)
    obs.world[15] = obs.world[13]  # a forearm of no length
    obs.world[16] = np.nan
    obs.world[12] = [np.inf, 0.0, 0.0]  # an infinite right shoulder
    pairs = world_cues.direction_pairs(obs, weight, 10.0)
    assert pairs is not None
    a, b, u, w = pairs
    # Only the left upper arm: the others have no length, a NaN or an infinity. An end of one
    # landmark is its row twice (an end's point is the mean of its rows).
    assert a.tolist() == [[POSE + 11] * 2] and b.tolist() == [[POSE + 13] * 2]
    np.testing.assert_allclose(u, [[0.0, -1.0, 0.0]])  # down, in the camera frame (y up)
    assert world_cues.direction_pairs(obs, weight, 0.0) is None
    weight[POSE + 13] = 0.0
    assert world_cues.direction_pairs(obs, weight, 10.0) is None


def test_objective_jacobian_with_the_arm_cues_matches_finite_differences(model_and_betas, cued):
    """Every residual, with the elbow rows (one backward bend active) and the world bone
    directions, against central differences."""
    model, _ = model_and_betas
    rng = np.random.default_rng(11)
    axes = elbow_prior.elbow_axes(cued.kinematics.j_shape)
    axis, sideways = axes[JOINT["left_elbow"]]
    p = _arm_pose(model, [0.2, -0.3, -0.5], -0.4 * axis + 0.2 * sideways, side="left")
    x = cued.pack(p) + rng.normal(0, 0.05, cued.pack(p).size)
    x[cued.layout["transl"][0]] = p["transl"]
    pixels = cued._data(x, CAMERA, False).pixels
    target = np.nan_to_num(pixels)
    sqrt_w = np.where(cued.kinematics.available, 1.0, 0.0)
    obs = empty_observations((640, 480))
    obs.world = rng.normal(0, 0.3, (33, 3))
    pairs = world_cues.direction_pairs(obs, sqrt_w ** 2, cued.config.world_direction_weight)
    assert pairs is not None and len(pairs[0]) == 4
    problem = _Problem(CAMERA, target, 6.4, None, direction_pairs=pairs)
    assert_objective_jacobian(cued, x, problem, sqrt_w)


def test_world_directions_turn_a_foreshortened_forearm_the_right_way(model_and_betas):
    """A forearm pointing toward the camera projects short, and without the hand's landmarks
    the 2D fit (3 px noise, cold start) turns it the wrong way; BlazePose's world directions
    of the truth bring it within a few degrees."""
    model, betas = model_and_betas
    truth = _arm_pose(model, [0.0, 0.6, 1.1], [0.0, 1.5, 0.0])
    rows = [11, 12, 13, 14, 15, 16]
    errors = {}
    for weight in (0.0, 10.0):
        fitter = FrameFitter(model, betas, FitConfig(world_direction_weight=weight))
        pts, _ = fitter._keypoints(fitter.pack(truth), False)
        true_fore = pts[POSE + 16] - pts[POSE + 14]
        for seed in (0, 1):
            obs, _ = synthetic_observations(fitter, truth, CAMERA, 3.0,
                                            np.random.default_rng(seed),
                                            drop=("left_hand", "right_hand"))
            obs.world = np.full((33, 3), np.nan)
            obs.world[rows] = (pts[POSE + np.array(rows)] - pts[POSE + 11]) \
                * world_cues.WORLD_TO_CAMERA
            got, _ = fitter._keypoints(fitter.pack(fitter.fit(obs, CAMERA).params), False)
            fore = got[POSE + 16] - got[POSE + 14]
            cos = fore @ true_fore / np.linalg.norm(fore) / np.linalg.norm(true_fore)
            errors[weight, seed] = math.degrees(math.acos(min(1.0, cos)))
    assert all(errors[10.0, s] < 10.0 for s in (0, 1)), errors
    assert all(errors[0.0, s] > 60.0 for s in (0, 1)), errors


def test_world_landmarks_are_smoothed_row_by_row_and_restart_when_rows_change(
        model_and_betas):
    from avatar_core.track.fit.sequence import SequenceFit, SequenceFitConfig

    model, betas = model_and_betas
    seq = SequenceFit(model, betas, SequenceFitConfig(world_min_cutoff=1.0))
    rng = np.random.default_rng(2)
    obs = empty_observations((640, 480))
    base = rng.normal(0, 0.3, (33, 3))
    base[25:] = np.nan  # rows BlazePose did not give
    raw, smooth = [], []
    for i in range(30):
        obs.world = base + rng.normal(0, 0.02, (33, 3))
        out = seq._smoothed_world(obs, i / 30)
        assert np.isnan(out.world[25:]).all() and np.isfinite(out.world[:25]).all()
        raw.append(obs.world[:25].copy())
        smooth.append(out.world[:25])
    assert np.std(np.diff(smooth, axis=0)) < 0.5 * np.std(np.diff(raw, axis=0))
    # A row lost: the filter restarts, so this frame passes as it is.
    obs.world = base + rng.normal(0, 0.02, (33, 3))
    obs.world[3] = np.nan
    out = seq._smoothed_world(obs, 1.0)
    np.testing.assert_array_equal(out.world, obs.world)
    # Off by default: the observations pass untouched.
    plain = SequenceFit(model, betas)
    assert plain._smoothed_world(obs, 1.1) is obs
    for bad in (-1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="world_min_cutoff"):
            SequenceFit(model, betas, SequenceFitConfig(world_min_cutoff=bad))


def test_the_body_may_have_its_own_temporal_weight(model_and_betas):
    fitter = FrameFitter(*model_and_betas, FitConfig(temporal_weight=0.5,
                                                     body_temporal_weight=10.0))
    arms = fitter._free_mask(("global_orient", "spine2", "neck", "left_shoulder",
                              "right_elbow", "left_wrist"))
    face = fitter._free_mask(("jaw_pose", "expression", "left_hand_pose"))
    assert np.allclose(fitter.temporal_sqrt[arms], math.sqrt(10.0))
    assert np.allclose(fitter.temporal_sqrt[face], math.sqrt(0.5))
    transl = fitter._free_mask(("transl",))
    assert np.allclose(fitter.temporal_sqrt[transl], math.sqrt(1000.0))


@pytest.mark.parametrize("field", ["body_temporal_weight", "elbow_hinge_weight",
                                   "world_direction_weight", "temporal_weight"])
@pytest.mark.parametrize("value", [-1.0, math.nan, math.inf])
def test_bad_cue_weights_are_refused(model_and_betas, field, value):
    with pytest.raises(ValueError, match=field):
        FrameFitter(*model_and_betas, FitConfig(**{field: value}))


def test_the_live_path_carries_the_arm_cues_and_the_plain_config_none():
    from avatar_core.track.fit.sequence import ARM_CUES, SequenceFitConfig, live_config

    live = live_config(fov_x_deg=50.0, smoothing=False)
    assert live.fov_x_deg == 50.0 and not live.smoothing
    assert all(getattr(live.fit, k) == v for k, v in ARM_CUES.items())
    plain = SequenceFitConfig().fit
    assert plain.world_direction_weight == 0 and plain.elbow_hinge_weight == 0
    assert plain.body_temporal_weight is None


def test_the_torso_axis_runs_from_the_hips_midpoint_to_the_shoulders(model_and_betas, cued):
    """Its ends are midpoints; the hips, left out of the 2D fit, still start it."""
    obs = empty_observations((640, 480))
    obs.world = np.full((33, 3), np.nan)
    obs.world[[23, 24]] = [[0.1, 0.0, 0.0], [-0.1, 0.0, 0.2]]   # hips, y down
    obs.world[[11, 12]] = [[0.2, -0.5, 0.0], [-0.2, -0.5, 0.2]]  # shoulders above them
    weight = np.ones(cor.NUM_KEYPOINTS)
    weight[[POSE + 23, POSE + 24]] = 0.0  # as observations.MISMATCHED_ROWS leaves them
    # below the frame (640 x 480) or within 2% of its edge, BlazePose's hips count for nothing
    obs.pixels[[POSE + 23, POSE + 24]] = [[300.0, 450.0], [340.0, 520.0]]
    assert world_cues.direction_pairs(obs, weight, 10.0, world_cues.TORSO_AXIS) is None
    obs.pixels[POSE + 24] = [340.0, 470.0]
    assert world_cues.direction_pairs(obs, weight, 10.0, world_cues.TORSO_AXIS) is None
    obs.pixels[POSE + 24] = [340.0, 460.0]  # 20 px inside, as the other
    a, b, u, _ = world_cues.direction_pairs(obs, weight, 10.0, world_cues.TORSO_AXIS)
    assert a.tolist() == [[POSE + 23, POSE + 24]] and b.tolist() == [[POSE + 11, POSE + 12]]
    np.testing.assert_allclose(u, [[0.0, 1.0, 0.0]])  # up, in the camera frame (y up)
    # The model's axis: the mean of the two rows at each end, with its Jacobian.
    points = np.zeros((cor.NUM_KEYPOINTS, 3))
    points[[POSE + 23, POSE + 24]] = [[0.1, 0.0, 0.0], [-0.1, 0.0, 0.0]]
    points[[POSE + 11, POSE + 12]] = [[0.2, 0.4, 0.3], [-0.2, 0.4, 0.3]]  # leaning 36.9 deg
    d_points = np.random.default_rng(0).normal(size=(cor.NUM_KEYPOINTS, 3, 4))
    pairs = (a, b, u, np.ones(1))
    r, jac = world_cues.direction_residuals(points, d_points, pairs, jacobian=True)
    np.testing.assert_allclose(r, [0.0, 0.8 - 1.0, 0.6], atol=1e-12)
    step = 1e-6 * np.arange(1, 5)
    r2, _ = world_cues.direction_residuals(points + d_points @ step, d_points, pairs, False)
    np.testing.assert_allclose(r2 - r, jac @ step, atol=1e-10)
    # Told not to ask, the hips count wherever they are: below the frame too.
    obs.pixels[POSE + 24] = [340.0, 520.0]
    assert world_cues.direction_pairs(obs, weight, 10.0, world_cues.TORSO_AXIS) is None
    a2, b2, u2, _ = world_cues.direction_pairs(obs, weight, 10.0, world_cues.TORSO_AXIS,
                                               world_only_in_view=False)
    assert a2.tolist() == a.tolist() and b2.tolist() == b.tolist()
    np.testing.assert_allclose(u2, u)
    # A landmark out of the 2D fit and not WORLD_ONLY keeps its bone out, even so.
    obs.world[13] = [0.3, -0.2, 0.0]
    weight[POSE + 13] = 0.0
    assert world_cues.direction_pairs(obs, weight, 10.0, ((11, 13),)) is None
    assert world_cues.direction_pairs(obs, weight, 10.0, ((11, 13),),
                                      world_only_in_view=False) is None
    # A hip that is not seen (no world point): no axis.
    obs.world[23] = np.nan
    assert world_cues.direction_pairs(obs, weight, 10.0, world_cues.TORSO_AXIS) is None


def test_the_torso_axis_weight_adds_its_bone_to_the_arm_bones(model_and_betas, cued):
    """`FitConfig.torso_axis_weight`: the axis joins the arm bones at its own weight."""
    obs = empty_observations((640, 480))
    obs.world = np.zeros((33, 3))
    obs.world[13] = [0.0, 0.3, 0.0]
    obs.world[[11, 12]] = [[0.2, -0.5, 0.0], [-0.2, -0.5, 0.0]]
    obs.pixels[[POSE + 23, POSE + 24]] = [[300.0, 400.0], [340.0, 400.0]]  # hips in view
    weight = np.ones(cor.NUM_KEYPOINTS)
    arms = world_cues.direction_pairs(obs, weight, 100.0, ((11, 13),))
    torso = world_cues.direction_pairs(obs, weight, 4.0, world_cues.TORSO_AXIS)
    a, b, u, w = world_cues.joined_pairs(arms, None, torso)
    assert a.tolist() == [[POSE + 11] * 2, [POSE + 23, POSE + 24]]
    assert b.tolist() == [[POSE + 13] * 2, [POSE + 11, POSE + 12]]
    np.testing.assert_allclose(w, [10.0, 2.0])  # each at the root of its own weight
    assert world_cues.joined_pairs(None, None) is None
    assert world_cues.joined_pairs(None, torso) is torso


@pytest.mark.parametrize("fields", [{"elbow_extension_deg": math.nan},
                                    {"elbow_extension_deg": -5.0},
                                    {"world_direction_bones": ((11, 33),)},
                                    {"world_direction_bones": ((11, 11),)},
                                    {"world_direction_bones": ((11, 13, 15),)},
                                    {"world_direction_bones": (((23, 24, 11), 12),)},
                                    {"world_direction_bones": (((11, 12), (12, 11)),)},
                                    {"world_direction_bones": (((23, 23), 11),)},
                                    {"world_direction_bones": (("hip", 11),)},
                                    {"torso_axis_weight": -1.0},
                                    {"torso_axis_weight": math.inf}])
def test_bad_arm_cue_settings_are_refused(model_and_betas, fields):
    with pytest.raises(ValueError, match=next(iter(fields))):
        FrameFitter(*model_and_betas, FitConfig(**fields))


def test_the_shoulders_line_turn_is_multiplied_and_bounded():
    """`turned_line`: the turn about the vertical times the gain, the rise and horizontal
    length kept, at most MAX_LINE_TURN_DEG; `direction_pairs` turns the shoulders' line
    only."""
    turn = math.radians(10.0)
    line = np.array([0.3 * math.cos(turn), 0.02, 0.3 * math.sin(turn)])
    got = world_cues.turned_line(line, 2.0)
    assert math.degrees(math.atan2(got[2], got[0])) == pytest.approx(20.0)
    assert got[1] == line[1] and np.hypot(got[0], got[2]) == pytest.approx(0.3)
    np.testing.assert_allclose(world_cues.turned_line(line, 1.0), line, atol=1e-15)
    far = world_cues.turned_line(np.array([0.0, 0.0, 0.3]), 2.0)  # 90 deg, doubled: bounded
    assert math.degrees(math.atan2(far[2], far[0])) == pytest.approx(
        world_cues.MAX_LINE_TURN_DEG)
    obs = empty_observations((640, 480))
    weight = np.ones(cor.NUM_KEYPOINTS)
    obs.world = np.zeros((33, 3))
    obs.world[11] = line * world_cues.WORLD_TO_CAMERA  # the right shoulder at 0
    obs.world[13] = [0.2, 0.3, 0.05]
    bones = (*world_cues.ARM_BONES[:1], *world_cues.SHOULDER_LINE)
    plain = world_cues.direction_pairs(obs, weight, 10.0, bones)
    doubled = world_cues.direction_pairs(obs, weight, 10.0, bones, line_yaw_gain=2.0)
    np.testing.assert_allclose(doubled[2][0], plain[2][0])  # the upper arm as given
    np.testing.assert_allclose(doubled[2][1], got / np.linalg.norm(got))


@pytest.mark.parametrize("gain", [0.0, -1.0, math.nan, math.inf])
def test_a_bad_shoulder_line_gain_is_refused(model_and_betas, gain):
    with pytest.raises(ValueError, match="shoulder_line_yaw_gain"):
        FrameFitter(*model_and_betas, FitConfig(shoulder_line_yaw_gain=gain))
