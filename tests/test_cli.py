"""The `telesplat body` commands, end to end."""

import subprocess
import sys

import cv2
import numpy as np

from avatar_core.cli import main


def test_make_synthetic_writes_loadable_files(tmp_path):
    assert main(["body", "make-synthetic", "--out", str(tmp_path / "m"), "--resolution", "0.4",
                 "--identities", "3"]) == 0
    names = {p.name for p in (tmp_path / "m").iterdir()}
    assert {"SMPLX_NEUTRAL.npz", "SMPLX_NEUTRAL.pkl", "FLAME_NEUTRAL.pkl", "MANO_LEFT.pkl",
            "MANO_RIGHT.pkl", "smplx_vert_segmentation.json", "manifest.json"} <= names
    assert len(list((tmp_path / "m" / "identities").iterdir())) == 3


def test_demo_renders_a_strip_of_a_moving_body(synthetic_files, tmp_path):
    out = tmp_path / "demo.png"
    assert main(["body", "demo", "--out", str(out), "--models", str(synthetic_files.root),
                 "--frames", "8", "--size", "96"]) == 0
    strip = cv2.imread(str(out))
    assert strip.shape == (96, 96 * 8, 3)
    frames = strip.reshape(96, 8, 96, 3).transpose(1, 0, 2, 3).astype(float)
    background = np.array([0.96, 0.94, 0.93]) * 255  # BGR of the demo background
    assert all((np.abs(f - background).sum(-1) > 30).mean() > 0.05 for f in frames)  # a body
    assert np.abs(frames[0] - frames[4]).mean() > 1.0  # and it moves


def test_demo_writes_mp4(synthetic_files, tmp_path):
    out = tmp_path / "demo.mp4"
    assert main(["body", "demo", "--out", str(out), "--models", str(synthetic_files.root),
                 "--frames", "3", "--size", "64"]) == 0
    cap = cv2.VideoCapture(str(out))
    assert cap.isOpened() and int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 3


def test_bad_arguments_give_an_error_not_a_traceback(tmp_path):
    result = subprocess.run([sys.executable, "-m", "avatar_core.cli", "body", "demo", "--out",
                             str(tmp_path / "x.gif"), "--models", str(tmp_path / "m"),
                             "--frames", "0"], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and "error" in result.stderr
