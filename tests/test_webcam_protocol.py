"""The studio webcam protocol (`synth/tracking_eval/protocol.py`), small: its pieces on known
inputs, and a few frames of one identity in one framing through the real tracker and fit
(the full run is `telesplat synth webcam-eval`, docs/results.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from avatar_core.motion.library import motion_sequence
from avatar_core.synth.tracking_eval import protocol as wp
from avatar_core.synth.tracking_eval.metrics import Posed
from avatar_core.synth.tracking_eval.protocol_report import protocol_markdown, run_protocol


def test_the_take_is_long_enough_and_moves_the_arms():
    take = motion_sequence(list(wp.TAKE))
    assert take.duration >= wp.MIN_TAKE_S
    assert {"wave", "clapping", "pointing", "hands_to_face", "reach_out"} <= set(wp.TAKE)


@pytest.fixture(scope="module")
def actor():
    from avatar_core.synth.actor import Actor
    from avatar_core.synth.model_writer import ensure_models

    return Actor.load(ensure_models(), 0)


def test_framings_fill_the_webcam_from_the_head_down(actor):
    from avatar_core.synth.tracking_eval.metrics import evaluate_params

    cam = wp.webcam_camera()
    near = wp.framed_transl(actor, cam, "head_shoulders")
    far = wp.framed_transl(actor, cam, "waist_up")
    farther = wp.framed_transl(actor, cam, "hips_in_view")
    assert -near[2] < -far[2] < -farther[2]  # head-and-shoulders is closest
    assert "hips_in_view" not in wp.DEFAULT_FRAMINGS  # measured on request only
    rest = {"betas": np.asarray(actor.betas)}
    for transl in (near, far, farther):
        posed = evaluate_params(actor, [{**rest, "transl": transl}], cam)
        assert posed.visible["face"].all()  # the whole face in the image

    with pytest.raises(ValueError, match="unknown framing"):
        wp.framed_transl(actor, cam, "full_body")


def test_the_score_camera_looks_at_the_chest_from_the_side(actor):
    cam = wp.webcam_camera()
    transl = wp.framed_transl(actor, cam, "waist_up")
    score = wp.score_camera(transl, actor, 160, 120)
    axis = score.R[2]  # optical axis in the world
    angle = math.degrees(math.acos(float(np.clip(axis @ np.array([0, 0, -1.0]), -1, 1))))
    assert abs(angle - wp.SCORE_ANGLE_DEG) < 1.0


def _obs(value: float):
    from avatar_core.track.fit import correspondence as cor
    from avatar_core.track.fit.observations import Observations

    k = cor.NUM_KEYPOINTS
    return Observations(np.full((k, 2), value), np.full(k, 1.0), (640, 480),
                        {g: True for g in cor.GROUP_SLICES}, np.full(k, value))


def test_each_drive_fits_with_its_own_inputs():
    from avatar_core.synth.tracking_eval import protocol_drives as pd
    from avatar_core.track.fit.sequence import SequenceFitConfig

    base = SequenceFitConfig()
    assert pd.drive_config("live", base) == base
    embedded = pd.drive_config("embedding", base).fit
    assert embedded.embedding is not None
    assert embedded.image_z_weight == pd.EMBEDDING_IMAGE_Z_WEIGHT > 0
    depth = pd.drive_config("true_all_arm_depth", base).fit
    assert depth.world_weight == pd.TRUE_DEPTH_WEIGHT and depth.embedding is None
    assert pd.drive_config("live_pose_hands", base).pose_hands and not base.pose_hands
    from avatar_core.track.fit.sequence import ARM_CUES

    cued = pd.drive_config("arm_cues", base).fit
    assert all(getattr(cued, k) == v for k, v in ARM_CUES.items()) and cued.embedding is None
    assert base.fit.world_direction_weight == 0 and base.fit.elbow_hinge_weight == 0
    both = pd.drive_config("embedding_arm_cues", base).fit
    assert both.embedding is not None and both.world_direction_weight > 0
    points = np.arange(33 * 3, dtype=float).reshape(33, 3)
    world = pd.true_world(points, ("torso",))  # shoulders' line, nose against each shoulder
    assert set(np.flatnonzero(np.isfinite(world[:, 2]))) == {0, 11, 12}
    np.testing.assert_array_equal(world[[0, 11, 12], 2], -points[[0, 11, 12], 2])
    assert np.isfinite(pd.true_world(points, ("arms",))[:, 2]).sum() == 6
    with pytest.raises(ValueError, match="drives must be among"):
        pd.check_drives(["live", "nope"])


def test_mixing_takes_only_the_named_parts_from_the_truth():
    from avatar_core.track.fit import correspondence as cor

    live, truth = _obs(1.0), _obs(2.0)
    truth.weights[cor.GROUP_SLICES["left_hand"]] = 0.0  # the true hand is out of the image
    mixed = wp.mix_observations(live, truth, ("pose", "left_hand"))
    assert (mixed.pixels[cor.POSE_SLICE] == 2.0).all()
    assert (mixed.pixels[cor.FACE_SLICE] == 1.0).all()
    assert (mixed.pixels[cor.RIGHT_HAND_SLICE] == 1.0).all()
    assert not mixed.seen["left_hand"] and (mixed.weights[cor.LEFT_HAND_SLICE] == 0).all()
    assert mixed.seen["pose"] and mixed.seen["face"]
    assert (live.pixels == 1.0).all() and live.seen["left_hand"]  # untouched


def _posed(uv: np.ndarray) -> Posed:
    t = len(uv)
    groups = {"face": uv, "left_hand": uv[:, :0], "right_hand": uv[:, :0], "torso": uv[:, :0]}
    return Posed(groups, {g: np.ones(v.shape[:2], bool) for g, v in groups.items()},
                 np.zeros((t, 55, 3, 3)), np.zeros((t, 55, 3)), np.zeros((t, 51, 3)))


def test_lag_finds_a_known_delay_and_jitter_ignores_true_motion():
    fps, delay = 30.0, 3
    t = np.arange(90) / fps
    uv = np.stack([100 + 40 * np.sin(2 * np.pi * 0.7 * t), 50 + 20 * np.cos(2 * np.pi * 1.3 * t)],
                  -1)[:, None, :].repeat(4, 1)
    delayed = np.concatenate([uv[:1].repeat(delay, 0), uv[:-delay]])
    assert wp.lag_ms(_posed(delayed), _posed(uv), fps) == pytest.approx(1e3 * delay / fps,
                                                                         abs=6)
    assert wp.jitter_px(_posed(uv), _posed(uv)) == pytest.approx(0.0, abs=1e-9)
    noisy = uv + np.random.default_rng(0).normal(0, 2.0, uv.shape)
    assert wp.jitter_px(_posed(noisy), _posed(uv)) > 1.5


def test_joint_errors_are_geodesic_degrees():
    truth = [{"global_orient": np.zeros(3), "body_pose": np.zeros((21, 3))}]
    turned = {"global_orient": np.array([0.0, math.radians(10), 0.0]),
              "body_pose": np.zeros((21, 3))}
    turned["body_pose"][wp.JOINT["left_elbow"] - 1] = [0.0, 0.0, math.radians(20)]
    turned["body_pose"][wp.JOINT["neck"] - 1] = [math.radians(5), 0.0, 0.0]
    turned["body_pose"][wp.JOINT["head"] - 1] = [math.radians(-5), 0.0, 0.0]
    err = wp.joint_errors([turned], truth)
    assert err["root"] == pytest.approx(10.0, abs=1e-6)
    assert err["elbows"] == pytest.approx(10.0, abs=1e-6)  # mean of 20 and 0
    assert err["shoulders"] == pytest.approx(0.0, abs=1e-6)
    assert err["neck_head"] == pytest.approx(0.0, abs=1e-6)  # they cancel: the head is right


def test_bad_arguments_are_refused(tmp_path, capsys):
    with pytest.raises(ValueError, match="unknown framing"):
        run_protocol((0,), ("full_body",), 10.0, max_frames=2)
    with pytest.raises(ValueError, match="fps"):
        run_protocol((0,), ("waist_up",), 0.0, max_frames=2)
    with pytest.raises(ValueError, match="drives"):
        wp.run_condition(wp.Condition(0, "waist_up"), 10.0, max_frames=2, drives=("magic",))
    # the CLI's main() in this process (tests/cli_run.py says why): a SystemExit with a
    # message is what `python -m` prints to stderr before exiting 1
    from avatar_core.cli import main
    from tests.cli_run import run_main

    out = tmp_path / "unused"
    with pytest.raises(SystemExit, match="--identities takes integers"):
        main(["synth", "webcam-eval", "--out", str(out), "--identities", "a,b"])
    bad = run_main(main, ["synth", "webcam-eval", "--out", out, "--drives", "live,magic"],
                   capsys)
    assert bad.returncode != 0 and "drives must be among" in bad.stderr
    assert not out.exists()


def test_a_few_frames_of_the_protocol_through_the_real_tracker():
    pytest.importorskip("onnxruntime")
    from avatar_core.track.models import ModelFetchError, fetch_models

    try:
        fetch_models()
    except ModelFetchError as exc:
        pytest.skip(f"cannot fetch the MediaPipe landmark models: {exc}")
    # The first 0.6 s at 5 fps: the right arm rising into the wave.
    summary = run_protocol((0,), ("waist_up",), 5.0, max_frames=4, score_size=(160, 120),
                           drives=("live", "embedding", "arm_cues", "true_all",
                                   "true_all_depth"))
    live, true = summary["overall"]["live"], summary["overall"]["true_all"]
    assert summary["conditions"][0]["frames"] == 4
    assert summary["presence"]["face"] == 1.0 and summary["presence"]["pose"] == 1.0
    # The truth's 2D landmarks refitted put the avatar nearly where the truth does, and
    # better than the tracked ones (the fitter is sound; what the landmarks mean is not).
    assert true["psnr"] > live["psnr"] + 3.0
    assert true["root"] < 5.0 and true["neck_head"] < 8.0
    assert true["root"] < live["root"] and true["forearms"] < live["forearms"]
    assert live["fit_ms"] > 0 and np.isfinite(live["jitter_px"])
    assert [r["min_cutoff"] for r in summary["curve"]][0] is None  # unsmoothed first
    # The true depth of the arms and torso on top settles the forearms that 2D leaves open.
    depth = summary["overall"]["true_all_depth"]
    assert depth["forearms"] < true["forearms"] and depth["elbows"] < true["elbows"]
    embedded = summary["overall"]["embedding"]
    assert np.isfinite(embedded["psnr"]) and embedded["fit_ms"] > 0
    # The live path's cues (BlazePose's world bones) turn the forearms toward the truth.
    cued = summary["overall"]["arm_cues"]
    assert np.isfinite(cued["psnr"]) and cued["forearms"] < live["forearms"]
    md = protocol_markdown(summary)
    for label in ("webcam, live fit", "webcam, learned embedding + 3D cues", "all 2D true",
                  "all 2D true + true arm and torso depth",
                  "webcam, world bone directions + elbow hinge"):
        assert f"| {label} |" in md


def test_each_frame_is_labelled_with_the_motion_playing():
    take = motion_sequence(list(wp.TAKE))
    fps = 10.0
    labels = wp.motion_of_frames(wp.TAKE, fps, int(take.duration * fps) + 1)
    assert labels[0] == wp.TAKE[0] and labels[-1] == wp.TAKE[-1]
    assert [n for i, n in enumerate(labels) if i == 0 or labels[i - 1] != n] == list(wp.TAKE)
    first = take.tracks[0].duration
    assert labels[int(first * fps)] == wp.TAKE[0]  # its last frame
    assert labels[int(first * fps) + 2] == wp.TAKE[1]  # in the crossfade into the next
    assert wp.motion_of_frames(wp.TAKE, fps, 2, start_frame=int(first * fps) + 2) == \
        [wp.TAKE[1]] * 2


def test_a_recording_is_fitted_once_per_drive_and_variant():
    """Fit variants beside the base on the same recorded landmarks (`fit_recording`): here a
    recording whose 'live' landmarks are the truth's, so no tracker is needed."""
    from avatar_core.gaussians.animate import synthetic_package
    from avatar_core.motion.rig import model_rig
    from avatar_core.synth.model_writer import ensure_models
    from avatar_core.track.fit.camera import WebcamCamera
    from avatar_core.track.fit.fitter import FrameFitter

    files = ensure_models()
    from avatar_core.synth.actor import Actor

    actor = Actor.load(files, 0)
    cond = wp.Condition(0, "waist_up")
    transl = wp.framed_transl(actor, wp.webcam_camera(), cond.framing)
    truth = wp.take_params(actor, model_rig(files, actor.model), transl, 5.0, max_frames=2)
    fitter = FrameFitter(synthetic_package(files.root, 0)[1], np.asarray(actor.betas))
    cam = WebcamCamera(640, 480, wp.FOV_X_DEG)
    obs = [wp._true_observations(fitter, p, cam)[0] for p in truth]
    n = len(truth)
    rec = wp.Recording(cond, 5.0, truth, obs, obs, [wp._true_pose_points(fitter, p)
                                                     for p in truth], [1.0] * n,
                       {g: np.ones(n, bool) for g in ("face", "left_hand", "right_hand",
                                                      "pose")},
                       {}, {"left_hand": np.zeros(n, bool), "right_hand": np.zeros(n, bool)})
    variants = {"arms": {"hold_arms": True}}
    crossed = wp.fit_recording(rec, drives=("live",), variants=variants, score_size=(80, 60),
                               curve=False)
    assert list(crossed.metrics) == ["live", "live+arms"]
    assert all(len(crossed.fit_ms[d]) == n for d in crossed.metrics)
    assert crossed.metrics["live"]["psnr"] > 20.0  # the truth's landmarks, refitted
    named = wp.fit_recording(rec, drives=("true_all_depth+arms",), variants=variants,
                             score_size=(80, 60), curve=False)
    assert list(named.metrics) == ["true_all_depth+arms"]
    # BlazePose's world points swapped for the truth's, and run through the learned
    # correction (a no-op here: these observations carry no world points)
    worlds = wp.fit_recording(rec, drives=("arm_cues_true_world", "arm_cues_corrected"),
                              score_size=(80, 60), curve=False)
    assert worlds.metrics["arm_cues_true_world"]["psnr"] > 20.0
    assert np.isfinite(worlds.metrics["arm_cues_corrected"]["psnr"])
    assert wp.drive_observations(rec, 0, "arm_cues_true_world").world is not None
    assert rec.live[0].world is None  # the recording untouched
    with pytest.raises(ValueError, match="unknown fit variant"):
        wp.fit_recording(rec, drives=("live+nope",), variants=variants, curve=False)


