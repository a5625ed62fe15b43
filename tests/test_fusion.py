"""FLAME and MANO parameters fused into SMPL-X move the mesh as their own models do."""

import numpy as np
import pytest
import torch

from avatar_core.body import lbs
from avatar_core.body.errors import ParameterError
from avatar_core.body.fusion import (
    FusionModels,
    fuse,
    fuse_flame,
    fuse_mano,
    fuse_sequence,
    mirror_axis_angle,
)
from avatar_core.body.model_data import load_correspondence
from avatar_core.body.models import FLAMEModel, MANOModel, SMPLXModel
from avatar_core.body.skeleton import JOINT
from avatar_core.body.upper_body import UpperBodyModel

F64 = {"dtype": torch.float64}


@pytest.fixture(scope="module")
def corr(synthetic_files):
    return {**load_correspondence(synthetic_files.flame_correspondence),
            **load_correspondence(synthetic_files.mano_correspondence)}


def test_flame_expression_and_jaw_move_the_head_as_flame_does(smplx_data, flame_data, corr,
                                                              segmentation):
    rng = np.random.default_rng(0)
    flame = {"expr": np.zeros((2, 100)), "jaw_pose": rng.normal(0, 0.2, (2, 3)),
             "eyes_pose": rng.normal(0, 0.2, (2, 6)), "neck_pose": rng.normal(0, 0.2, (2, 3))}
    flame["expr"][:, :10] = rng.normal(0, 1.0, (2, 10))
    model = SMPLXModel(smplx_data, **F64)
    fused = fuse_flame({}, flame, model, head_rotation="keep")
    ours = model(fused).vertices[:, corr["flame"]]
    theirs = FLAMEModel(flame_data, **F64)(flame).vertices
    assert torch.allclose(ours, theirs, atol=1e-10)
    # The same through the upper-body model.
    upper64 = UpperBodyModel(smplx_data, segmentation, **F64)
    local = np.searchsorted(upper64.vertex_ids, corr["flame"])
    assert torch.allclose(upper64(fuse_flame({}, flame, upper64, head_rotation="keep"))
                          .vertices[:, local], theirs, atol=1e-10)


def _segmentation(smplx_data):
    import json
    from pathlib import Path

    from avatar_core.body.skeleton import SMPLX_PART_NAMES  # noqa: F401 - documents the names
    path = Path(smplx_data.source).with_name("smplx_vert_segmentation.json")
    return {k: np.asarray(v) for k, v in json.loads(path.read_text()).items()}


def test_flame_shape_becomes_faded_offsets(smplx_data, flame_data, corr):
    shape = np.zeros((1, 300))
    shape[0, :10] = np.random.default_rng(1).normal(0, 1.5, 10)
    model = SMPLXModel(smplx_data, flat_hand_mean=True, **F64)
    flame_model = FLAMEModel(flame_data, **F64)
    fused = fuse_flame({}, {"shape": shape}, model, flame_model=flame_model,
                       correspondence=corr["flame"], head_rotation="keep")
    verts = model(fused).vertices[0]
    disp = (verts - torch.as_tensor(smplx_data.v_template))[corr["flame"]]
    expected = flame_model({"shape": shape}).vertices[0] - flame_model.v_template
    fade = smplx_data.weights[corr["flame"]][:, [15, 22, 23, 24]].sum(1)
    interior = fade > 1 - 1e-9
    assert interior.sum() > 100
    assert torch.allclose(disp[interior], expected[interior], atol=1e-12)
    # Toward the neck the offsets fade out, so no seam opens where FLAME's region ends.
    outside = np.setdiff1d(np.arange(model.num_vertices), corr["flame"])
    assert (verts - torch.as_tensor(smplx_data.v_template))[outside].abs().max() < 1e-12


def test_world_head_rotation_orients_the_neck(smplx_data):
    model = SMPLXModel(smplx_data, **F64)
    body = {"global_orient": [0.2, 0.5, -0.1], "body_pose": np.random.default_rng(2).normal(
        0, 0.2, (21, 3))}
    target = np.array([0.3, -0.4, 0.25])
    fused = fuse_flame(body, {"rotation": target}, model)
    rot = lbs.rodrigues(model.full_pose(model._normalize(fused, _spec(model), "t")))
    world = lbs.global_rotations(rot, model.parents)[0, JOINT["neck"]]
    assert torch.allclose(world, lbs.rodrigues(torch.as_tensor(target)), atol=1e-10)
    assert np.allclose(fused.global_orient.numpy(), [[0.2, 0.5, -0.1]])  # body kept


def _spec(model):
    return {k: v for k, v in model.param_spec().items() if k != "vertex_offsets"}


@pytest.mark.parametrize("pca", [None, 12])
def test_mano_hand_moves_as_mano_does(smplx_data, mano_data, corr, pca):
    rng = np.random.default_rng(3)
    mano_model = MANOModel(mano_data["right"], hand_pca=pca, **F64)
    hand = {"hand_pose": rng.normal(0, 0.5 if pca else 0.3, (1, pca) if pca else (1, 15, 3)),
            "global_orient": [0.4, -0.2, 0.9]}
    model = SMPLXModel(smplx_data, **F64)
    body = {"body_pose": rng.normal(0, 0.3, (21, 3)), "global_orient": [0.1, 0.2, 0.3]}
    out = model(fuse_mano(body, hand, model, side="right", mano_model=mano_model))
    ours = out.vertices[0, corr["right_hand"]] - out.joints[0, JOINT["right_wrist"]]
    mano = mano_model(hand)
    theirs = mano.vertices[0] - mano.joints[0, 0]
    assert torch.allclose(ours, theirs, atol=1e-10)


