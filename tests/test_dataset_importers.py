"""Importers: foreign layouts written by the fixtures come back exactly (cameras, params,
images, masks, splits)."""

from __future__ import annotations

import argparse
import dataclasses
import json

import cv2
import numpy as np
import pytest
import torch

from avatar_core.body.models import SMPLXModel
from avatar_core.dataset import load_dataset
from avatar_core.dataset.cli import register
from avatar_core.dataset.importers import import_easymocap, import_vhap
from avatar_core.dataset.importers.easymocap import pelvis_rest, root_to_smplx
from tests.dataset_fixtures import write_easymocap_fixture, write_vhap_fixture


def _points(n: int = 200, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-0.4, 0.4, (n, 3))


def _assert_same_projection(imported, truth) -> None:
    pts = _points()
    uv_a, z_a = imported.camera.project(pts)
    uv_b, z_b = truth.camera.project(pts)
    assert np.all(z_b > 0)
    np.testing.assert_allclose(uv_a, uv_b, rtol=0, atol=1e-9)
    np.testing.assert_allclose(z_a, z_b, rtol=0, atol=1e-9)


def _project_opengl(frame: dict, pts: np.ndarray) -> np.ndarray:
    """The NeRF convention itself: world -> OpenGL camera (z backward, y up) -> pixels."""
    w2c = np.linalg.inv(np.array(frame["transform_matrix"]))
    x = pts @ w2c[:3, :3].T + w2c[:3, 3]
    u = frame["fl_x"] * x[:, 0] / -x[:, 2] + frame["cx"]
    v = frame["fl_y"] * -x[:, 1] / -x[:, 2] + frame["cy"]
    return np.stack([u, v], axis=1)


# -- VHAP / GaussianAvatars ------------------------------------------------------------------

@pytest.mark.parametrize("combined", [False, True], ids=["single", "combined"])
def test_vhap_import_round_trip(tmp_path, combined):
    truth = write_vhap_fixture(tmp_path / "src", combined=combined)
    progress = []
    out = import_vhap(truth.src, tmp_path / "ds", fps=24.0,
                      progress=lambda i, n: progress.append((i, n)))
    ds = load_dataset(out, deep=True)
    assert progress[-1][0] == progress[-1][1] == len(truth.rgb)

    assert list(ds.cameras) == [c.name for c in truth.cameras]
    for cam in truth.cameras:
        _assert_same_projection(ds.cameras[cam.name], cam)
    frame0 = json.loads((truth.src / "transforms_train.json").read_text())["frames"][0]
    cam0 = ds.cameras[str(frame0["camera_id"])].camera
    pts = _points(seed=1)
    np.testing.assert_allclose(cam0.project(pts)[0], _project_opengl(frame0, pts), atol=1e-9)

    assert ds.sequences == {s: len(ts) for s, ts in truth.sequences.items()}
    for seq, steps in truth.sequences.items():
        assert ds.meta["sequences"][seq]["source_frames"] == steps
        params = ds.params(seq)
        assert set(params) == set(truth.flame[seq])
        for key, value in truth.flame[seq].items():
            np.testing.assert_array_equal(params[key], value, err_msg=key)
    assert ds.meta["body_model"] == {"type": "flame", "num_betas": 5, "num_expression": 4,
                                     "source": "vhap"}
    assert ds.meta["subject"]["identity"] == "306" or combined
    for (seq, f, cam), rgb in truth.rgb.items():
        view = ds.view(seq, f, cam)
        np.testing.assert_array_equal(np.round(view.rgb * 255).astype(np.uint8), rgb)
        np.testing.assert_array_equal(np.round(view.alpha * 255).astype(np.uint8),
                                      truth.alpha[(seq, f, cam)])
    assert {n: {"sequences": list(s.sequences), "cameras": list(s.cameras)}
            for n, s in ds.splits.items()} == truth.splits
    assert ds.fps == 24.0


def test_vhap_import_refuses_incomplete_views(tmp_path):
    truth = write_vhap_fixture(tmp_path / "src", combined=False)
    path = truth.src / "transforms_val.json"
    doc = json.loads(path.read_text())
    doc["frames"] = doc["frames"][1:]  # one view of the held-out camera is gone
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="views missing from the source"):
        import_vhap(truth.src, tmp_path / "ds")


# -- EasyMocap --------------------------------------------------------------------------------