def test_replay_variants_take_tuples_and_fit_fields():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "bench" / "webcam_replay.py"
    spec = importlib.util.spec_from_file_location("webcam_replay", path)
    replay = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(replay)
    got = replay.parse_variants(
        "a:fit.world_direction_bones=((11,13),(12,11)),fit.world_direction_weight=30.0;"
        "b:world_min_cutoff=3.0")
    assert got[""] == {} and got["b"] == {"world_min_cutoff": 3.0}
    assert got["a"]["fit"] == {"world_direction_bones": ((11, 13), (12, 11)),
                               "world_direction_weight": 30.0}
    with pytest.raises(TypeError):
        replay.parse_variants("c:fit.no_such_field=1")


def test_a_variant_changes_the_drives_own_fit():
    """A variant of the arm_cues drive that names its bones changes them and keeps the other
    cues (applied before the drive's cues, they were silently overwritten)."""
    from avatar_core.synth.tracking_eval.protocol import with_variant
    from avatar_core.synth.tracking_eval.protocol_drives import drive_config
    from avatar_core.track.fit.sequence import ARM_CUES, SequenceFitConfig

    bones = ((11, 13), (23, 11))
    config = with_variant(drive_config("arm_cues", SequenceFitConfig()),
                          {"hold_arms": True, "fit": {"world_direction_bones": bones}})
    assert config.fit.world_direction_bones == bones and config.hold_arms
    assert config.fit.world_direction_weight == ARM_CUES["world_direction_weight"]
    assert with_variant(drive_config("live", SequenceFitConfig()), {}).fit == \
        SequenceFitConfig().fit


