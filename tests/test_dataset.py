"""Dataset Format v1: writer -> loader round trip, validation of every corruption, threads."""

from __future__ import annotations

import argparse
import json
import os
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from avatar_core.dataset import (
    CameraSpec,
    DatasetError,
    DatasetWriter,
    load_dataset,
    validate_dataset,
)
from avatar_core.dataset.cli import register
from avatar_core.dataset.format import view_path
from avatar_core.dataset.problems import ERROR, WARNING
from avatar_core.dataset.validate import box_visible
from avatar_core.render.camera import look_at
from tests.dataset_fixtures import BOX, ring_cameras, write_tiny_dataset


@pytest.fixture()
def tiny(tmp_path):
    return write_tiny_dataset(tmp_path / "ds")


def _codes(problems, severity=ERROR):
    return sorted({p.code for p in problems if p.severity == severity})


# -- round trip -----------------------------------------------------------------------------

def test_writer_loader_round_trip(tiny):
    assert validate_dataset(tiny.root) == []
    assert validate_dataset(tiny.root, deep=True) == []
    ds = load_dataset(tiny.root, deep=True)
    assert list(ds.cameras.values()) == tiny.cameras  # exact: K, R, t, size, role
    assert ds.sequences == {"seq0": 3}
    assert ds.has_masks and ds.has_parts and ds.meta["synthetic"] is True
    np.testing.assert_array_equal(ds.subject_bounds, BOX)
    assert ds.splits["novel_view"].cameras == ("cam01",)
    params = ds.params("seq0")
    for key, value in tiny.params["seq0"].items():
        np.testing.assert_array_equal(params[key], value)
    for (seq, f, cam), rgb in tiny.rgb.items():
        view = ds.view(seq, f, cam)
        assert view.rgb.dtype == np.float32 and view.rgb.shape == (24, 32, 3)
        np.testing.assert_array_equal(view.rgb, rgb.astype(np.float32) / 255.0)
        np.testing.assert_array_equal(view.alpha, tiny.alpha[(seq, f, cam)] / np.float32(255))
        parts = tiny.parts[(seq, f, cam)].astype(np.int16) - 1
        np.testing.assert_array_equal(view.parts, parts)
        assert view.parts.dtype == np.int16 and view.parts.min() == -1
        upper = np.isin(parts, ds.upper_body_ids)
        np.testing.assert_array_equal(view.upper_body_mask, upper)
        assert 0 < upper.sum() < (parts >= 0).sum()  # both upper and lower parts appear
        assert view.camera == tiny.cameras[int(cam[-2:])].camera
        np.testing.assert_array_equal(view.params["body_pose"],
                                      tiny.params[seq]["body_pose"][f])
        np.testing.assert_array_equal(view.params["betas"], tiny.params[seq]["betas"])
    fp = ds.frame_params("seq0", 2)
    assert fp["betas"].shape == (10,) and fp["body_pose"].shape == (21, 3)
    assert ds.views("train") == [("seq0", f, "cam00") for f in range(3)]
    assert ds.views("novel_view")[1] == ("seq0", 1, "cam01")


