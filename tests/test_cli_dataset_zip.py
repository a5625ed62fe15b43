"""`telesplat dataset zip` (its `main`, in process): the archive unpacks through the server's own
archive reader to the same dataset; an incomplete dataset is refused with a clear message.
The default held-out camera is never the front one; `telesplat train` warns for a schedule too
short for a usable avatar."""

from __future__ import annotations

import json
import math
import shutil

import pytest

from avatar_core.cli import main
from avatar_core.dataset.loader import load_dataset
from avatar_core.synth.capture import default_holdout
from avatar_core.synth.studio import StudioConfig, studio_rig
from server.jobs.archive import UploadLimits, extract_archive

from . import test_jobs_support as support
from .cli_run import run_main

capture_dir = support.capture_dir  # the shared session fixture


def test_zip_is_what_the_server_unpacks(capture_dir, tmp_path, capsys):
    out = tmp_path / "up" / "take.zip"
    done = run_main(main, ["dataset", "zip", capture_dir, "--out", out], capsys)
    assert done.returncode == 0, done.stderr
    assert "100%" in done.stderr.replace("\r", "\n")  # the progress bar ran to the end
    assert f"wrote {out}" in done.stdout and "jobs submit --archive" in done.stdout
    root = extract_archive(out, tmp_path / "unpacked", UploadLimits())
    assert root.name == capture_dir.name  # one top-level folder named after the dataset
    ours = sorted(p.relative_to(capture_dir).as_posix() for p in capture_dir.rglob("*")
                  if p.is_file())
    theirs = sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())
    assert theirs == ours
    assert load_dataset(root, validate=True).sequences == load_dataset(capture_dir).sequences


def test_an_incomplete_dataset_is_refused(capture_dir, tmp_path, capsys):
    broken = tmp_path / "broken"
    shutil.copytree(capture_dir, broken)
    image = next(p for p in sorted(broken.rglob("*.png")) if "images" in p.parts)
    image.unlink()
    out = tmp_path / "broken.zip"
    done = run_main(main, ["dataset", "zip", broken, "--out", out], capsys)
    assert done.returncode == 2
    assert "is not a complete dataset" in done.stderr and "dataset validate" in done.stderr
    assert "missing_image" in done.stderr
    assert not out.exists() and not list(tmp_path.glob("*.partial"))


def _azimuth(cam) -> float:
    x, _, z = cam.camera.center  # the studio's target sits on the y axis
    return math.degrees(math.atan2(x, z))


@pytest.mark.parametrize("n", [2, 3, 4, 5, 8, 17])
def test_the_default_holdout_is_never_the_front_camera(n):
    rig = studio_rig(32, StudioConfig(num_cameras=n), jitter=False)
    held = default_holdout(rig)
    assert len(held) == 1
    by_name = {c.name: c for c in rig}
    assert abs(_azimuth(by_name[held[0]])) > 1.0  # never the camera at azimuth 0
    # the front-arc camera nearest azimuth 0 on the right
    right = [_azimuth(c) for c in rig if c.role == "front" and _azimuth(c) > 1e-6]
    assert _azimuth(by_name[held[0]]) == pytest.approx(min(right))


def test_train_warns_when_the_schedule_is_too_short(capture_dir, synthetic_files, tmp_path,
                                                    capsys):
    config = tmp_path / "tiny.json"
    config.write_text(json.dumps({"preset": "test", "iterations": 2, "progress_interval": 1,
                                  "checkpoint_interval": 2}))
    done = run_main(main, ["train", capture_dir, "--out", tmp_path / "out", "--config", config,
                           "--device", "cpu", "--body-models", synthetic_files.root], capsys)
    assert done.returncode == 0, done.stderr
    assert "2 iterations is too few for a usable avatar" in done.stderr
    assert "wrote avatar" in done.stdout