def test_partial_truth_drives_swap_only_their_part():
    """`arm_cues_true_forearms` keeps BlazePose's upper arms and lengths and turns only the
    forearms onto the truth; `arm_cues_true_shoulders_2d` moves only the shoulders' pixels."""
    from avatar_core.track.fit import correspondence as cor
    from avatar_core.track.fit.observations import empty_observations
    from avatar_core.track.fit.world_correction import bone_directions
    from avatar_core.track.fit.world_cues import WORLD_TO_CAMERA

    rng = np.random.default_rng(0)
    truth_points = rng.normal(0, 0.3, (33, 3)) + [0.0, 0.0, -2.0]
    live, true = empty_observations((640, 480)), empty_observations((640, 480))
    for obs in (live, true):
        obs.weights[cor.POSE_SLICE] = 1.0
    live.pixels[cor.POSE_SLICE] = rng.uniform(0, 480, (33, 2))
    true.pixels[cor.POSE_SLICE] = rng.uniform(0, 480, (33, 2))
    live.world = rng.normal(0, 0.3, (33, 3))
    n = 1
    rec = wp.Recording(wp.Condition(0, "waist_up"), 5.0, [{}], [live], [true], [truth_points],
                       [1.0], {}, {}, {"left_hand": np.zeros(n, bool),
                                       "right_hand": np.zeros(n, bool)})
    fore = wp.drive_observations(rec, 0, "arm_cues_true_forearms")
    got_unit, got_len = bone_directions(fore.world * WORLD_TO_CAMERA)
    live_unit, live_len = bone_directions(live.world * WORLD_TO_CAMERA)
    true_unit, _ = bone_directions(truth_points)
    np.testing.assert_allclose(got_len, live_len)
    np.testing.assert_allclose(got_unit[[0, 2]], live_unit[[0, 2]])
    np.testing.assert_allclose(got_unit[[1, 3]], true_unit[[1, 3]], atol=1e-12)
    shoulders = wp.drive_observations(rec, 0, "arm_cues_true_shoulders_2d")
    moved = np.flatnonzero((shoulders.pixels != live.pixels).any(1)) - cor.POSE_SLICE.start
    assert moved.tolist() == [11, 12]
    np.testing.assert_array_equal(shoulders.world, live.world)
    assert rec.live[0] is live and np.array_equal(live.world, rec.live[0].world)


