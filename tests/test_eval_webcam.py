"""The webcam protocol (`telesplat eval --protocol webcam`) end to end on a tiny avatar and a
tiny noisy-tracker capture: the live tracker and fit on the front camera's frames, scored at a
second camera beside the true parameters and the simulated trackers + fusion."""

import json
import math

import numpy as np
import pytest

from avatar_core.body.model_paths import BodyModelFiles
from avatar_core.cli import main
from avatar_core.dataset import load_dataset
from avatar_core.gaussians.animate import AvatarAnimator, synthetic_package
from avatar_core.gaussians.loading import LoadedAvatar
from avatar_core.gaussians.package import save_package
from avatar_core.metrics.webcam import (
    DRIVES,
    METRICS,
    STAGES,
    evaluate_webcam,
    webcam_cameras,
)
from avatar_core.synth.capture import CaptureSpec, capture
from avatar_core.synth.trackers import TrackerNoise
from tests.track_models import needs_models

FRAMES, CAMERAS, SIZE = 3, 5, 96


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory, synthetic_files):
    out = tmp_path_factory.mktemp("webcam") / "ds"
    spec = CaptureSpec(sequences=(("smile",), ("thumbs_up",)), num_cameras=CAMERAS,
                       resolution=SIZE, max_frames=FRAMES, supersample=1,
                       tracker_noise=TrackerNoise(jaw_deg=8.0, body_deg=4.0))
    return capture(out, spec, model_dir=synthetic_files.root)


@pytest.fixture(scope="module")
def avatar(synthetic_files):
    package, model = synthetic_package(synthetic_files.root, 0)
    animator = AvatarAnimator(model, package.avatar, betas=np.asarray(package.body.betas))
    return LoadedAvatar(package, animator, BodyModelFiles(synthetic_files.root))


