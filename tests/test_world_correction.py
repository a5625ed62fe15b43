"""The learned correction of BlazePose's world arm bones (`track.fit.world_correction`)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from avatar_core.track.fit import correspondence as cor
from avatar_core.track.fit import world_correction as wc
from avatar_core.track.fit.observations import empty_observations
from avatar_core.track.fit.world_cues import ARM_BONES, WORLD_TO_CAMERA

SIZE = (640, 480)


def body_points(rng: np.random.Generator) -> np.ndarray:
    """[33, 3] an upper body in the fit's camera frame (x right, y up, z toward the camera,
    m), arms posed at random; NaN on rows the correction does not read."""
    pts = np.full((33, 3), np.nan)
    pts[0] = [0.0, 0.25, -1.9]
    pts[11], pts[12] = [0.18, 0.0, -2.0], [-0.18, 0.0, -2.0]
    pts[23], pts[24] = [0.1, -0.5, -2.0], [-0.1, -0.5, -2.0]
    for a, b in ARM_BONES:
        d = rng.normal(size=3) + [0.0, -1.0, 0.0]
        pts[b] = pts[a] + 0.27 * d / np.linalg.norm(d)
    return pts


def observe(points: np.ndarray, focal: float = 500.0):
    """Observations of `points`: world in BlazePose's axes, pinhole image points."""
    obs = empty_observations(SIZE)
    rows = np.isfinite(points).all(1)
    px = np.full((33, 2), 0.0)
    px[rows, 0] = SIZE[0] / 2 + focal * points[rows, 0] / -points[rows, 2]
    px[rows, 1] = SIZE[1] / 2 - focal * points[rows, 1] / -points[rows, 2]
    obs.pixels[cor.POSE_SLICE] = px
    obs.weights[cor.POSE_SLICE] = rows.astype(float)
    obs.world = points * WORLD_TO_CAMERA
    return obs


def test_solve_recovers_a_known_pose_dependent_residual():
    """Targets that are a linear function of the features are learned back: held-out
    frames get the residual within a few percent."""
    rng = np.random.default_rng(0)
    frames = [observe(body_points(rng)) for _ in range(400)]
    truth_map = rng.normal(scale=0.02, size=(wc.NUM_FEATURES, len(ARM_BONES) * 3))
    x = np.stack([wc.training_pair(o, np.nan_to_num(o.world * WORLD_TO_CAMERA))[0]
                  for o in frames])
    y = x @ truth_map
    mask = np.ones((len(x), len(ARM_BONES)), bool)
    corr = wc.solve(x[:300], y[:300], mask[:300], ridge=1e-6)
    xs = np.concatenate([(x[300:] - corr.mean) / corr.scale, np.ones((100, 1))], 1)
    pred = np.concatenate([xs @ corr.weights[b] for b in range(len(ARM_BONES))], 1)
    assert np.abs(pred - y[300:]).max() < 0.05 * np.abs(y[300:]).max()


def test_a_zero_correction_leaves_the_world_points_alone():
    rng = np.random.default_rng(1)
    obs = observe(body_points(rng))
    zero = wc.WorldCorrection(np.zeros(wc.NUM_FEATURES), np.ones(wc.NUM_FEATURES),
                              np.zeros((len(ARM_BONES), wc.NUM_FEATURES + 1, 3)))
    np.testing.assert_allclose(wc.correct_world(obs, zero), obs.world, atol=1e-12)


def test_the_correction_moves_elbows_and_wrists_only_and_keeps_bone_lengths():
    rng = np.random.default_rng(2)
    obs = observe(body_points(rng))
    weights = np.zeros((len(ARM_BONES), wc.NUM_FEATURES + 1, 3))
    weights[:, -1] = [0.3, 0.2, -0.4]  # the same residual in every frame
    corr = wc.WorldCorrection(np.zeros(wc.NUM_FEATURES), np.ones(wc.NUM_FEATURES), weights)
    out = wc.correct_world(obs, corr)
    moved = ~np.isclose(out, obs.world).all(1) & np.isfinite(obs.world).all(1)
    assert set(np.flatnonzero(moved)) == {13, 14, 15, 16}
    before, after = (wc.bone_directions(w * WORLD_TO_CAMERA)[1] for w in (obs.world, out))
    np.testing.assert_allclose(after, before, rtol=1e-9)
    assert np.isnan(out[~np.isfinite(obs.world).all(1)]).all()


