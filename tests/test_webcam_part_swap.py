"""The part swaps of the webcam protocol (`synth/tracking_eval/part_swap.py`): which
parameters each part takes from the truth, and that the scores move the right way on real
renders of the studio actor."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from avatar_core.body.skeleton import JOINT
from avatar_core.synth.tracking_eval import part_swap as ps


def _params(value: float) -> dict[str, np.ndarray]:
    return {"global_orient": np.full(3, value), "transl": np.zeros(3),
            "body_pose": np.full((21, 3), value), "jaw_pose": np.full(3, value),
            "leye_pose": np.full(3, value), "reye_pose": np.full(3, value),
            "expression": np.full(10, value), "left_hand_pose": np.full((15, 3), value),
            "right_hand_pose": np.full((15, 3), value)}


def test_each_part_takes_only_its_own_parameters():
    fitted, truth = _params(1.0), _params(2.0)
    arms = ps.swap_parts(fitted, truth, ("arms",))
    rows = [JOINT[j] - 1 for j in ps.PARTS["arms"][1]]
    assert (arms["body_pose"][rows] == 2.0).all()
    others = np.delete(arms["body_pose"], rows, axis=0)
    assert (others == 1.0).all() and (arms["global_orient"] == 1.0).all()
    assert (fitted["body_pose"] == 1.0).all()  # untouched
    every = ps.swap_parts(fitted, truth, tuple(ps.PARTS))
    free = [JOINT[j] - 1 for _, joints in ps.PARTS.values() for j in joints]
    for k, v in every.items():
        if k == "body_pose":
            assert (v[free] == 2.0).all()
        elif k != "transl":
            assert (v == 2.0).all(), k
    with pytest.raises(ValueError, match="unknown part"):
        ps.swap_parts(fitted, truth, ("legs",))


def test_variants_are_none_each_alone_and_all_but_each():
    v = ps.swap_variants(("arms", "face"))
    assert v["fitted"] == () and v["only arms true"] == ("arms",)
    assert set(v["all true but face"]) == set(ps.PARTS) - {"face"}
    assert len(v) == 5


def _random_body(rng) -> dict[str, np.ndarray]:
    return {"global_orient": rng.normal(0, 0.3, 3), "body_pose": rng.normal(0, 0.5, (21, 3))}


def _bone(params, rest, joint: str, child: str) -> np.ndarray:
    from avatar_core.metrics.webcam import world_rotations

    return world_rotations(params)[JOINT[joint]] @ (rest[JOINT[child]] - rest[JOINT[joint]])


def test_arm_directions_come_from_the_truth_and_the_twist_stays_the_fits():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    rest = rng.normal(0, 0.3, (55, 3))
    fitted, truth = _random_body(rng), _random_body(rng)
    out = ps.with_arm_directions(fitted, truth, rest)
    for side in ("left", "right"):
        for joint, child in (("shoulder", "elbow"), ("elbow", "wrist")):
            np.testing.assert_allclose(_bone(out, rest, f"{side}_{joint}", f"{side}_{child}"),
                                       _bone(truth, rest, f"{side}_{joint}", f"{side}_{child}"),
                                       atol=1e-9)
    arms = [JOINT[f"{s}_{j}"] - 1 for s in ("left", "right") for j in ("shoulder", "elbow")]
    np.testing.assert_array_equal(np.delete(out["body_pose"], arms, 0),
                                  np.delete(fitted["body_pose"], arms, 0))
    np.testing.assert_array_equal(out["global_orient"], fitted["global_orient"])
    # the same directions already: nothing moves
    same = ps.with_arm_directions(fitted, fitted, rest)
    np.testing.assert_allclose(same["body_pose"], fitted["body_pose"], atol=1e-9)
    # a truth that differs only by the upper arm's twist about its bone: the fit's twist stays
    shoulder = JOINT["left_shoulder"]
    upper = rest[JOINT["left_elbow"]] - rest[shoulder]
    twisted = {k: np.array(v) for k, v in fitted.items()}
    local = Rotation.from_rotvec(fitted["body_pose"][shoulder - 1])
    twisted["body_pose"][shoulder - 1] = (local * Rotation.from_rotvec(
        0.7 * upper / np.linalg.norm(upper))).as_rotvec()
    kept = ps.with_arm_directions(fitted, twisted, rest)
    np.testing.assert_allclose(kept["body_pose"][shoulder - 1],
                               fitted["body_pose"][shoulder - 1], atol=1e-9)


def test_arm_split_variants_label_what_comes_from_the_truth():
    rng = np.random.default_rng(4)
    rest = rng.normal(0, 0.3, (55, 3))
    fitted, truth = _params(0.1), _params(0.2)
    fitted["body_pose"] = rng.normal(0, 0.4, (21, 3))
    truth["body_pose"] = rng.normal(0, 0.4, (21, 3))
    v = ps.arm_split_variants(fitted, truth, rest)
    assert v["fitted"] is fitted
    rest_true = v["all true but arms"]
    np.testing.assert_array_equal(rest_true["global_orient"], truth["global_orient"])
    # all true but the twist: the truth's bones, the fitted arms' twist on the true torso
    bone = _bone(v["all true but arm twist (directions true)"], rest, "left_elbow", "left_wrist")
    np.testing.assert_allclose(bone, _bone(truth, rest, "left_elbow", "left_wrist"), atol=1e-9)
    bone = _bone(v["all true but arm directions (twist true)"], rest, "left_shoulder",
                 "left_elbow")
    np.testing.assert_allclose(bone, _bone(fitted, rest, "left_shoulder", "left_elbow"),
                               atol=1e-9)


def test_swaps_on_renders_of_the_studio_actor():
    from avatar_core.motion.library import motion_sequence
    from avatar_core.motion.rig import model_rig
    from avatar_core.synth.actor import Actor
    from avatar_core.synth.model_writer import ensure_models
    from avatar_core.synth.tracking_eval import protocol as wp

    files = ensure_models()
    actor = Actor.load(files, 0)
    transl = wp.framed_transl(actor, wp.webcam_camera(), "waist_up")
    truth = wp.take_params(actor, model_rig(files, actor.model), transl, 5.0, max_frames=11,
                           names=("wave",), start_frame=8)
    assert motion_sequence(["wave"]).duration > 2.0
    fitted = [{**p, "body_pose": np.array(p["body_pose"])} for p in truth]
    for p in fitted:  # the arms wrong by 40 deg, the rest exact
        for j in ("left_elbow", "right_elbow"):
            p["body_pose"][JOINT[j] - 1] += [0.0, math.radians(40), 0.0]
    res = SimpleNamespace(smooth={"fit": fitted}, truth=truth)
    cam = wp.score_camera(transl, actor, 96, 72)
    scores = ps.score_swaps(actor, res, "fit", cam, {
        "fitted": (), "only arms true": ("arms",), "only face true": ("face",),
        "all true but face": tuple(p for p in ps.PARTS if p != "face")}, arm_split=True)
    assert scores["only arms true"]["psnr"] == ps.PSNR_CAP_DB  # exact
    assert scores["all true but face"]["psnr"] == ps.PSNR_CAP_DB
    assert scores["fitted"]["psnr"] < 40.0
    assert scores["only face true"]["psnr"] == pytest.approx(scores["fitted"]["psnr"])
    assert scores["fitted"]["elbows"] == pytest.approx(40.0, abs=0.5)
    assert scores["only arms true"]["elbows"] == pytest.approx(0.0, abs=1e-3)
    # the elbows' error bends the forearms (a swing, nearly no twist): their true directions
    # all but undo it, their true twist alone does not
    assert scores["arm directions true, twist fitted"]["psnr"] > scores["fitted"]["psnr"] + 10
    assert scores["arm directions true, twist fitted"]["elbows"] < 5.0
    assert scores["all true but arm directions (twist true)"]["psnr"] < 40.0