def test_dataset_without_masks_or_parts_and_jpeg(tmp_path):
    w = _writer(tmp_path / "j", image_format="jpg", subject_bounds=BOX)
    rgb = np.zeros((24, 32, 3), np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 200, 60, np.arange(32)[None] * 4  # R, G, B
    w.write_view("s", 0, "cam00", rgb)
    w.write_view("s", 0, "cam01", rgb)
    w.write_params("s", {"transl": np.zeros((1, 3))})
    w.close()
    ds = load_dataset(tmp_path / "j", deep=True)
    view = ds.view("s", 0, "cam00")
    assert view.alpha is None and view.parts is None and view.upper_body_mask is None
    assert np.abs(view.rgb * 255 - rgb).max() < 8  # lossy, but channels in RGB order
    assert not (tmp_path / "j" / "sequences" / "s" / "masks").exists()


def test_loader_names_bad_requests(tiny):
    ds = load_dataset(tiny.root)
    with pytest.raises(KeyError, match="cam07"):
        ds.view("seq0", 0, "cam07")
    with pytest.raises(IndexError, match="frame 3"):
        ds.view("seq0", 3, "cam00")
    with pytest.raises(KeyError, match="nope"):
        ds.params("nope")
    with pytest.raises(KeyError, match="test"):
        ds.views("test")


def test_camera_spec_json_round_trip_and_checks():
    spec = ring_cameras(3, 64, 48, seed=3)[2]
    spec = CameraSpec(spec.name, spec.K, spec.R, spec.t, 64, 48, [0.1, -0.01, 0, 0, 0.001],
                      "rear")
    back = CameraSpec.from_dict(json.loads(json.dumps(spec.to_dict())))
    assert back == spec and back.role == "rear"
    np.testing.assert_array_equal(back.distortion, [0.1, -0.01, 0, 0, 0.001])
    with pytest.raises(ValueError, match="orthonormal"):
        CameraSpec("c", spec.K, spec.R * 1.1, spec.t, 64, 48)
    with pytest.raises(ValueError, match="name"):
        CameraSpec("a/b", spec.K, spec.R, spec.t, 64, 48)
    with pytest.raises(ValueError, match="distortion"):
        CameraSpec("c", spec.K, spec.R, spec.t, 64, 48, [0.1, 0.2])


def test_frustum_check_is_exact_for_boxes_around_and_behind():
    cam = CameraSpec.from_camera("c", look_at((0, 0, 2), (0, 0, 0), width=32, height=24))
    box = np.array(BOX)
    assert box_visible(cam, box)
    assert not box_visible(cam, box + [0, 0, 5])            # behind the camera
    assert not box_visible(cam, box + [3, 0, 0])            # off to the side
    assert box_visible(cam, np.array([[-9, -9, -9], [9, 9, 1]]))  # corners all outside
    assert box_visible(cam, np.array([[-9, -9, -9], [9, 9, 9]]))  # camera inside the box


# -- the writer refuses bad input ----------------------------------------------------------

def _writer(root: Path, **kw) -> DatasetWriter:
    args = dict(name="w", fps=30, cameras=ring_cameras(2, 32, 24), part_names=["a", "b"],
                upper_body_parts=["a"], subject={"identity": "x"},
                body_model={"type": "smplx", "num_betas": 10, "num_expression": 10,
                            "source": "t"})
    args.update(kw)
    return DatasetWriter(root, **args)


def test_writer_validates_its_input(tmp_path):
    w = _writer(tmp_path / "w")
    rgb = np.zeros((24, 32, 3), np.uint8)
    with pytest.raises(ValueError, match=r"shape \[24, 32, 3\]"):
        w.write_view("s", 0, "cam00", np.zeros((32, 24, 3), np.uint8))
    with pytest.raises(ValueError, match="uint8"):
        w.write_view("s", 0, "cam00", rgb.astype(np.float32))
    with pytest.raises(ValueError, match="unknown camera"):
        w.write_view("s", 0, "camX", rgb)
    with pytest.raises(ValueError, match="labels are 0..2"):
        w.write_view("s", 0, "cam00", rgb, None, np.full((24, 32), 3, np.uint8))
    with pytest.raises(ValueError, match="alpha must have shape"):
        w.write_view("s", 0, "cam00", rgb, np.zeros((24, 31), np.uint8))
    with pytest.raises(ValueError, match="sequence name"):
        w.write_view("../s", 0, "cam00", rgb)
    w.write_view("s", 0, "cam00", rgb)
    with pytest.raises(ValueError, match="already written"):
        w.write_view("s", 0, "cam00", rgb)
    with pytest.raises(ValueError, match="NaN"):
        w.write_params("s", {"transl": np.array([[0, np.nan, 0]])})
    with pytest.raises(ValueError, match="body_pose has shape"):
        w.write_params("s", {"body_pose": np.zeros((1, 20, 3))})
    with pytest.raises(ValueError, match="declares 10"):
        w.write_params("s", {"betas": np.zeros(11), "transl": np.zeros((1, 3))})
    with pytest.raises(ValueError, match="unknown key"):
        w.write_params("s", {"transl": np.zeros((1, 3)), "smile": np.zeros((1, 3))})
    with pytest.raises(ValueError, match="unknown camera"):
        w.write_splits({"train": {"sequences": ["s"], "cameras": ["cam09"]}})
    with pytest.raises(ValueError, match="upper_body_parts"):
        _writer(tmp_path / "v", upper_body_parts=["c"])
    with pytest.raises(ValueError, match="fps"):
        _writer(tmp_path / "v", fps=0)


def test_close_lists_every_missing_piece_and_keeps_dataset_json_unwritten(tmp_path):
    w = _writer(tmp_path / "w")
    rgb = np.zeros((24, 32, 3), np.uint8)
    w.write_view("s", 0, "cam00", rgb)
    w.write_view("s", 1, "cam01", rgb)
    w.write_params("s", {"transl": np.zeros((2, 3))})
    with pytest.raises(DatasetError) as info:
        w.close()
    missing = {(p.where.camera, p.where.frame) for p in info.value.problems
               if p.code == "missing_image"}
    assert missing == {("cam01", 0), ("cam00", 1)}
    assert not (tmp_path / "w" / "dataset.json").exists()  # recognisably unfinished
    with pytest.raises(DatasetError, match="missing_dataset_json"):
        load_dataset(tmp_path / "w")


def test_views_written_from_two_threads(tmp_path):
    cams = ring_cameras(2, 32, 24)
    w = _writer(tmp_path / "w", cameras=cams, subject_bounds=BOX)
    rng = np.random.default_rng(1)
    frames = 12
    images = {(f, c.name): rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
              for f in range(frames) for c in cams}
    full = np.full((24, 32), 255, np.uint8)  # masks for every view, or for none
    barrier = threading.Barrier(2)
    errors = []

    def worker(cam: str) -> None:
        try:
            barrier.wait(timeout=10)
            for f in range(frames):
                w.write_view("s", f, cam, images[(f, cam)], full)
        except Exception as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=worker, args=(c.name,)) for c in cams]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not errors
    # The same view from two threads at once: exactly one wins.
    outcomes = []

    def racer() -> None:
        barrier.wait(timeout=10)
        try:
            w.write_view("s2", 0, "cam00", images[(0, "cam00")], full)
            outcomes.append("ok")
        except ValueError:
            outcomes.append("refused")

    racers = [threading.Thread(target=racer) for _ in range(2)]
    for t in racers:
        t.start()
    for t in racers:
        t.join(timeout=60)
    assert sorted(outcomes) == ["ok", "refused"]
    w.write_view("s2", 0, "cam01", images[(0, "cam01")], full)
    w.write_params("s", {"transl": np.zeros((frames, 3))})
    w.write_params("s2", {"transl": np.zeros((1, 3))})
    w.close()
    ds = load_dataset(tmp_path / "w", deep=True)
    for (f, cam), img in images.items():
        np.testing.assert_array_equal(np.round(ds.view("s", f, cam).rgb * 255), img)
    assert not [p for p in (tmp_path / "w").rglob("*.tmp")]


