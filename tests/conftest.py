"""Shared fixtures: one family of synthetic model files per test session (per xdist worker)."""

import numpy as np
import pytest
import torch

from avatar_core.body.model_data import load_flame, load_mano, load_smplx
from avatar_core.body.upper_body import load_segmentation
from avatar_core.synth.model_writer import write_synthetic_models


@pytest.fixture(scope="session")
def synthetic_files(tmp_path_factory):
    return write_synthetic_models(tmp_path_factory.mktemp("synthetic"), seed=0)


@pytest.fixture(scope="session")
def smplx_data(synthetic_files):
    return load_smplx(synthetic_files.smplx_npz)


@pytest.fixture(scope="session")
def segmentation(synthetic_files, smplx_data):
    return load_segmentation(synthetic_files.segmentation, smplx_data.num_vertices)


@pytest.fixture(scope="session")
def flame_data(synthetic_files):
    return load_flame(synthetic_files.flame_pkl,
                      static_landmarks=synthetic_files.flame_static_embedding,
                      dynamic_landmarks=synthetic_files.flame_dynamic_embedding)


@pytest.fixture(scope="session")
def mano_data(synthetic_files):
    return {side: load_mano(synthetic_files.mano_pkl(side)) for side in ("left", "right")}


@pytest.fixture(scope="session")
def shared_chromium():
    """The worker's one plain headless Chromium (tests/browser_fixtures.py), started on first
    use."""
    from tests.browser_fixtures import SharedChromium

    shared = SharedChromium()
    try:
        yield shared
    finally:
        shared.close()


def random_smplx_params(batch: int, seed: int, *, scale: float = 0.3, num_betas: int = 10,
                        num_expression: int = 10) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "betas": rng.normal(0, 1, (batch, num_betas)),
        "expression": rng.normal(0, 1, (batch, num_expression)),
        "global_orient": rng.normal(0, scale, (batch, 3)),
        "body_pose": rng.normal(0, scale, (batch, 21, 3)),
        "jaw_pose": rng.normal(0, scale, (batch, 3)),
        "leye_pose": rng.normal(0, scale, (batch, 3)),
        "reye_pose": rng.normal(0, scale, (batch, 3)),
        "left_hand_pose": rng.normal(0, scale, (batch, 15, 3)),
        "right_hand_pose": rng.normal(0, scale, (batch, 15, 3)),
        "transl": rng.normal(0, 0.5, (batch, 3)),
    }


def as_torch(params: dict, dtype=torch.float64) -> dict[str, torch.Tensor]:
    return {k: torch.as_tensor(v, dtype=dtype) for k, v in params.items()}


@pytest.hookimpl(wrapper=True)  # around pytest-xdist's, which reads the groups
def pytest_collection_modifyitems(config, items):
    """A test module without an ``xdist_group`` is a group of its own: under ``-n 2 --dist
    loadgroup`` its module-scoped fixtures (servers, trained avatars, browsers) are built on
    one worker, not on both. Tests marked ``gpu`` need a CUDA device (``make gpu-check`` runs
    them): without one they skip and say so."""
    for item in items:
        if item.get_closest_marker("xdist_group") is None:
            item.add_marker(pytest.mark.xdist_group(item.nodeid.split("::")[0]))
    yield
    check_xdist_groups(config, items)
    gpu_items = [item for item in items if item.get_closest_marker("gpu") is not None]
    if not gpu_items or torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="no CUDA device: gpu tests run with `make gpu-check` on a "
                                   "CUDA machine")
    for item in gpu_items:
        item.add_marker(skip)


GROUP_LOST = pytest.StashKey[str]()


def check_xdist_groups(config, items) -> None:
    """Under ``--dist loadgroup`` an ``xdist_group`` test's id ends in ``@group``: that is how
    the scheduler keeps a group on one worker. pytest 9.2 with pytest-xdist 3.8 loses it
    (pytest-xdist#1386) and the groups spread silently (two Ray clusters, not one): those
    tests then fail, saying why."""
    if not getattr(config.option, "loadgroup", False):  # set on xdist workers only
        return
    for item in items:
        if item.get_closest_marker("xdist_group") is not None and "@" not in item.nodeid:
            item.stash[GROUP_LOST] = (
                f"--dist loadgroup lost this test's xdist_group: pytest {pytest.__version__} "
                "with this pytest-xdist does not group tests (pytest-xdist#1386); install "
                "pytest<9.2 (pyproject.toml's dev extra)")


def pytest_runtest_setup(item):
    if GROUP_LOST in item.stash:
        pytest.fail(item.stash[GROUP_LOST], pytrace=False)