def _actor_rig():
    """Identity 0 of the studio family and its motion rig."""
    from avatar_core.motion.rig import model_rig
    from avatar_core.synth.actor import Actor
    from avatar_core.synth.model_writer import ensure_models

    files = ensure_models()
    actor = Actor.load(files, 0)
    return actor, model_rig(files, actor.model)


def test_a_turned_condition_turns_the_whole_body_about_the_vertical():
    from scipy.spatial.transform import Rotation

    actor, rig = _actor_rig()
    transl = np.zeros(3)
    straight = wp.take_params(actor, rig, transl, 5.0, max_frames=3)
    turned = wp.take_params(actor, rig, transl, 5.0, max_frames=3, turn_deg=-30.0)
    for a, b in zip(straight, turned, strict=True):
        rel = Rotation.from_rotvec(b["global_orient"]) * \
            Rotation.from_rotvec(np.asarray(a["global_orient"]).reshape(3)).inv()
        np.testing.assert_allclose(rel.as_rotvec(), [0.0, np.radians(-30.0), 0.0], atol=1e-9)
        np.testing.assert_array_equal(a["body_pose"], b["body_pose"])
    assert wp.Condition(1, "waist_up", -30.0).name == "1_waist_up_turn-30"
    assert wp.Condition(1, "waist_up").name == "1_waist_up"
    assert wp.Condition(1, "waist_up", -30.0, 12.0).name == "1_waist_up_turn-30_lean+12"
    assert wp.Condition(1, "waist_up", -30.0, 12.0).framing_label == \
        "waist_up turned -30 deg leaned +12 deg"
    assert wp.Condition(1, "waist_up").framing_label == "waist_up"


