"""The dataset validator on hostile input: params.npz bombs and impossible shapes are problems
(never an allocation), a split may only borrow a dataset inside this one (the answer is the
same whether an outside path exists), and fuzzed files give problems, never an exception."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from avatar_core.dataset import DatasetError, load_dataset, validate_dataset
from avatar_core.dataset.problems import ERROR
from tests.dataset_fixtures import write_tiny_dataset

from .test_bounded_npz import MiB, peak_memory
from .upload_bombs import impossible_shape_npy, npz_bytes


@pytest.fixture(scope="module")
def tiny_root(tmp_path_factory) -> Path:
    return write_tiny_dataset(tmp_path_factory.mktemp("hardening") / "tiny").root


@pytest.fixture()
def tiny(tiny_root, tmp_path) -> Path:
    root = tmp_path / "tiny"
    shutil.copytree(tiny_root, root)
    return root


def _params(root: Path) -> Path:
    return root / "sequences" / "seq0" / "params.npz"


def _errors(root: Path, code: str) -> list:
    return [p for p in validate_dataset(root) if p.severity == ERROR and p.code == code]


@pytest.mark.parametrize("make, words", [
    (lambda: npz_bytes({"betas": np.zeros(10)}, bomb=("body_pose", 1 << 30)),
     "decompression bomb"),
    (lambda: npz_bytes({}, raw={"body_pose": impossible_shape_npy((10**13,))}), "declares shape"),
])
def test_params_bombs_are_problems_within_a_bounded_memory(tiny, make, words):
    _params(tiny).write_bytes(make())
    with peak_memory() as mem:
        problems = _errors(tiny, "params_unreadable")
    assert len(problems) == 1 and words in problems[0].message, problems
    assert mem["peak"] < 16 * MiB, mem
    with pytest.raises(DatasetError, match=words):
        load_dataset(tiny)


SPLIT_OUTSIDE = "split_outside_dataset"


@pytest.mark.parametrize("target", ["/etc", "/no/such/folder", "../../x", "../tiny", "a/../..",
                                    "C:/Windows", "sub\\..\\..", ""])
def test_a_split_may_not_name_a_dataset_outside(tiny, target):
    splits = json.loads((tiny / "splits.json").read_text())
    splits["other"] = {"sequences": ["seq0"], "cameras": ["cam00"], "dataset": target}
    (tiny / "splits.json").write_text(json.dumps(splits))
    problems = _errors(tiny, SPLIT_OUTSIDE)
    assert [p.message for p in problems] == [
        "split other: dataset must be a relative path inside this dataset (no absolute path, "
        "no '..')"]  # one message for every refused path: nothing about it leaks
    with pytest.raises(DatasetError):
        load_dataset(tiny)


def test_a_symlink_out_of_the_dataset_is_refused_like_a_path(tiny, tmp_path):
    shutil.copytree(tiny, tmp_path / "elsewhere" / "tiny")
    (tiny / "link").symlink_to(tmp_path / "elsewhere", target_is_directory=True)
    splits = json.loads((tiny / "splits.json").read_text())
    splits["other"] = {"sequences": ["seq0"], "cameras": ["cam00"], "dataset": "link/tiny"}
    (tiny / "splits.json").write_text(json.dumps(splits))
    assert len(_errors(tiny, SPLIT_OUTSIDE)) == 1


def test_a_split_may_borrow_a_dataset_inside(tiny, tiny_root):
    shutil.copytree(tiny_root, tiny / "identities" / "bo")
    splits = json.loads((tiny / "splits.json").read_text())
    splits["cross"] = {"sequences": ["seq0"], "cameras": ["cam00"], "dataset": "identities/bo"}
    (tiny / "splits.json").write_text(json.dumps(splits))
    dataset = load_dataset(tiny)
    assert dataset.source("cross").root == tiny / "identities" / "bo"
    assert len(dataset.views("cross")) == 3


def test_deeply_nested_json_is_a_problem(tiny):
    (tiny / "cameras.json").write_text("[" * 100_000 + "]" * 100_000)
    assert [p.code for p in validate_dataset(tiny) if p.severity == ERROR] == ["invalid_json"]


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner,
                                                                 max_size=4),
    max_leaves=12)
DOCS = ("dataset.json", "cameras.json", "splits.json")


def _validate_bounded(root: Path) -> None:
    with peak_memory() as mem:
        problems = validate_dataset(root)
    assert isinstance(problems, list)
    assert mem["peak"] < 64 * MiB, mem
    try:
        load_dataset(root)
    except (DatasetError, ValueError):  # the validator's error, or a bounded-npz one
        pass


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(doc=st.sampled_from(DOCS), path=st.lists(st.text(max_size=12), min_size=1, max_size=3),
       value=JSON_VALUES)
def test_fuzz_json_documents(tiny_root, tmp_path_factory, doc, path, value):
    root = tmp_path_factory.mktemp("fuzz-json") / "d"
    shutil.copytree(tiny_root, root)
    data = json.loads((root / doc).read_text())
    node = data
    for key in path[:-1]:  # replace (or add) a field somewhere in the document
        child = node.get(key) if isinstance(node, dict) else None
        if not isinstance(child, dict):
            break
        node = child
    if isinstance(node, dict):
        node[path[-1]] = value
    else:
        data = value
    (root / doc).write_text(json.dumps(data))
    _validate_bounded(root)
    shutil.rmtree(root)


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(flips=st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(0, 255)),
                      max_size=8),
       keep=st.floats(0, 1))
def test_fuzz_params_npz_bytes(tiny_root, tmp_path_factory, flips, keep):
    root = tmp_path_factory.mktemp("fuzz-npz") / "d"
    shutil.copytree(tiny_root, root)
    data = bytearray(_params(root).read_bytes())
    for at, value in flips:
        data[int(at * len(data))] = value
    _params(root).write_bytes(bytes(data[:int(keep * len(data))]))
    _validate_bounded(root)
    shutil.rmtree(root)


def test_a_huge_declared_frame_count_costs_what_is_present(tiny):
    meta = json.loads((tiny / "dataset.json").read_text())
    meta["sequences"]["seq0"]["num_frames"] = 10**12  # a few bytes of JSON
    (tiny / "dataset.json").write_text(json.dumps(meta))
    with peak_memory() as mem:
        problems = validate_dataset(tiny)
    assert mem["peak"] < 4 * MiB, mem
    missing = [p for p in problems if p.code == "missing_image" and p.where.camera == "cam00"]
    assert [p.where.frames for p in missing[:2]] == [(3,), (4,)]  # 0..2 are there
    assert len(missing) == 21 and missing[-1].message == (
        f"sequences/seq0/images/cam00: {10**12 - 3 - 20} more of its {10**12} frames are "
        "missing")
