"""Enrollment (avatar_core.enroll) on the studio's one-camera take: a few seconds at small size,
tiny training runs. The real tracker (ONNX), the real trainer, the real package loader."""

from __future__ import annotations

import json
from dataclasses import replace

import cv2
import numpy as np
import pytest
import torch

from avatar_core.enroll import EnrollConfig, EnrollmentRefused
from avatar_core.enroll.pipeline import enroll, prepare, train_prepared
from avatar_core.enroll.selection import select_frames
from avatar_core.enroll.tracking import yaw_deg
from avatar_core.enroll.video import VideoLimits, read_video
from avatar_core.synth.enroll_video import EnrollVideoSpec, film_enroll_video
from avatar_core.track.models import ModelFetchError, fetch_models

pytest.importorskip("onnxruntime")

SMALL = dict(seconds=1.6, fps=10.0, width=320, height=240)  # 16 frames
CONFIG = EnrollConfig(iterations=6, resolution=64, min_frames=8, fit_iterations=20,
                      preflight_frames=4)


@pytest.fixture(scope="module")
def onnx_models():
    try:
        return fetch_models()
    except ModelFetchError as exc:
        pytest.skip(f"cannot fetch the MediaPipe wheel: {exc}")


def _film(tmp_path_factory, name: str, **spec) -> list[np.ndarray]:
    path = tmp_path_factory.mktemp("enroll") / f"{name}.mp4"
    film_enroll_video(path, EnrollVideoSpec(**{**SMALL, **spec}))
    # test takes are shorter than a real one (the probe's min_duration_s)
    video = read_video(path, VideoLimits(min_duration_s=0.0), long_side=SMALL["width"])
    assert video.fps == pytest.approx(spec.get("fps", SMALL["fps"]))
    return list(video.frames)


@pytest.fixture(scope="module")
def take(tmp_path_factory, onnx_models) -> list[np.ndarray]:
    return _film(tmp_path_factory, "take")