def test_the_mirror_image_is_a_valid_training_pair():
    """A frame and its mirror give features of the same size and the bones swapped."""
    rng = np.random.default_rng(3)
    pts = body_points(rng)
    obs = observe(pts)
    x, y, m = wc.training_pair(obs, pts, mirror=False)
    xm, ym, mm = wc.training_pair(obs, pts, mirror=True)
    assert x.shape == xm.shape == (wc.NUM_FEATURES,) and m.all() and mm.all()
    np.testing.assert_allclose(y, 0.0, atol=1e-12)  # BlazePose exact here: no residual
    np.testing.assert_allclose(ym, 0.0, atol=1e-12)
    assert not np.allclose(x, xm)


@pytest.mark.parametrize("hard", ["no_world", "no_shoulders", "nan_elbow", "inf_wrist",
                                  "zero_bone", "empty"])
def test_hard_frames_stay_finite_or_untouched(hard):
    rng = np.random.default_rng(4)
    pts = body_points(rng)
    obs = observe(pts)
    if hard == "no_world":
        obs.world = None
    elif hard == "no_shoulders":
        obs.world[11] = np.nan
    elif hard == "nan_elbow":
        obs.world[13] = np.nan
    elif hard == "inf_wrist":
        obs.world[16] = np.inf
    elif hard == "zero_bone":
        obs.world[15] = obs.world[13]
    elif hard == "empty":
        obs = empty_observations(SIZE)
        obs.world = np.full((33, 3), np.nan)
    corr = wc.WorldCorrection(np.zeros(wc.NUM_FEATURES), np.ones(wc.NUM_FEATURES),
                              np.full((len(ARM_BONES), wc.NUM_FEATURES + 1, 3), 0.1))
    out = wc.correct_world(obs, corr)
    if obs.world is None:
        assert out is None
        return
    given = np.isfinite(obs.world).all(1)
    assert np.isfinite(out[given]).all()
    x, y, m = wc.training_pair(obs, pts)
    assert np.isfinite(x).all() and np.isfinite(y).all()
    if hard in ("no_shoulders", "empty"):
        assert not m.any()
        np.testing.assert_array_equal(np.isnan(out), np.isnan(obs.world))


def test_save_and_load_round_trip_and_refuse_a_wrong_asset(tmp_path):
    rng = np.random.default_rng(5)
    corr = wc.WorldCorrection(rng.normal(size=wc.NUM_FEATURES), np.ones(wc.NUM_FEATURES),
                              rng.normal(size=(len(ARM_BONES), wc.NUM_FEATURES + 1, 3)))
    path = tmp_path / "c.npz"
    wc.save(corr, path)
    back = wc.load_world_correction(path)
    np.testing.assert_array_equal(back.weights, corr.weights)
    bad = dataclasses.replace(corr, weights=np.full_like(corr.weights, np.nan))
    wc.save(bad, path)
    with pytest.raises(ValueError, match="not finite"):
        wc.load_world_correction(path)
    wc.save(dataclasses.replace(corr, version=99), path)
    with pytest.raises(ValueError, match="version"):
        wc.load_world_correction(path)
    with pytest.raises(FileNotFoundError, match="build-world-correction"):
        wc.load_world_correction(tmp_path / "missing.npz")