# -- every corruption is caught, with its code and location --------------------------------

def _edit_json(path: Path, edit) -> None:
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))


def _edit_params(root: Path, edit) -> None:
    path = root / "sequences" / "seq0" / "params.npz"
    with np.load(path) as npz:
        params = {k: npz[k] for k in npz.files}
    edit(params)
    np.savez(path, **params)


def _camera(root: Path, name: str, edit) -> None:
    def apply(doc):
        edit(next(c for c in doc["cameras"] if c["name"] == name))
    _edit_json(root / "cameras.json", apply)


def _look_away(cam: dict) -> None:
    away = look_at((0, 0, 2), (0, 0, 5), width=32, height=24)
    cam["R"], cam["t"] = away.R.tolist(), away.t.tolist()


def _rewrite_png(root: Path, kind: str, cam: str, frame: int, img: np.ndarray) -> None:
    cv2.imwrite(str(view_path(root, "seq0", kind, cam, frame, "png")), img)


CORRUPTIONS = {
    "delete a frame": (
        lambda r: view_path(r, "seq0", "images", "cam01", 1, "png").unlink(),
        "missing_image", dict(sequence="seq0", camera="cam01", frames=(1,))),
    "delete a mask": (
        lambda r: view_path(r, "seq0", "masks", "cam00", 0, "png").unlink(),
        "missing_mask", dict(sequence="seq0", camera="cam00", frames=(0,))),
    "delete a part map": (
        lambda r: view_path(r, "seq0", "parts", "cam00", 2, "png").unlink(),
        "missing_parts", dict(sequence="seq0", camera="cam00", frames=(2,))),
    "resize an image": (
        lambda r: _rewrite_png(r, "images", "cam00", 2, np.zeros((12, 16, 3), np.uint8)),
        "image_size_mismatch", dict(sequence="seq0", camera="cam00", frames=(2,))),
    "resize a mask": (
        lambda r: _rewrite_png(r, "masks", "cam01", 0, np.zeros((12, 16), np.uint8)),
        "mask_size_mismatch", dict(sequence="seq0", camera="cam01", frames=(0,))),
    "grey image": (
        lambda r: _rewrite_png(r, "images", "cam01", 0, np.zeros((24, 32), np.uint8)),
        "bad_file_format", dict(sequence="seq0", camera="cam01", frames=(0,))),
    "truncated image": (
        lambda r: view_path(r, "seq0", "images", "cam01", 2, "png").write_bytes(b"\x89PNG"),
        "unreadable_file", dict(sequence="seq0", camera="cam01", frames=(2,))),
    "NaN in params": (
        lambda r: _edit_params(r, lambda p: p["body_pose"].__setitem__((1, 3, 0), np.nan)),
        "params_nonfinite", dict(sequence="seq0", key="body_pose", frames=(1,))),
    "shrink the params frame count": (
        lambda r: _edit_params(r, lambda p: p.__setitem__("transl", p["transl"][:2])),
        "params_frame_count", dict(sequence="seq0", key="transl")),
    "wrong params shape": (
        lambda r: _edit_params(r, lambda p: p.__setitem__("jaw_pose", np.zeros((3, 4)))),
        "params_bad_shape", dict(sequence="seq0", key="jaw_pose")),
    "params missing": (
        lambda r: (r / "sequences" / "seq0" / "params.npz").unlink(),
        "params_missing", dict(sequence="seq0")),
    "camera looks away": (
        lambda r: _camera(r, "cam01", _look_away),
        "camera_sees_nothing", dict(camera="cam01")),
    "non-rotation R": (
        lambda r: _camera(r, "cam00", lambda c: c.__setitem__("R", np.diag([1, 1, -1.0])
                                                              .tolist())),
        "camera_bad_rotation", dict(camera="cam00")),
    "negative focal length": (
        lambda r: _camera(r, "cam00", lambda c: c["K"][0].__setitem__(0, -5.0)),
        "camera_bad_intrinsics", dict(camera="cam00")),
    "zero width": (
        lambda r: _camera(r, "cam01", lambda c: c.__setitem__("width", 0)),
        "camera_bad_size", dict(camera="cam01")),
    "NaN translation": (
        lambda r: _camera(r, "cam00", lambda c: c["t"].__setitem__(1, float("nan"))),
        "camera_nonfinite", dict(camera="cam00")),
    "unknown split camera": (
        lambda r: _edit_json(r / "splits.json",
                             lambda d: d["train"]["cameras"].append("cam99")),
        "split_unknown_camera", dict(camera="cam99", key="train")),
    "unknown split sequence": (
        lambda r: _edit_json(r / "splits.json",
                             lambda d: d["novel_view"]["sequences"].append("seq9")),
        "split_unknown_sequence", dict(sequence="seq9", key="novel_view")),
    "newer version": (
        lambda r: _edit_json(r / "dataset.json", lambda d: d.__setitem__("version", 2)),
        "newer_version", dict(key="version")),
    "unknown format": (
        lambda r: _edit_json(r / "dataset.json", lambda d: d.__setitem__("format", "nerf")),
        "unknown_format", dict(key="format")),
    "missing dataset.json": (
        lambda r: (r / "dataset.json").unlink(), "missing_dataset_json", {}),
    "missing cameras.json": (
        lambda r: (r / "cameras.json").unlink(), "missing_cameras_json", {}),
    "bad fps": (
        lambda r: _edit_json(r / "dataset.json", lambda d: d.__setitem__("fps", -1)),
        "bad_metadata", dict(key="fps")),
}