@pytest.mark.parametrize("layout", [165, 87])
def test_easymocap_import_round_trip(tmp_path, layout):
    truth = write_easymocap_fixture(tmp_path / "src", layout=layout)
    out = import_easymocap(truth.src, tmp_path / "ds", holdout_cameras=("02",))
    ds = load_dataset(out, deep=True)

    for cam in truth.cameras:
        spec = ds.cameras[cam.name]
        _assert_same_projection(spec, cam)
        # and against OpenCV's own projection of the calibration (pixel centres +0.5)
        pts = _points(seed=2)
        rvec = cv2.Rodrigues(cam.R)[0]
        uv_cv = cv2.projectPoints(pts, rvec, cam.t, truth.K_cv[cam.name], np.zeros(5))[0]
        np.testing.assert_allclose(spec.camera.project(pts)[0], uv_cv[:, 0] + 0.5, atol=1e-6)

    seq = "src"
    assert ds.sequences == {seq: 4}
    assert ds.meta["sequences"][seq]["source_frames"] == truth.frames
    params = ds.params(seq)
    assert set(params) == set(truth.params)
    for key, value in truth.params.items():
        np.testing.assert_allclose(params[key], value, rtol=0, atol=1e-12, err_msg=key)
    bm = ds.meta["body_model"]
    assert bm["root"] == "origin" and bm["source"] == "easymocap"
    assert (bm["hand_pca"], bm["flat_hand_mean"]) == ((None, True) if layout == 165
                                                      else (6, False))
    assert ds.meta["subject"]["person"] == 3
    for i, f in enumerate(truth.frames):
        for cam in truth.cameras:
            view = ds.view(seq, i, cam.name)
            np.testing.assert_array_equal(np.round(view.rgb * 255).astype(np.uint8),
                                          truth.images[(f, cam.name)])
            np.testing.assert_array_equal(np.round(view.alpha * 255).astype(np.uint8),
                                          truth.masks[(f, cam.name)])
    assert ds.splits["train"].cameras == ("01", "03")
    assert ds.splits["novel_view"].cameras == ("02",)
    assert ds.meta["image_format"] == "jpg"


def test_easymocap_undistorts_images_and_reads_sizes_from_them(tmp_path):
    truth = write_easymocap_fixture(tmp_path / "src", distortion=True, with_size=False)
    ds = load_dataset(import_easymocap(truth.src, tmp_path / "ds", image_format="png",
                                       mask_dir=None, sequence="take 1"))
    assert not ds.has_masks and list(ds.sequences) == ["take_1"]
    cam = truth.cameras[1]
    spec = ds.cameras[cam.name]
    assert (spec.width, spec.height) == (40, 30)
    np.testing.assert_array_equal(spec.distortion, truth.dist[cam.name])
    expected = cv2.undistort(truth.images[(10, cam.name)], truth.K_cv[cam.name],
                             truth.dist[cam.name])
    view = ds.view("take_1", 2, cam.name)
    np.testing.assert_array_equal(np.round(view.rgb * 255).astype(np.uint8), expected)
    assert np.abs(expected.astype(int) - truth.images[(10, cam.name)]).mean() > 1  # it moved


@pytest.mark.parametrize("layout", [165, 87])
def test_easymocap_root_conversion_poses_the_same_body(tmp_path, synthetic_files, smplx_data,
                                                       layout):
    """Rh/Th rotate about the world origin; the converted global_orient/transl about the
    pelvis: both put every vertex in the same place."""
    truth = write_easymocap_fixture(tmp_path / "src", layout=layout, num_cameras=2)
    ds = load_dataset(import_easymocap(truth.src, tmp_path / "ds",
                                       smplx_model=synthetic_files.smplx_npz))
    bm = ds.meta["body_model"]
    assert bm["root"] == "smplx"
    model = SMPLXModel(smplx_data, dtype=torch.float64, hand_pca=bm["hand_pca"],
                       flat_hand_mean=bm["flat_hand_mean"])
    for i in range(len(truth.frames)):
        ours = ds.frame_params("src", i)
        batch = {k: torch.as_tensor(np.array(v))[None] for k, v in ours.items()}
        posed = model(batch).vertices[0].numpy()
        rootless = dict(batch, global_orient=torch.zeros(1, 3), transl=torch.zeros(1, 3))
        X = model(rootless).vertices[0].numpy()
        R = cv2.Rodrigues(truth.Rh[i].reshape(3, 1))[0]
        np.testing.assert_allclose(posed, X @ R.T + truth.Th[i], atol=1e-9)
        np.testing.assert_allclose(ours["global_orient"], truth.Rh[i], atol=1e-12)