@pytest.fixture(scope="module")
def result(avatar, dataset_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("webcam_out")
    frames = []
    return evaluate_webcam(avatar, dataset_dir, out_dir=out, max_images=2,
                           on_frame=frames.append), out, frames


@needs_models
def test_the_table_has_three_finite_drives(result):
    r, out, _ = result
    assert list(r.drives) == list(DRIVES)
    for drive, row in r.drives.items():
        assert set(row) == set(METRICS)
        for key in METRICS:
            assert row[key] is not None and math.isfinite(row[key]), (drive, key)
        assert 0 < row["ssim"] <= 1 and row["psnr"] > 5
    # AKD is against the true body: zero for it, not for the noisy trackers' parameters
    assert r.drives["true"]["akd_torso"] == 0.0
    assert r.drives["trackers"]["akd_torso"] > 0.0
    assert r.truth == "true_params.npz" and r.num_frames == FRAMES
    assert r.sequences == ["thumbs_up"]  # the held-out take


@needs_models
def test_latency_budget_and_files(result):
    r, out, _ = result
    assert set(STAGES) <= set(r.latency_ms) and "live path" in r.latency_ms
    for stage, v in r.latency_ms.items():
        assert math.isfinite(v["median"]) and v["p95"] >= v["median"] >= 0, stage
    assert set(r.seen) == {"face", "left_hand", "right_hand", "pose"}
    assert all(0 <= v <= 1 for v in r.seen.values())
    doc = json.loads((out / "webcam.json").read_text())
    assert doc["webcam_camera"] == r.webcam_camera != r.score_camera
    md = (out / "webcam.md").read_text()
    assert "| webcam tracking (live config) |" in md and "| live path |" in md
    assert len(r.images) == 2 and all((out / p).is_file() for p in r.images)


@needs_models
def test_each_scored_frame_reaches_on_frame(result, dataset_dir):
    r, _, frames = result
    assert len(frames) == r.num_frames and len({f.key for f in frames}) == r.num_frames
    ds = load_dataset(dataset_dir)
    for f in frames:
        np.testing.assert_allclose(f.camera.R, ds.cameras[r.webcam_camera].camera.R)
        assert f.webcam["global_orient"].shape == (3,)
        assert np.isfinite(f.webcam["global_orient"]).all()
        assert set(f.truth) >= {"global_orient", "body_pose"}
        assert f.observations.weights.shape == f.observations.pixels.shape[:1]


def test_root_error_axes_are_the_webcams(dataset_dir):
    """bench/webcam_root.py: a root leaned about the webcam's own x axis by 10 deg reads as
    10 deg about x, whatever the webcam's place in the studio."""
    import importlib.util
    import sys
    from pathlib import Path

    from scipy.spatial.transform import Rotation

    path = Path(__file__).resolve().parents[1] / "bench" / "webcam_root.py"
    spec = importlib.util.spec_from_file_location("webcam_root", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    cam = load_dataset(dataset_dir).cameras["cam01"].camera
    truth = {"global_orient": np.array([0.1, -0.3, 0.05]), "body_pose": np.zeros(63)}
    lean = Rotation.from_matrix(cam.R.T @ Rotation.from_euler("x", 10, degrees=True).as_matrix()
                                @ cam.R)
    fit = {**truth, "global_orient": (lean * Rotation.from_rotvec(truth["global_orient"]))
           .as_rotvec()}
    np.testing.assert_allclose(module.root_error_axes(fit, truth, cam), [10, 0, 0], atol=1e-9)
    np.testing.assert_allclose(module.root_error_axes(truth, truth, cam), 0, atol=1e-9)
    # in the webcam's frame as the fit states it (y and z flipped: x keeps its sign) the
    # fitted root is the true one turned 10 deg about x
    before = Rotation.from_rotvec(np.radians(module.root_in_webcam(truth["global_orient"], cam)))
    after = Rotation.from_rotvec(np.radians(module.root_in_webcam(fit["global_orient"], cam)))
    np.testing.assert_allclose(np.degrees((after * before.inv()).as_rotvec()), [10, 0, 0],
                               atol=1e-9)
    # webcam_orient undoes what the evaluation scores the fitted root by
    from avatar_core.metrics.webcam import _world_orient, webcam_orient

    rotvec = np.array([0.2, -0.1, 0.3])
    np.testing.assert_allclose(webcam_orient(_world_orient(rotvec, cam), cam), rotvec,
                               atol=1e-12)


@needs_models
def test_cli_runs_the_webcam_protocol(avatar, dataset_dir, synthetic_files, tmp_path, capsys):
    pkg = save_package(avatar.package, tmp_path / "avatar")
    out = tmp_path / "eval"
    assert main(["eval", str(pkg), str(dataset_dir), "--protocol", "webcam", "--out", str(out),
                 "--body-models", str(synthetic_files.root), "--max-views", "2"]) == 0
    assert json.loads((out / "webcam.json").read_text())["num_frames"] == 2
    assert "| true parameters |" in capsys.readouterr().out


def test_cameras_default_and_refusals(dataset_dir):
    ds = load_dataset(dataset_dir)
    webcam, score = webcam_cameras(ds)
    assert webcam != score and ds.cameras[webcam].role == "front"
    assert webcam_cameras(ds, score="cam00")[1] == "cam00"
    with pytest.raises(ValueError, match="unknown camera"):
        webcam_cameras(ds, webcam="nope")
    with pytest.raises(ValueError, match="differ"):
        webcam_cameras(ds, webcam="cam01", score="cam01")


def test_bad_arguments_fail_before_any_work(avatar, dataset_dir):
    for kw in ({"frame_stride": 0}, {"max_frames": 0}, {"max_images": -1}):
        with pytest.raises(ValueError, match="at least 1"):
            evaluate_webcam(avatar, dataset_dir, **kw)


def test_the_fit_flags_change_the_live_fit_or_drop_its_arm_cues():
    """`eval --protocol webcam` fits as the live path does (None: its own config); the flags
    change that fit, and --no-arm-cues gives the 2D fit the cues were measured against."""
    import argparse

    from avatar_core.cli import webcam_fit_config
    from avatar_core.track.fit.sequence import ARM_CUES, SequenceFitConfig, live_config

    def config(**flags):
        return webcam_fit_config(argparse.Namespace(**{
            "embedding": None, "world_weight": 0.0, "image_z_weight": 0.0,
            "no_arm_cues": False, **flags}))

    assert config() is None
    weighted = config(world_weight=2.0)
    assert weighted.world_weight == 2.0
    assert weighted.world_direction_weight == ARM_CUES["world_direction_weight"]
    assert config(no_arm_cues=True) == SequenceFitConfig().fit != live_config().fit
    assert config(no_arm_cues=True, image_z_weight=0.1).world_direction_weight == 0.0