def test_a_leaned_condition_leans_forward_before_it_turns():
    from scipy.spatial.transform import Rotation

    actor, rig = _actor_rig()
    transl = np.zeros(3)
    straight = wp.take_params(actor, rig, transl, 5.0, max_frames=2)
    leaned = wp.take_params(actor, rig, transl, 5.0, max_frames=2, lean_deg=12.0)
    both = wp.take_params(actor, rig, transl, 5.0, max_frames=2, turn_deg=90.0, lean_deg=12.0)
    up = np.array([0.0, 1.0, 0.0])  # the spine's direction at rest, in the root's frame
    for a, b, c in zip(straight, leaned, both, strict=True):
        root = Rotation.from_rotvec(np.asarray(a["global_orient"]).reshape(3))
        rel = Rotation.from_rotvec(b["global_orient"]) * root.inv()
        np.testing.assert_allclose(rel.as_rotvec(), [np.radians(12.0), 0.0, 0.0], atol=1e-9)
        # the body faces +z, so a forward lean tips its up axis toward +z
        assert rel.apply(up)[2] == pytest.approx(np.sin(np.radians(12.0)))
        # turned a quarter to its left afterwards, the lean tips it toward +x
        tipped = (Rotation.from_rotvec(c["global_orient"]) * root.inv()).apply(up)
        np.testing.assert_allclose(tipped, [np.sin(np.radians(12.0)), np.cos(np.radians(12.0)),
                                            0.0], atol=1e-9)


