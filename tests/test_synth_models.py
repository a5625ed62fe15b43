"""The synthetic model family: formats, determinism, identities, correspondences."""

import json

import numpy as np
import pytest

from avatar_core.body.model_data import load_correspondence
from avatar_core.body.skeleton import SMPLX_PART_NAMES
from avatar_core.synth.model_writer import write_synthetic_models


def test_counts_and_manifest(synthetic_files, smplx_data, flame_data, mano_data):
    manifest = json.loads(synthetic_files.manifest.read_text())
    assert manifest["synthetic"] is True
    assert smplx_data.num_vertices >= 10475
    assert smplx_data.num_joints == 55 and flame_data.num_joints == 5
    assert mano_data["left"].num_joints == mano_data["right"].num_joints == 16
    assert smplx_data.shapedirs.shape[-1] == 10 and smplx_data.exprdirs.shape[-1] == 10
    assert flame_data.shapedirs.shape[-1] == 300 and flame_data.exprdirs.shape[-1] == 100
    assert flame_data.lmk_faces.shape == (51,) and flame_data.dynamic_lmk_faces.shape == (79, 17)
    assert len(manifest["expression_names"]) == 10


def test_segmentation_labels_every_vertex_once(synthetic_files, smplx_data, segmentation):
    assert set(segmentation) <= set(SMPLX_PART_NAMES)
    ids = np.concatenate(list(segmentation.values()))
    assert len(ids) == len(np.unique(ids)) == smplx_data.num_vertices


def test_correspondences_point_at_the_same_geometry(synthetic_files, smplx_data, flame_data,
                                                   mano_data):
    flame_ids = load_correspondence(synthetic_files.flame_correspondence)["flame"]
    assert np.array_equal(smplx_data.v_template[flame_ids], flame_data.v_template)
    hands = load_correspondence(synthetic_files.mano_correspondence)
    for side in ("left", "right"):
        assert np.array_equal(smplx_data.v_template[hands[f"{side}_hand"]],
                              mano_data[side].v_template)
    # MANO left is the mirror image of MANO right, vertex for vertex.
    mirrored = mano_data["right"].v_template * np.array([-1.0, 1.0, 1.0])
    assert np.allclose(mano_data["left"].v_template, mirrored, atol=1e-12)


def test_identities_differ_in_shape_and_appearance(synthetic_files):
    paths = synthetic_files.identities()
    assert len(paths) >= 2
    a, b = (np.load(p) for p in paths[:2])
    assert np.linalg.norm(a["betas"] - b["betas"]) > 1.0
    assert np.abs(a["vertex_colors"] - b["vertex_colors"]).mean() > 0.05
    assert str(a["name"]) != str(b["name"])


@pytest.mark.slow
def test_generation_is_deterministic_for_a_seed(tmp_path):
    one = write_synthetic_models(tmp_path / "a", seed=3, resolution=0.4, num_identities=1)
    two = write_synthetic_models(tmp_path / "b", seed=3, resolution=0.4, num_identities=1)
    other = write_synthetic_models(tmp_path / "c", seed=4, resolution=0.4, num_identities=1)
    with np.load(one.smplx_npz) as x, np.load(two.smplx_npz) as y, np.load(other.smplx_npz) as z:
        for key in x.files:
            assert np.array_equal(x[key], y[key]), key
        assert not np.array_equal(x["v_template"], z["v_template"])
    for name in ("FLAME_NEUTRAL.pkl", "MANO_LEFT.pkl", "smplx_vert_segmentation.json"):
        assert (one.root / name).read_bytes() == (two.root / name).read_bytes()
