"""Reading official model files: chumpy without chumpy, sparse regressors, clear errors."""

import os
import pickle

import numpy as np
import pytest

from avatar_core.body.errors import ModelFileError
from avatar_core.body.model_data import load_mano, load_smplx
from avatar_core.body.model_reader import read_model_file, require, to_array
from avatar_core.synth.model_writer import _write_official_pickle


def test_chumpy_and_sparse_values_are_read_as_arrays(tmp_path):
    arr = np.arange(12.0).reshape(2, 3, 2)
    reg = np.eye(3)
    _write_official_pickle(tmp_path / "m.pkl", {"shapedirs": arr, "J_regressor": reg, "n": 3},
                           chumpy_keys=("shapedirs",), sparse_keys=("J_regressor",))
    raw = (tmp_path / "m.pkl").read_bytes()
    assert b"chumpy.ch" in raw and b"csc_matrix" in raw
    data = read_model_file(tmp_path / "m.pkl")
    assert np.array_equal(to_array(data["shapedirs"], "shapedirs", tmp_path), arr)
    assert np.array_equal(to_array(data["J_regressor"], "J_regressor", tmp_path), reg)


def test_a_chumpy_expression_gets_a_clear_error(tmp_path):
    data = {"shapedirs": None}
    path = tmp_path / "m.pkl"
    _write_official_pickle(path, {"shapedirs": np.zeros(2)}, chumpy_keys=("shapedirs",))
    data = read_model_file(path)
    data["shapedirs"].state = {"a": 1, "b": 2}  # an operator node has no 'x'
    with pytest.raises(ModelFileError, match="chumpy expression"):
        to_array(data["shapedirs"], "shapedirs", path)


class _Evil:
    def __reduce__(self):
        return (os.system, ("echo pwned",))


def test_pickles_that_run_code_are_refused(tmp_path):
    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps({"v_template": _Evil()}))
    with pytest.raises(ModelFileError, match="refusing"):
        read_model_file(path)


def test_missing_file_unknown_type_and_not_a_dict(tmp_path):
    with pytest.raises(ModelFileError, match="not found"):
        read_model_file(tmp_path / "nope.npz")
    (tmp_path / "m.txt").write_text("x")
    with pytest.raises(ModelFileError, match="unknown model file type"):
        read_model_file(tmp_path / "m.txt")
    (tmp_path / "list.pkl").write_bytes(pickle.dumps([1, 2]))
    with pytest.raises(ModelFileError, match="expected a dict"):
        read_model_file(tmp_path / "list.pkl")
    (tmp_path / "broken.pkl").write_bytes(b"\x80\x02garbage")
    with pytest.raises(ModelFileError, match="cannot read"):
        read_model_file(tmp_path / "broken.pkl")


def test_require_names_missing_keys_and_wrong_shapes(tmp_path):
    data = {"v_template": np.zeros((5, 2))}
    with pytest.raises(ModelFileError, match="missing key 'f'"):
        require(data, "f", tmp_path)
    with pytest.raises(ModelFileError, match=r"'v_template' should have shape \[\*, 3\]"):
        require(data, "v_template", tmp_path, shape=(None, 3))


def test_loaders_report_the_first_missing_key(tmp_path):
    np.savez(tmp_path / "SMPLX_NEUTRAL.npz", v_template=np.zeros((4, 3)))
    with pytest.raises(ModelFileError, match="missing key"):
        load_smplx(tmp_path / "SMPLX_NEUTRAL.npz")
    np.savez(tmp_path / "hand.npz", v_template=np.zeros((4, 3)))
    with pytest.raises(ModelFileError, match="cannot tell the hand"):
        load_mano(tmp_path / "hand.npz")