def _one_frame_recording(seed: int):
    """(BlazePose's observations with random world landmarks, random true pose points [33, 3],
    a one-frame recording of the two) for the partial-truth drives."""
    from avatar_core.track.fit import correspondence as cor
    from avatar_core.track.fit.observations import empty_observations

    rng = np.random.default_rng(seed)
    live = empty_observations((640, 480))
    live.weights[cor.POSE_SLICE] = 1.0
    live.world = rng.normal(0, 0.3, (33, 3))
    truth = rng.normal(0, 0.3, (33, 3))
    rec = wp.Recording(wp.Condition(0, "waist_up"), 5.0, [{}], [live], [live], [truth],
                       [1.0], {}, {}, {"left_hand": np.zeros(1, bool),
                                       "right_hand": np.zeros(1, bool)})
    return live, truth, rec


def test_true_upper_arms_keep_blazepose_forearms():
    """`arm_cues_true_upper_arms` moves the elbows, and each forearm follows at BlazePose's own
    direction and length."""
    from avatar_core.track.fit.world_correction import bone_directions
    from avatar_core.track.fit.world_cues import WORLD_TO_CAMERA

    live, truth_points, rec = _one_frame_recording(1)
    upper = wp.drive_observations(rec, 0, "arm_cues_true_upper_arms")
    got, got_len = bone_directions(upper.world * WORLD_TO_CAMERA)
    live_unit, live_len = bone_directions(live.world * WORLD_TO_CAMERA)
    np.testing.assert_allclose(got[[0, 2]], bone_directions(truth_points)[0][[0, 2]],
                               atol=1e-12)
    np.testing.assert_allclose(got[[1, 3]], live_unit[[1, 3]], atol=1e-12)
    np.testing.assert_allclose(got_len, live_len)