def test_left_right_mirroring(smplx_data, mano_data, corr):
    model = SMPLXModel(smplx_data, flat_hand_mean=True, **F64)
    right_pose = np.random.default_rng(4).normal(0, 0.4, (15, 3))
    out = model({"right_hand_pose": right_pose,
                 "left_hand_pose": mirror_axis_angle(torch.as_tensor(right_pose)).numpy()})
    left = out.vertices[0, corr["left_hand"]]
    right = out.vertices[0, corr["right_hand"]]
    assert torch.allclose(left, right * torch.tensor([-1.0, 1.0, 1.0], **F64), atol=1e-10)
    # A right-hand MANO fit used for the left hand with mirror=True gives the same left hand.
    mano_r = MANOModel(mano_data["right"], flat_hand_mean=True, **F64)
    fused = fuse_mano({}, {"hand_pose": right_pose}, model, side="left", mano_model=mano_r,
                      mirror=True, wrist="keep")
    assert torch.allclose(model(fused).vertices[0, corr["left_hand"]], left, atol=1e-10)


def test_fuse_everything_and_reject_bad_calls(smplx_data, flame_data, mano_data, corr):
    model = SMPLXModel(smplx_data, **F64)
    with pytest.warns(UserWarning, match="dropped"):
        out = fuse({"betas": np.ones(10)}, model,
                   flame={"expr": np.ones(100), "jaw_pose": [0.2, 0, 0]},
                   right_hand={"hand_pose": np.zeros((15, 3))},
                   left_hand={"hand_pose": np.zeros(45)},
                   mano_models={"right": MANOModel(mano_data["right"], **F64)})
    assert torch.allclose(out.betas, torch.ones(1, 10, **F64))
    assert torch.allclose(out.expression, torch.ones(1, 10, **F64))
    with pytest.raises(ParameterError, match="head_rotation"):
        fuse_flame({}, {}, model, head_rotation="sideways")
    with pytest.raises(ParameterError, match="hand_pca=None"):
        fuse_mano({}, {}, SMPLXModel(smplx_data, hand_pca=6), side="left")
    with pytest.raises(ParameterError, match="NaN"):
        fuse_flame({}, {"jaw_pose": [np.nan, 0, 0]}, model)
    with pytest.raises(ParameterError, match="flame_model"):
        fuse_flame({}, {"shape": np.ones(10)}, model)


def test_front_door_fuses_a_sequence_as_frame_by_frame(smplx_data, mano_data):
    """fuse_sequence on params.npz arrays [T, ...] equals FusionModels.fuse one frame at a
    time; nothing to fuse leaves the SMPL-X keys as they are; strict refuses what it cannot
    fuse, lenient drops a FLAME shape with a warning."""
    rng = np.random.default_rng(3)
    models = FusionModels(SMPLXModel(smplx_data, **F64),
                          {"left": MANOModel(mano_data["left"], **F64)})
    t = 3
    params = {"betas": rng.normal(0, 1, 10), "body_pose": rng.normal(0, 0.2, (t, 21, 3)),
              "flame_expr": rng.normal(0, 1, (t, 10)), "flame_jaw_pose": rng.normal(0, .2, (t, 3)),
              "flame_rotation": rng.normal(0, .2, (t, 3)),
              "mano_left_hand_pose": rng.normal(0, .3, (t, 15, 3)),
              "mano_left_global_orient": rng.normal(0, .3, (t, 3))}
    seq, fused = fuse_sequence(params, t, models)
    assert fused and seq["body_pose"].shape == (t, 21, 3) and seq["betas"].shape == (t, 10)
    for f in range(t):
        one = models.fuse({"betas": params["betas"], "body_pose": params["body_pose"][f]},
                          {k[6:]: params[k][f] for k in params if k.startswith("flame_")},
                          {"left": {k[10:]: params[k][f] for k in params
                                    if k.startswith("mano_left_")}})
        for k, v in one.items():
            np.testing.assert_allclose(seq[k][f], v.numpy().reshape(seq[k][f].shape), atol=1e-12)
    plain, fused = fuse_sequence(params, t, None)
    assert not fused and set(plain) == {"betas", "body_pose"}
    np.testing.assert_array_equal(plain["body_pose"], params["body_pose"])
    assert models.fuse({"betas": params["betas"]}, {}, {"left": {}}) == {"betas": params["betas"]}
    right = {**params, "mano_right_hand_pose": params["mano_left_hand_pose"]}
    with pytest.raises(ParameterError, match="MANO"):
        fuse_sequence(right, t, models, strict=True)
    shaped = {**params, "flame_shape": np.ones(10)}
    with pytest.raises(ParameterError, match="FLAME model"):
        fuse_sequence(shaped, t, models, strict=True)
    lenient, _ = fuse_sequence(shaped, t, models)
    np.testing.assert_allclose(lenient["expression"], seq["expression"])
