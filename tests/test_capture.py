"""The software capture: determinism, masks agreeing with images, splits, and the CLI."""

import hashlib

import numpy as np
import pytest

from avatar_core.body.skeleton import SMPLX_PART_NAMES
from avatar_core.cli import main
from avatar_core.dataset.loader import load_dataset
from avatar_core.dataset.preview import contact_sheet, frame_strip
from avatar_core.synth.actor import Actor
from avatar_core.synth.capture import CaptureSpec, capture, count_views, parse_sequences
from avatar_core.synth.studio import StudioConfig, studio_rig

SMALL = dict(num_cameras=5, resolution=48, max_frames=2, supersample=1, workers=2)


@pytest.fixture(scope="module")
def small_capture(tmp_path_factory, synthetic_files):
    out = tmp_path_factory.mktemp("cap") / "ds"
    spec = CaptureSpec(sequences=(("smile",), ("nod",)), cross_identity=1, **SMALL)
    ticks = []
    capture(out, spec, model_dir=synthetic_files.root, progress=lambda i, n: ticks.append(i))
    return out, spec, ticks


def _digest(root):
    h = hashlib.sha256()
    for p in sorted(root.rglob("*.png")):
        h.update(p.relative_to(root).as_posix().encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def test_capture_is_a_valid_dataset_with_the_paper_splits(small_capture):
    out, spec, ticks = small_capture
    ds = load_dataset(out, validate=True, deep=True)
    assert set(ds.sequences) == {"smile", "nod", "cross-bo-nod"}
    assert all(n == 2 for n in ds.sequences.values())
    assert ticks == list(range(1, count_views(spec) + 1))
    # 4 front + 1 rear: none at azimuth 0; one of the two nearest it (+-25 deg) is held out
    assert ds.splits["novel_view"].cameras == ("cam02",)
    assert "cam02" not in ds.splits["train"].cameras
    assert ds.splits["train"].sequences == ("smile",)
    assert ds.splits["self_reenactment"].sequences == ("nod",)
    assert ds.splits["cross_identity"].extra["identity"] == "bo"
    assert ds.fps == 25.0
    lo, hi = ds.subject_bounds
    assert np.all(hi - lo > 0.3)
    params = ds.params("smile")
    assert params["body_pose"].shape == (2, 21, 3)
    # Simulated trackers: the face lives in the FLAME keys, the body tracker has none.
    assert params["flame_expr"][1].max() > 0  # the smile starts moving by frame 1
    assert not params["expression"].any()
    assert params["mano_right_hand_pose"].shape == (2, 15, 3)
    # The cross-identity sequence carries the other identity's betas.
    assert not np.allclose(ds.params("cross-bo-nod")["betas"], params["betas"])


def test_masks_agree_with_images(small_capture):
    out, _, _ = small_capture
    ds = load_dataset(out)
    for cam in ds.cameras:
        v = ds.view("smile", 1, cam)
        empty = v.alpha == 0
        assert np.all((v.parts == -1) == empty)
        np.testing.assert_allclose(v.rgb[empty], 1.0, atol=1 / 255)  # white backdrop
        assert v.alpha.max() == 1.0
        # Lower-body parts are excluded by the upper-body mask.
        lower = np.isin(v.parts, [SMPLX_PART_NAMES.index(p) for p in ("hips", "leftUpLeg")])
        assert not np.any(v.upper_body_mask & lower)


def test_capture_is_deterministic_for_a_seed(small_capture, tmp_path, synthetic_files):
    out, _, _ = small_capture
    again = tmp_path / "again"
    capture(again, CaptureSpec(sequences=(("smile",), ("nod",)), cross_identity=1, **SMALL),
            model_dir=synthetic_files.root)
    assert _digest(again) == _digest(out)


def test_every_front_camera_sees_the_head_in_the_part_mask(synthetic_files):
    actor = Actor.load(synthetic_files, 0)
    posed = actor.pose({})
    head = SMPLX_PART_NAMES.index("head")
    for cam in studio_rig(96, StudioConfig()):
        view = actor.render(posed, cam.camera, supersample=1)
        assert (view.parts == head).sum() > 60, cam.name


def test_previews(small_capture):
    out, _, _ = small_capture
    ds = load_dataset(out)
    sheet = contact_sheet(ds, "smile", 0, columns=3, size=40)
    assert sheet.shape == (80, 120, 3) and sheet.dtype == np.uint8
    strip = frame_strip(ds, [("smile", 0, "a"), ("nod", 1, "b")], "cam02", size=40)
    assert strip.shape == (40, 80, 3)


def test_bad_specs_are_refused(synthetic_files, tmp_path):
    with pytest.raises(ValueError, match="unknown motion"):
        capture(tmp_path / "x", CaptureSpec(sequences=(("smiel",),), **SMALL),
                model_dir=synthetic_files.root)
    with pytest.raises(ValueError, match="repeat"):
        capture(tmp_path / "y", CaptureSpec(sequences=(("smile",), ("smile",)), **SMALL),
                model_dir=synthetic_files.root)
    with pytest.raises(ValueError, match="unknown held-out camera"):
        capture(tmp_path / "z", CaptureSpec(sequences=(("smile",),), holdout_cameras=("c9",),
                                            **SMALL), model_dir=synthetic_files.root)
    with pytest.raises(ValueError, match="keep one for training"):
        CaptureSpec(sequences=(("smile",), ("nod",)), holdout_sequences=2)
    with pytest.raises(ValueError, match="no motions"):
        parse_sequences(" , ")
    assert parse_sequences("smile+grin, nod") == (("smile", "grin"), ("nod",))


def test_cli_capture(synthetic_files, tmp_path, capsys):
    out = tmp_path / "cli"
    rc = main(["synth", "capture", "--out", str(out), "--cameras", "3", "--resolution", "32",
               "--max-frames", "1", "--motions", "neutral,nod", "--supersample", "1",
               "--models", str(synthetic_files.root)])
    assert rc == 0
    assert "wrote dataset" in capsys.readouterr().out
    assert load_dataset(out, deep=True).sequences.keys() == {"neutral", "nod", "cross-bo-nod"}
    assert main(["dataset", "validate", str(out)]) == 0


def test_cli_previews(small_capture, synthetic_files, tmp_path):
    import cv2

    out, _, _ = small_capture
    assert main(["dataset", "preview", str(out), "--out", str(tmp_path / "s.png"),
                 "--size", "32", "--columns", "5"]) == 0
    assert cv2.imread(str(tmp_path / "s.png")).shape == (32, 160, 3)
    assert main(["synth", "preview", "--out", str(tmp_path / "m.png"), "--motions",
                 "smile,heart", "--size", "40", "--models", str(synthetic_files.root)]) == 0
    assert cv2.imread(str(tmp_path / "m.png")).shape == (40, 80, 3)