def test_the_true_torso_axis_drive_moves_only_blazeposes_hips():
    """`arm_cues_true_torso_axis`: BlazePose's hips' midpoint moves so that its axis to the
    shoulders is the truth's (at BlazePose's length and hip width), nothing else moves, and
    its fit uses the axis whether or not the hips are in view."""
    from avatar_core.synth.tracking_eval.protocol_drives import drive_config
    from avatar_core.track.fit.sequence import SequenceFitConfig
    from avatar_core.track.fit.world_cues import WORLD_TO_CAMERA

    live, truth_points, rec = _one_frame_recording(2)
    got = wp.drive_observations(rec, 0, "arm_cues_true_torso_axis").world
    unchanged = [i for i in range(33) if i not in (23, 24)]
    np.testing.assert_array_equal(got[unchanged], live.world[unchanged])

    def axis(points):
        v = points[[11, 12]].mean(axis=0) - points[[23, 24]].mean(axis=0)
        return v / np.linalg.norm(v), np.linalg.norm(v)

    np.testing.assert_allclose(axis(got * WORLD_TO_CAMERA)[0], axis(truth_points)[0],
                               atol=1e-12)
    np.testing.assert_allclose(axis(got)[1], axis(live.world)[1])
    np.testing.assert_allclose(got[23] - got[24], live.world[23] - live.world[24])
    np.testing.assert_array_equal(live.world, rec.live[0].world)  # the recording untouched
    # Missing BlazePose hips still get an axis (at a default length), never NaN.
    live.world[[23, 24]] = np.nan
    got = wp.drive_observations(rec, 0, "arm_cues_true_torso_axis").world
    assert np.isfinite(got[[23, 24]]).all()
    np.testing.assert_allclose(axis(got * WORLD_TO_CAMERA)[0], axis(truth_points)[0],
                               atol=1e-12)
    config = drive_config("arm_cues_true_torso_axis", SequenceFitConfig())
    assert not config.fit.torso_axis_hips_in_view and config.fit.torso_axis_weight > 0
    assert drive_config("arm_cues", SequenceFitConfig()).fit.torso_axis_hips_in_view


def test_the_true_torso_drive_turns_blazeposes_shoulders_and_keeps_its_arm_bones():
    """`arm_cues_true_torso`: the shoulders' line is the truth's about BlazePose's own midpoint
    and width, each arm bone keeps BlazePose's direction and length from its moved shoulder,
    the torso's axis is the truth's, and the line's turn is not multiplied again."""
    from avatar_core.synth.tracking_eval.protocol_drives import drive_config
    from avatar_core.track.fit.sequence import SequenceFitConfig
    from avatar_core.track.fit.world_correction import bone_directions
    from avatar_core.track.fit.world_cues import WORLD_TO_CAMERA

    live, truth, rec = _one_frame_recording(3)
    got = wp.drive_observations(rec, 0, "arm_cues_true_torso").world
    cam, live_cam = got * WORLD_TO_CAMERA, live.world * WORLD_TO_CAMERA

    def unit(v):
        return v / np.linalg.norm(v)

    np.testing.assert_allclose(unit(cam[11] - cam[12]), unit(truth[11] - truth[12]), atol=1e-12)
    np.testing.assert_allclose(got[[11, 12]].mean(0), live.world[[11, 12]].mean(0), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(got[11] - got[12]),
                               np.linalg.norm(live.world[11] - live.world[12]))
    for a, b in zip(bone_directions(cam), bone_directions(live_cam), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-12)
    axis = cam[[11, 12]].mean(0) - cam[[23, 24]].mean(0)
    np.testing.assert_allclose(unit(axis), unit(truth[[11, 12]].mean(0) - truth[[23, 24]].mean(0)),
                               atol=1e-12)
    kept = [i for i in range(33) if i not in (11, 12, 13, 14, 15, 16, 23, 24)]
    np.testing.assert_array_equal(got[kept], live.world[kept])
    fit = drive_config("arm_cues_true_torso", SequenceFitConfig()).fit
    assert fit.shoulder_line_yaw_gain == 1.0 and not fit.torso_axis_hips_in_view
    assert drive_config("arm_cues", SequenceFitConfig()).fit.shoulder_line_yaw_gain == 2.0