def test_solve_refuses_non_finite_pairs():
    x = np.zeros((4, wc.NUM_FEATURES))
    x[0, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        wc.solve(x, np.zeros((4, 12)), np.ones((4, 4), bool))


def test_the_committed_asset_loads_and_corrects_a_frame():
    corr = wc.load_world_correction()
    obs = observe(body_points(np.random.default_rng(6)))
    out = wc.correct_world(obs, corr)
    assert np.isfinite(out[np.isfinite(obs.world).all(1)]).all()


def test_the_build_command_is_reproducible_and_reuses_its_recordings(tmp_path):
    """`telesplat track build-world-correction` at a tiny scale: studio renders, tracked,
    solved; built again from fresh renders, the same asset."""
    import json

    from avatar_core.cli import main
    from avatar_core.synth.model_writer import ensure_models

    family = str(ensure_models().root)
    args = ["track", "build-world-correction", "--identities", "1", "--framings", "waist_up",
            "--take", "clapping", "--max-frames", "6", "--body-models", family]
    assert main([*args, "--work", str(tmp_path / "a"), "--out", str(tmp_path / "a.npz")]) == 0
    recording, = (tmp_path / "a").glob("1_waist_up_*.pkl")
    stamp = recording.stat().st_mtime_ns
    assert main([*args, "--work", str(tmp_path / "a"), "--out", str(tmp_path / "b.npz")]) == 0
    assert recording.stat().st_mtime_ns == stamp  # reused, not filmed again
    other = [*args[:args.index("--take") + 1], "wave", *args[args.index("--take") + 2:]]
    assert main([*other, "--work", str(tmp_path / "a"), "--out", str(tmp_path / "w.npz")]) == 0
    assert len(list((tmp_path / "a").glob("1_waist_up_*.pkl"))) == 2  # another take: filmed
    assert main([*args, "--work", str(tmp_path / "c"), "--out", str(tmp_path / "c.npz")]) == 0
    a, b, c = (wc.load_world_correction(tmp_path / f"{k}.npz") for k in "abc")
    np.testing.assert_array_equal(a.weights, b.weights)
    np.testing.assert_array_equal(a.weights, c.weights)
    report = json.loads((tmp_path / "a.json").read_text())
    assert report["frames"] >= 6 and report["spec"]["take"] == ["clapping"]
    errors = report["train_bone_error_deg"]
    assert errors["blazepose"]["upper_count"] == errors["corrected"]["upper_count"] > 0


def test_the_sequence_fit_reads_the_corrected_world_points():
    """`SequenceFitConfig.world_correction` reaches the fit: a zero correction fits as none
    does, a non-zero one moves the arms."""
    from avatar_core.gaussians.animate import synthetic_package
    from avatar_core.synth.model_writer import ensure_models
    from avatar_core.track.fit.camera import WebcamCamera
    from avatar_core.track.fit.fitter import neutral_params
    from avatar_core.track.fit.sequence import SequenceFit, live_config
    from avatar_core.track.fit.synthetic import synthetic_observations

    package, model = synthetic_package(ensure_models().root, 0)
    betas = np.asarray(package.body.betas)
    camera = WebcamCamera(*SIZE, 60.0)
    plain = SequenceFit(model, betas, live_config(smoothing=False))
    truth = neutral_params(plain.fitter)
    truth["transl"] = np.array([0.0, 0.3, -2.0])
    obs, _ = synthetic_observations(plain.fitter, truth, camera, 0.0, np.random.default_rng(0))
    pts, _ = plain.fitter._keypoints(plain.fitter.pack(truth), False)
    obs.world = (pts[cor.POSE_SLICE] - pts[cor.POSE_SLICE][[23, 24]].mean(0)) * WORLD_TO_CAMERA
    shape = (len(ARM_BONES), wc.NUM_FEATURES + 1, 3)
    zero = wc.WorldCorrection(np.zeros(wc.NUM_FEATURES), np.ones(wc.NUM_FEATURES),
                              np.zeros(shape))
    turn = np.zeros(shape)
    turn[:, -1] = [0.0, 0.0, 0.8]  # every arm bone toward the camera
    toward = dataclasses.replace(zero, weights=turn)
    fits = {name: SequenceFit(model, betas, live_config(smoothing=False, world_correction=c))
            .step(obs, 0.0).params for name, c in (("zero", zero), ("turn", toward))}
    base = plain.step(obs, 0.0).params
    np.testing.assert_allclose(fits["zero"]["body_pose"], base["body_pose"], atol=1e-9)
    assert np.abs(fits["turn"]["body_pose"] - base["body_pose"]).max() > 0.05