def _noise_frame(shape, seed: int) -> np.ndarray:
    """A sharp frame with nobody in it."""
    rng = np.random.default_rng(seed)
    small = rng.integers(40, 220, (shape[0] // 8, shape[1] // 8, 3), dtype=np.uint8)
    return cv2.resize(small, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST)


@pytest.fixture(scope="module")
def doctored(take) -> list[np.ndarray]:
    """The take with one duplicated frame, one blurred frame and two frames of nobody."""
    frames = list(take)
    frames.insert(4, frames[3].copy())                                   # duplicate
    frames.insert(9, cv2.GaussianBlur(frames[8], (0, 0), 4.0))           # blurred
    frames.insert(12, _noise_frame(frames[0].shape, 1))                  # failed track
    frames.insert(14, _noise_frame(frames[0].shape, 2))                  # failed track
    return frames


@pytest.fixture(scope="module")
def prepared(doctored, onnx_models):
    return prepare(doctored, 10.0, config=CONFIG)


# -- the studio take ------------------------------------------------------------------


def test_studio_take_is_a_turning_video(take):
    assert len(take) == 16 and take[0].shape == (240, 320, 3) and take[0].dtype == np.uint8
    # the turn shows: the first frame (facing) and the quarter (turned) differ a lot
    assert np.abs(take[0].astype(int) - take[4].astype(int)).mean() > 5


# -- frame selection ------------------------------------------------------------------


def test_selection_drops_and_counts_blurred_and_duplicated_frames(doctored):
    kept, dropped, quality = select_frames(doctored, CONFIG)
    assert dropped == {"blurred": 1, "duplicate": 1}
    assert 4 not in kept and 9 not in kept and 3 in kept and 8 in kept
    assert len(kept) == len(doctored) - 2 and quality.brightness.shape == (len(doctored),)


def test_prepare_counts_every_frame_once(prepared, doctored):
    c = prepared.counts
    assert c.total == len(doctored)
    assert (c.blurred, c.duplicate) == (1, 1)
    assert c.failed_track >= 2  # the two frames of nobody
    assert c.used + c.failed_track + c.blurred + c.duplicate + c.subsampled == c.total
    assert len(prepared.frames) == len(prepared.params) == len(prepared.masks) == c.used


def test_prepare_fits_one_shape_and_the_turn(prepared):
    assert prepared.betas.shape == (10,) and np.isfinite(prepared.betas).all()
    assert not any("betas" in p for p in prepared.params)  # one shape, not one per frame
    yaws = [yaw_deg(p["global_orient"]) for p in prepared.params]
    assert max(yaws) > 20 and min(yaws) < -20  # turned both ways
    assert prepared.fit_px[1] < prepared.fit_px[0]  # the joint fit reprojects better
    assert prepared.focal_source == "prior+fit" and 100 < prepared.focal_px < 800


def test_subsampling_above_max_frames_is_counted(doctored, onnx_models):
    cfg = replace(CONFIG, min_frames=4, max_frames=8, preflight_frames=0)
    prep = prepare(doctored, 10.0, config=cfg)
    c = prep.counts
    assert c.subsampled == len(doctored) - 2 - 8  # all sharp, new frames past the first 8
    assert c.used + c.failed_track == 8 and c.used >= 6
    assert c.used + c.failed_track + c.blurred + c.duplicate + c.subsampled == c.total


# -- end to end -----------------------------------------------------------------------


def test_enroll_writes_a_loadable_driveable_avatar(prepared, tmp_path):
    from avatar_core.gaussians.loading import load_avatar
    from avatar_core.render.rasterize import rasterize
    from avatar_core.render.types import RenderRequest

    events = []
    result = train_prepared(prepared, tmp_path, config=CONFIG,
                            progress=lambda s, f: events.append((s, f)))
    assert result.package == tmp_path / "avatar" and result.package.is_dir()
    assert result.train["iterations"] == CONFIG.iterations and result.train["fine_tuned"]
    assert {s for s, _ in events} >= {"dataset", "train", "done"}
    doc = json.loads((tmp_path / "enroll.json").read_text())
    assert doc["frames"]["dropped"]["duplicate"] == 1 and doc["package"] == str(result.package)
    loaded = load_avatar(str(result.package))
    assert loaded.package.body.betas == pytest.approx(prepared.betas.tolist(), abs=1e-5)
    posed = loaded.animator.pose({k: v for k, v in prepared.params[0].items()})
    from avatar_core.enroll.dataset import video_camera

    cam = video_camera(64, 48, prepared.focal_px * 64 / 320)
    with torch.no_grad():
        rgb = rasterize(posed.gaussians, cam, RenderRequest(outputs=("rgb", "alpha"))).alpha
    assert float(rgb.mean()) > 0.05  # the avatar is in the video camera's view


def test_switches_reach_the_dataset_and_the_training(prepared, tmp_path):
    from avatar_core.dataset.loader import load_dataset

    off = replace(CONFIG, fine_tune=False, masks=False)
    result = train_prepared(replace(prepared, masks=None), tmp_path / "off", config=off)
    training = json.loads((result.package / "avatar.json").read_text())["training"]
    assert training["fine_tuned"] is False
    assert training["config"]["loss"]["lambda_mask"] == 0.0
    assert not (tmp_path / "off" / "finetuned_params").exists()
    assert load_dataset(tmp_path / "off" / "dataset").meta["masks"] is False
    on = train_prepared(prepared, tmp_path / "on", config=CONFIG)
    training = json.loads((on.package / "avatar.json").read_text())["training"]
    assert training["fine_tuned"] is True and training["config"]["loss"]["lambda_mask"] > 0
    assert (tmp_path / "on" / "finetuned_params" / "take.npz").is_file()
    assert load_dataset(tmp_path / "on" / "dataset").meta["masks"] is True


# -- refusals: each before anything is written ------------------------------------------


def _refused(frames, tmp_path, reason: str, config: EnrollConfig = CONFIG) -> EnrollmentRefused:
    out = tmp_path / "out"
    with pytest.raises(EnrollmentRefused) as info:
        enroll(frames, 10.0, out, config=config)
    assert info.value.reason == reason
    assert info.value.what_to_do and info.value.what_to_do in str(info.value)
    assert not out.exists()  # nothing stored
    return info.value


def test_refuses_a_dark_take(take, tmp_path):
    dark = [(f.astype(np.float32) * 0.08).astype(np.uint8) for f in take]
    assert "light" in _refused(dark, tmp_path, "too_dark").what_to_do


def test_refuses_a_blurred_take(take, tmp_path):
    blurred = [cv2.GaussianBlur(f, (0, 0), 4.0) for f in take]
    _refused(blurred, tmp_path, "too_blurred")


def test_refuses_a_short_take(take, tmp_path):
    _refused(take[:5], tmp_path, "too_short")


def test_refuses_a_take_with_nobody(take, tmp_path, onnx_models):
    empty = [_noise_frame(take[0].shape, s) for s in range(10)]
    _refused(empty, tmp_path, "no_person")


def test_refuses_two_people(tmp_path_factory, tmp_path, onnx_models):
    frames = _film(tmp_path_factory, "two", seconds=1.0, people=1)
    _refused(frames, tmp_path, "two_people")


def test_refuses_a_person_who_never_turns(tmp_path_factory, tmp_path, onnx_models):
    frames = _film(tmp_path_factory, "still", seconds=1.0, yaw_deg=0.0)
    _refused(frames, tmp_path, "never_turns", replace(CONFIG, preflight_frames=0))


def test_refuses_an_unreadable_video(tmp_path):
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"\x00not a video" * 100)
    with pytest.raises(EnrollmentRefused) as info:
        read_video(bad)
    assert info.value.reason in ("corrupt_video", "no_video_stream")


def test_bad_config_is_a_clear_error():
    with pytest.raises(ValueError, match="max_frames"):
        EnrollConfig(min_frames=10, max_frames=5)


def test_cli_reports_a_refusal_and_stores_nothing(take, tmp_path, capsys):
    from avatar_core.cli import main

    path = tmp_path / "dark.mp4"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (320, 240))
    for f in take + take:  # long enough: the dark check is what refuses it
        writer.write((f[..., ::-1].astype(np.float32) * 0.08).astype(np.uint8))
    writer.release()
    assert main(["enroll", str(path), "--out", str(tmp_path / "me")]) == 3
    err = capsys.readouterr().err
    assert "too_dark" in err and "what to do" in err
    assert not (tmp_path / "me").exists()


