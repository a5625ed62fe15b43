"""The synthetic SMPL-X file loads in the official `smplx` package and poses identically."""

import numpy as np
import pytest
import torch

from avatar_core.body.model_data import load_smplx
from avatar_core.body.models import SMPLXModel
from avatar_core.synth.model_writer import SMPLX_SEMANTIC_VERTEX_IDS
from tests.conftest import as_torch, random_smplx_params

smplx = pytest.importorskip("smplx")

EXTRA_JOINT_ORDER = ["nose", "reye", "leye", "rear", "lear", "LBigToe", "LSmallToe", "LHeel",
                     "RBigToe", "RSmallToe", "RHeel", "lthumb", "lindex", "lmiddle", "lring",
                     "lpinky", "rthumb", "rindex", "rmiddle", "rring", "rpinky"]


def _official(path, **kwargs):
    return smplx.SMPLX(model_path=str(path), ext="npz", num_betas=10, num_expression_coeffs=10,
                       dtype=torch.float64, **kwargs)


@pytest.mark.parametrize("pca", [None, 6])
def test_forward_matches_the_smplx_package(synthetic_files, smplx_data, pca):
    params = random_smplx_params(4, seed=11, scale=0.4)
    if pca:
        rng = np.random.default_rng(3)
        params["left_hand_pose"] = rng.normal(0, 1, (4, pca))
        params["right_hand_pose"] = rng.normal(0, 1, (4, pca))
    ref_model = _official(synthetic_files.smplx_npz, use_pca=pca is not None,
                          num_pca_comps=pca or 6, flat_hand_mean=False, batch_size=4,
                          use_face_contour=True)
    p = as_torch(params)
    ref = ref_model(**{k: (v.reshape(4, -1) if k == "body_pose" or v.dim() == 3 else v)
                       for k, v in p.items()})
    ours = SMPLXModel(smplx_data, hand_pca=pca, dtype=torch.float64, face_contour=True)(params)
    assert (ours.vertices - ref.vertices).abs().max() <= 1e-5
    assert (ours.joints - ref.joints[:, :55]).abs().max() <= 1e-5
    extra_ids = [SMPLX_SEMANTIC_VERTEX_IDS[n] for n in EXTRA_JOINT_ORDER]
    assert (ours.vertices[:, extra_ids] - ref.joints[:, 55:76]).abs().max() <= 1e-5
    # Landmarks: 51 static, then 17 contour points.
    assert (ours.landmarks - ref.joints[:, 76:]).abs().max() <= 1e-5


def test_semantic_vertices_sit_where_smplx_expects_them(smplx_data):
    verts = smplx_data.v_template
    ids = SMPLX_SEMANTIC_VERTEX_IDS
    head = verts[ids["nose"]]
    assert head[2] > verts[ids["leye"], 2] - 0.05 and head[1] > 0.3  # nose on the face, up high
    assert verts[ids["leye"], 0] > 0 > verts[ids["reye"], 0]  # subject's left is +x
    assert verts[ids["lindex"], 0] > 0.6 and verts[ids["rindex"], 0] < -0.6  # T-pose fingertips
    assert verts[ids["LHeel"], 1] < -0.8 and verts[ids["LBigToe"], 2] > verts[ids["LHeel"], 2]


def test_pickle_and_npz_load_the_same_model(synthetic_files, smplx_data):
    from_pkl = load_smplx(synthetic_files.smplx_pkl)
    for name in ("v_template", "shapedirs", "exprdirs", "posedirs", "joint_regressor", "weights",
                 "joint_template", "lmk_bary", "dynamic_lmk_bary"):
        assert np.array_equal(getattr(from_pkl, name), getattr(smplx_data, name)), name
    assert np.array_equal(from_pkl.faces, smplx_data.faces)
    assert from_pkl.parents == smplx_data.parents
