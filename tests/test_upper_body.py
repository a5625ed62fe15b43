"""The upper-body cut: what stays, what goes, and that SMPL-X parameters drive it unchanged."""

import numpy as np
import torch

from avatar_core.body.models import SMPLXModel
from avatar_core.body.skeleton import LOWER_BODY_PARTS
from avatar_core.body.upper_body import UpperBodyModel
from tests.conftest import random_smplx_params


def test_cut_leaves_no_dangling_indices(smplx_data, segmentation):
    model = UpperBodyModel(smplx_data, segmentation)
    faces = model.faces.numpy()
    v = model.num_vertices
    assert faces.min() >= 0 and faces.max() < v
    used = np.zeros(v, dtype=bool)
    used[faces.ravel()] = True
    assert used.all(), "every kept vertex belongs to a kept face"
    # Faces are the full model's faces, re-indexed.
    full_faces = {tuple(sorted(f)) for f in smplx_data.faces.tolist()}
    ids = model.vertex_ids
    assert all(tuple(sorted(ids[f])) in full_faces for f in faces.tolist())


def test_face_arms_and_both_hands_stay_and_legs_go(smplx_data, segmentation):
    model = UpperBodyModel(smplx_data, segmentation)
    kept = set(model.vertex_ids.tolist())
    for part in ("head", "leftEye", "rightEye", "leftArm", "rightForeArm", "leftHand",
                 "rightHand", "leftHandIndex1", "rightHandIndex1", "neck", "spine2"):
        assert set(segmentation[part].tolist()) <= kept, part
    for part in LOWER_BODY_PARTS:
        if part in segmentation:
            assert not set(segmentation[part].tolist()) & kept, part
    assert model.lmk_faces is not None and model.dynamic_lmk_faces is None


def test_full_smplx_parameters_drive_it_exactly(smplx_data, segmentation):
    params = random_smplx_params(3, seed=21, scale=0.5)
    upper = UpperBodyModel(smplx_data, segmentation, dtype=torch.float64)(params)
    full = SMPLXModel(smplx_data, dtype=torch.float64)(params)
    ids = torch.as_tensor(UpperBodyModel(smplx_data, segmentation).vertex_ids)
    assert torch.allclose(upper.vertices, full.vertices[:, ids], atol=1e-12)
    assert torch.allclose(upper.joints, full.joints, atol=1e-12)
    assert torch.allclose(upper.landmarks, full.landmarks, atol=1e-12)


def test_load_from_files(synthetic_files):
    model = UpperBodyModel.load(synthetic_files.smplx_npz, synthetic_files.segmentation)
    assert model.num_vertices < 10475 and model(None).vertices.shape[1] == model.num_vertices