# -- the training side ----------------------------------------------------------------


def test_mask_loss_is_the_weighted_alpha_error():
    from avatar_core.train.regularizers import mask_loss

    alpha = torch.tensor([[0.0, 1.0], [0.5, 1.0]], requires_grad=True)
    mask = torch.tensor([[0.0, 1.0], [1.0, 0.0]])
    weight = torch.tensor([[1.0, 1.0], [1.0, 0.0]])  # the last pixel is not scored
    loss = mask_loss(alpha, mask, weight)
    assert float(loss) == pytest.approx(0.5 / 3)
    loss.backward()
    assert float(alpha.grad[1, 1]) == 0.0 and float(alpha.grad[1, 0]) < 0


def test_enroll_config_scales_the_schedule_to_the_run():
    from avatar_core.enroll.training import enroll_train_config

    short = enroll_train_config(EnrollConfig(iterations=1000), frames=300)
    assert short.densify.interval == 250 and short.densify.until_iter == 800
    assert short.finetune.schedule == "budget" and short.loss.lambda_mask > 0
    long = enroll_train_config(EnrollConfig(iterations=20_000, masks=False, fine_tune=False),
                               frames=300)
    assert long.densify.interval == 1000 and long.densify.from_iter == 2000
    assert long.loss.lambda_mask == 0 and not long.finetune.enabled
    assert not long.data.crop_to_subject  # no mask, no subject box
