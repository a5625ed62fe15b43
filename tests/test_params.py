"""Parameter validation: clear errors that name the field."""

import numpy as np
import pytest
import torch

from avatar_core.body.errors import ParameterError
from avatar_core.body.params import SMPLXParams, normalize_params

SPEC = {"betas": (10,), "body_pose": (21, 3), "transl": (3,)}


def _norm(values):
    return normalize_params(values, SPEC, dtype=torch.float64, device=torch.device("cpu"),
                            family="SMPL-X")


def test_missing_fields_are_zeros_and_unbatched_values_broadcast():
    out = _norm({"betas": np.ones((4, 10)), "transl": [0.0, 1.0, 2.0]})
    assert out["body_pose"].shape == (4, 21, 3) and not out["body_pose"].any()
    assert out["transl"].shape == (4, 3)
    assert torch.equal(out["transl"][3], torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64))


def test_flat_pose_is_accepted():
    assert _norm({"body_pose": np.zeros((2, 63))})["body_pose"].shape == (2, 21, 3)


@pytest.mark.parametrize("field,value", [
    ("body_pose", np.zeros((2, 20, 3))),
    ("betas", np.zeros((2, 11))),
    ("transl", np.zeros((2, 3, 1))),
    ("transl", "abc"),
])
def test_wrong_shape_names_the_field(field, value):
    with pytest.raises(ParameterError, match=f"SMPL-X.{field}"):
        _norm({field: value})


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_values_are_refused(bad):
    pose = np.zeros((1, 21, 3))
    pose[0, 5, 1] = bad
    with pytest.raises(ParameterError, match="body_pose contains NaN or Inf"):
        _norm({"body_pose": pose})


def test_unknown_field_and_batch_mismatch():
    with pytest.raises(ParameterError, match="unknown"):
        _norm({"bdy_pose": np.zeros((1, 63))})
    with pytest.raises(ParameterError, match="batch sizes disagree"):
        _norm({"betas": np.zeros((2, 10)), "transl": np.zeros((3, 3))})
    with pytest.raises(ParameterError, match="unknown SMPLXParams"):
        SMPLXParams.from_dict({"pose": 1})