@pytest.mark.parametrize("name", list(CORRUPTIONS))
def test_each_corruption_is_caught_with_its_location(tiny, name):
    corrupt, code, where = CORRUPTIONS[name]
    corrupt(tiny.root)
    problems = validate_dataset(tiny.root)
    hits = [p for p in problems if p.code == code]
    assert hits, f"{name}: expected {code}, got {[str(p) for p in problems]}"
    assert all(p.severity == ERROR for p in hits)
    assert any(all(getattr(p.where, k) == v for k, v in where.items()) for p in hits), \
        [str(p) for p in hits]
    with pytest.raises(DatasetError, match=code):
        load_dataset(tiny.root)


def test_deep_validation_decodes_part_values_and_empty_masks(tiny):
    _rewrite_png(tiny.root, "parts", "cam00", 1, np.full((24, 32), 200, np.uint8))
    for f in range(3):
        _rewrite_png(tiny.root, "masks", "cam01", f, np.zeros((24, 32), np.uint8))
    assert validate_dataset(tiny.root) == []  # headers are fine
    problems = validate_dataset(tiny.root, deep=True)
    assert _codes(problems) == ["camera_masks_empty", "parts_bad_value"]
    bad = next(p for p in problems if p.code == "parts_bad_value")
    assert (bad.where.sequence, bad.where.camera, bad.where.frame) == ("seq0", "cam00", 1)
    assert next(p for p in problems if p.code == "camera_masks_empty").where.camera == "cam01"


