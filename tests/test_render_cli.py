"""`telesplat render`: avatars under motions, to PNG frames or MP4."""

import json

import cv2
import numpy as np
import pytest
import torch

from avatar_core.body.rest_pose import rest_body_pose
from avatar_core.cli import main
from avatar_core.gaussians.animate import synthetic_package
from avatar_core.gaussians.package import save_package
from avatar_core.motion.files import motion_frames
from avatar_core.render.camera import look_at
from avatar_core.render.camera_path import CHEST_DROP_M, cameras_for, framing_target
from avatar_core.render.types import to_uint8

pytest.importorskip("avatar_core.render.rasterize")


def _frames(folder):
    return [cv2.imread(str(p)) for p in sorted(folder.glob("frame_*.png"))]


def test_untrained_synthetic_avatar_renders_under_an_orbit(synthetic_files, tmp_path):
    out = tmp_path / "frames"
    assert main(["render", "synthetic:1", "--motion", "demo", "--frames", "3", "--size", "64",
                 "--models", str(synthetic_files.root), "--out", str(out)]) == 0
    frames = _frames(out)
    assert len(frames) == 3 and frames[0].shape == (64, 64, 3)
    for f in frames:  # a white background with a body on it
        assert (f.astype(int).sum(-1) < 600).mean() > 0.03
    assert np.abs(frames[0].astype(int) - frames[2]).mean() > 1.0  # the orbit moves


def test_package_motion_file_and_camera_file(synthetic_files, tmp_path):
    package, model = synthetic_package(synthetic_files.root)
    pkg = save_package(package, tmp_path / "avatar.zip")
    motion = tmp_path / "motion.json"
    motion.write_text(json.dumps([{"jaw_pose": [0.0, 0, 0]}, {"jaw_pose": [0.4, 0, 0]}]))
    head = model.joint_template[15].numpy()
    cam = look_at(eye=(0.0, head[1], 0.8), target=head, width=48, height=48)
    cam_file = tmp_path / "cam.json"
    cam_file.write_text(json.dumps(cam.to_dict()))
    out = tmp_path / "clip.mp4"
    assert main(["render", str(pkg), "--motion", str(motion), "--camera", str(cam_file),
                 "--size", "48", "--models", str(synthetic_files.root), "--out", str(out)]) == 0
    cap = cv2.VideoCapture(str(out))
    assert cap.isOpened() and int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 2


def test_bad_motion_is_a_clear_error(synthetic_files, tmp_path, capsys):
    assert main(["render", "synthetic", "--motion", "no-such-clip", "--models",
                 str(synthetic_files.root), "--out", str(tmp_path / "x")]) == 2
    assert "neither a built-in clip" in capsys.readouterr().err


def test_npz_motion_file_frames_and_errors(synthetic_files, tmp_path):
    _, model = synthetic_package(synthetic_files.root)
    files = synthetic_files
    path = tmp_path / "motion.npz"
    np.savez(path, jaw_pose=np.zeros((3, 3)), expression=np.ones((3, 10)))
    seq = motion_frames(str(path), files, model, fps=25.0)
    assert len(seq) == 3 and seq[1]["expression"].shape == (10,)
    assert len(motion_frames(str(path), files, model, fps=25.0, frames=2)) == 2
    rest = motion_frames("rest", files, model, fps=25.0, frames=4)
    assert len(rest) == 4 and all(set(f) == {"body_pose"} for f in rest)
    np.testing.assert_array_equal(rest[0]["body_pose"], rest_body_pose())  # not the T-pose
    np.savez(path, jaw_pose=np.zeros((3, 3)), expression=np.ones((2, 10)))
    with pytest.raises(ValueError, match="disagree on the number of frames"):
        motion_frames(str(path), files, model, fps=25.0)


def test_orbit_frames_the_chest_and_frames_are_uint8(synthetic_files):
    _, model = synthetic_package(synthetic_files.root)
    target = framing_target(model.joint_template)
    neck = model.joint_template[12].numpy()
    np.testing.assert_allclose(target, neck - np.array([0.0, CHEST_DROP_M, 0.0]))
    cams = cameras_for("orbit", 3, 32, target)
    for cam in cams:  # every orbit camera looks at the target: it projects to the centre
        x = cam.K @ (cam.R @ target + cam.t)
        np.testing.assert_allclose(x[:2] / x[2], (16.0, 16.0), atol=1e-6)
    img = to_uint8(torch.tensor([[-1.0, 0.2], [1.0, 3.0]]))
    assert img.dtype == np.uint8 and img.tolist() == [[0, 51], [255, 255]]