def test_root_conversion_about_an_offset_pelvis(smplx_data):
    """The synthetic pelvis sits at the origin; SMPL-X's is ~0.35 m below it. Move the model
    there and check the conversion poses every vertex where EasyMocap's convention does."""
    offset = np.array([0.01, -0.35, 0.02])
    data = dataclasses.replace(smplx_data, v_template=smplx_data.v_template + offset,
                               joint_template=smplx_data.joint_template + offset)
    model = SMPLXModel(data, dtype=torch.float64, flat_hand_mean=True)
    rng = np.random.default_rng(5)
    T = 3
    betas, expr = rng.normal(0, 1, (T, 10)), rng.normal(0, 1, (T, 10))
    Rh, Th, root = rng.normal(0, 0.5, (T, 3)), rng.normal(0, 0.2, (T, 3)), np.zeros((T, 3))
    body = rng.normal(0, 0.2, (T, 21, 3))
    orient, transl = root_to_smplx(Rh, Th, root, pelvis_rest(data, betas, expr))
    assert np.abs(transl - Th).max() > 0.05  # the offset matters
    common = {"betas": betas, "expression": expr, "body_pose": body}
    posed = model({**common, "global_orient": orient, "transl": transl}).vertices.numpy()
    X = model(common).vertices.numpy()
    for i in range(T):
        R = cv2.Rodrigues(Rh[i].reshape(3, 1))[0]
        np.testing.assert_allclose(posed[i], X[i] @ R.T + Th[i], atol=1e-9)
    # A non-zero EasyMocap root (poses[:3]) composes with Rh.
    root = rng.normal(0, 0.3, (T, 3))
    orient, transl = root_to_smplx(Rh, Th, root, pelvis_rest(data, betas, expr))
    posed = model({**common, "global_orient": orient, "transl": transl}).vertices.numpy()
    X = model({**common, "global_orient": root}).vertices.numpy()
    for i in range(T):
        R = cv2.Rodrigues(Rh[i].reshape(3, 1))[0]
        np.testing.assert_allclose(posed[i], X[i] @ R.T + Th[i], atol=1e-9)


def test_easymocap_errors_are_clear(tmp_path):
    truth = write_easymocap_fixture(tmp_path / "src")
    smpl = truth.src / "output-smplx" / "smpl"
    with pytest.raises(ValueError, match="person 7 is missing"):
        import_easymocap(truth.src, tmp_path / "a", person=7)
    first = smpl / "000000.json"
    original = json.loads(first.read_text())
    people = json.loads(first.read_text())
    people[-1]["poses"] = [[0.0] * 72]
    first.write_text(json.dumps(people))
    with pytest.raises(ValueError, match="000005.json has 165 poses values, 000000.json 72"):
        import_easymocap(truth.src, tmp_path / "b")
    for path in smpl.glob("*.json"):  # SMPL, not SMPL-X, everywhere
        people = json.loads(path.read_text())
        people[-1]["poses"] = [[0.0] * 72]
        path.write_text(json.dumps(people))
    with pytest.raises(ValueError, match="87 .* 165"):
        import_easymocap(truth.src, tmp_path / "c")
    truth = write_easymocap_fixture(tmp_path / "src2")
    first = truth.src / "output-smplx" / "smpl" / "000000.json"
    original[-1]["poses"] = [[0.3] + original[-1]["poses"][0][1:]]
    first.write_text(json.dumps(original))
    with pytest.raises(ValueError, match="--smplx-model"):
        import_easymocap(truth.src, tmp_path / "d")


def test_cli_imports_easymocap(tmp_path, capsys):
    truth = write_easymocap_fixture(tmp_path / "src", num_cameras=2)
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers(dest="group", required=True))
    args = parser.parse_args(["dataset", "import", "easymocap", str(truth.src), "--out",
                              str(tmp_path / "ds"), "--holdout-cameras", "02", "--fps", "50"])
    assert args.func(args) == 0
    assert "wrote dataset" in capsys.readouterr().out
    ds = load_dataset(tmp_path / "ds")
    assert ds.fps == 50.0 and ds.splits["novel_view"].cameras == ("02",)