def test_load_without_validation_reads_what_it_can(tiny):
    CORRUPTIONS["NaN in params"][0](tiny.root)
    CORRUPTIONS["delete a frame"][0](tiny.root)
    ds = load_dataset(tiny.root, validate=False)
    assert np.isnan(ds.frame_params("seq0", 1)["body_pose"][3, 0])
    assert ds.view("seq0", 0, "cam01").rgb.shape == (24, 32, 3)
    with pytest.raises(FileNotFoundError, match="00001.png"):
        ds.view("seq0", 1, "cam01")


def test_extra_files_are_warnings(tiny):
    extra = view_path(tiny.root, "seq0", "images", "cam00", 7, "png")
    extra.write_bytes(view_path(tiny.root, "seq0", "images", "cam00", 0, "png").read_bytes())
    (tiny.root / "sequences" / "seq5").mkdir()
    problems = validate_dataset(tiny.root)
    assert _codes(problems) == [] and _codes(problems, WARNING) == ["extra_file"]
    assert {p.where.path for p in problems} == {"sequences/seq0/images/cam00/00007.png",
                                                "sequences/seq5"}
    load_dataset(tiny.root)  # warnings do not stop loading


def test_all_problems_are_reported_together(tiny):
    picked = ["delete a frame", "resize an image", "NaN in params", "camera looks away",
              "unknown split camera", "negative focal length"]
    for name in picked:
        CORRUPTIONS[name][0](tiny.root)
    with pytest.raises(DatasetError) as info:
        load_dataset(tiny.root)
    codes = {p.code for p in info.value.problems}
    assert {CORRUPTIONS[n][1] for n in picked} <= codes
    assert "missing_image" in str(info.value) and "params_nonfinite" in str(info.value)


def test_shallow_validation_reads_headers_and_decodes_nothing(tmp_path, monkeypatch):
    """17 cameras x 100 frames: shallow validation reads each file's header and decodes no
    image (what keeps it quick; `deep=True` decodes)."""
    from avatar_core.dataset import validate_files

    headers, decodes = [], []

    def counted(fn, calls):
        def wrapper(path, *args, **kwargs):
            calls.append(path)
            return fn(path, *args, **kwargs)
        return wrapper

    monkeypatch.setattr(validate_files, "read_header",
                        counted(validate_files.read_header, headers))
    for name in ("decode_rgb", "decode_gray"):
        monkeypatch.setattr(validate_files, name, counted(getattr(validate_files, name),
                                                          decodes))
    tiny = write_tiny_dataset(tmp_path / "big", num_cameras=17, frames=1, width=16, height=12)
    root = tiny.root
    for kind in ("images", "masks", "parts"):
        for cam in tiny.cameras:
            first = view_path(root, "seq0", kind, cam.name, 0, "png")
            for f in range(1, 100):
                os.link(first, view_path(root, "seq0", kind, cam.name, f, "png"))
    _edit_params(root, lambda p: p.update({k: np.repeat(v, 100, axis=0) for k, v in p.items()
                                           if k != "betas"}))
    _edit_json(root / "dataset.json", lambda d: d["sequences"]["seq0"].update(num_frames=100))
    problems = validate_dataset(root)
    assert problems == []
    assert decodes == []
    files = 3 * len(tiny.cameras) * 100
    assert len(set(headers)) == files
    # The first frame of each camera and kind is read a second time (measured: 5151 reads).
    assert len(headers) <= files + 3 * len(tiny.cameras)


# -- command line ---------------------------------------------------------------------------

def _cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers(dest="group", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_validate_prints_every_problem(tiny, capsys):
    assert _cli(["dataset", "validate", str(tiny.root), "--deep"]) == 0
    assert "0 error(s)" in capsys.readouterr().out
    CORRUPTIONS["delete a frame"][0](tiny.root)
    CORRUPTIONS["NaN in params"][0](tiny.root)
    assert _cli(["dataset", "validate", str(tiny.root)]) == 1
    out = capsys.readouterr().out
    assert "missing_image" in out and "camera=cam01" in out and "frame=1" in out
    assert "params_nonfinite" in out and "key=body_pose" in out
