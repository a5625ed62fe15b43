"""Tracker errors that survive fusion (TrackerNoise): each effect on when asked, absent when
off, seeded, finite on extreme settings; and the capture records the truth beside them."""

from dataclasses import fields, replace

import numpy as np
import pytest

from avatar_core.synth.trackers import (
    TrackerNoise,
    parse_tracker_noise,
    simulate_trackers,
)

T = 12
RIGHT_ELBOW = 19 - 1  # body_pose index of SMPL-X joint 19


def _truth(seed: int = 0, t: int = T) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {"betas": np.zeros(10), "expression": rng.normal(0, 0.3, (t, 10)),
            "global_orient": rng.normal(0, 0.1, (t, 3)),
            "body_pose": rng.normal(0, 0.2, (t, 21, 3)),
            "jaw_pose": rng.normal(0, 0.1, (t, 3)), "leye_pose": np.zeros((t, 3)),
            "reye_pose": np.zeros((t, 3)), "transl": rng.normal(0, 0.05, (t, 3)),
            "left_hand_pose": rng.normal(0, 0.3, (t, 15, 3)),
            "right_hand_pose": rng.normal(0, 0.3, (t, 15, 3))}


def _sim(comps, noise: TrackerNoise | None, seed: int = 3, t: int = T):
    return simulate_trackers(_truth(t=t), comps, noise_deg=0.0, noise=noise,
                             rng=np.random.default_rng(seed))


def _changed(a: dict, b: dict) -> set[str]:
    return {k for k in a if not np.array_equal(a[k], b[k])}


@pytest.fixture(scope="module")
def comps(smplx_data):
    return smplx_data.hand_components


# field -> the tracker arrays that field (alone) must change
EFFECTS = {
    "expression_std": {"flame_expr"},
    "jaw_deg": {"flame_jaw_pose"},
    "body_deg": {"body_pose"},
    "body_lag_frames": {"global_orient", "body_pose", "transl"},
    "hand_swap_frames": {f"mano_{s}_{k}" for s in ("left", "right")
                         for k in ("hand_pose", "global_orient")},
    "calibration_deg": {"global_orient", "transl", "flame_rotation",
                        "mano_left_global_orient", "mano_right_global_orient"},
    "calibration_mm": {"transl"},
}


@pytest.mark.parametrize("name", sorted(EFFECTS))
def test_each_effect_changes_only_its_arrays(comps, name):
    clean = _sim(comps, None)
    value = 2 if name.endswith("frames") else 3.0
    noisy = _sim(comps, replace(TrackerNoise(), **{name: value}))
    assert _changed(clean, noisy) == EFFECTS[name]


def test_a_lost_hand_holds_its_last_pose(comps):
    clean = _sim(comps, None)
    noisy = _sim(comps, TrackerNoise(hand_lost_frames=4))
    changed = _changed(clean, noisy)
    side = "left" if "mano_left_hand_pose" in changed else "right"
    assert changed == {f"mano_{side}_hand_pose", f"mano_{side}_global_orient"}
    rows = np.flatnonzero(np.any(clean[f"mano_{side}_hand_pose"]
                                 != noisy[f"mano_{side}_hand_pose"], axis=(1, 2)))
    assert 1 <= len(rows) <= 4 and rows[0] >= 1
    held = noisy[f"mano_{side}_hand_pose"][rows]
    np.testing.assert_array_equal(held, np.broadcast_to(clean[f"mano_{side}_hand_pose"][
        rows[0] - 1], held.shape))


def test_swapped_frames_mirror_the_other_hand(comps):
    clean = _sim(comps, None)
    noisy = _sim(comps, TrackerNoise(hand_swap_frames=3))
    rows = np.flatnonzero(np.any(clean["mano_left_hand_pose"] != noisy["mano_left_hand_pose"],
                                 axis=(1, 2)))
    assert len(rows) == 3
    mirror = np.array([1.0, -1.0, -1.0])
    np.testing.assert_allclose(noisy["mano_left_hand_pose"][rows],
                               clean["mano_right_hand_pose"][rows] * mirror)


def test_lag_delays_the_body_by_whole_frames(comps):
    clean = _sim(comps, None)
    noisy = _sim(comps, TrackerNoise(body_lag_frames=2))
    np.testing.assert_array_equal(noisy["body_pose"][2:], clean["body_pose"][:-2])
    np.testing.assert_array_equal(noisy["transl"][:2], clean["transl"][[0, 0]])


def test_noise_scale_follows_the_setting(comps):
    clean = _sim(comps, None, t=400)
    noisy = _sim(comps, TrackerNoise(body_deg=3.0, jaw_deg=2.0), t=400)
    body = np.rad2deg(noisy["body_pose"] - clean["body_pose"])[:, RIGHT_ELBOW]
    jaw = np.rad2deg(noisy["flame_jaw_pose"] - clean["flame_jaw_pose"])
    assert 2.7 < body.std() < 3.3 and 1.8 < jaw.std() < 2.2


def test_off_is_the_plain_simulation_and_seeds_repeat(comps):
    assert not TrackerNoise().enabled and TrackerNoise.studio().enabled
    plain = simulate_trackers(_truth(), comps, rng=np.random.default_rng(5))
    off = simulate_trackers(_truth(), comps, rng=np.random.default_rng(5), noise=TrackerNoise())
    assert not _changed(plain, off)
    a = _sim(comps, TrackerNoise.studio(), seed=7)
    b = _sim(comps, TrackerNoise.studio(), seed=7)
    c = _sim(comps, TrackerNoise.studio(), seed=8)
    assert not _changed(a, b)
    assert _changed(a, c)


def test_switching_one_effect_off_keeps_the_others_draws(comps):
    studio = TrackerNoise.studio()
    full = _sim(comps, studio)
    no_jaw = _sim(comps, replace(studio, jaw_deg=0.0))
    assert _changed(full, no_jaw) == {"flame_jaw_pose"}


@pytest.mark.parametrize("t", [1, 2, T])
def test_extreme_settings_stay_finite(comps, t):
    huge = TrackerNoise(expression_std=1e6, jaw_deg=1e6, body_deg=1e6, body_lag_frames=10**6,
                        hand_swap_frames=10**6, hand_lost_frames=10**6, calibration_deg=1e6,
                        calibration_mm=1e9)
    out = _sim(comps, huge, t=t)
    assert all(np.isfinite(v).all() for v in out.values())
    assert all(len(v) == t for k, v in out.items() if k != "betas")


@pytest.mark.parametrize("bad", [{"jaw_deg": -1.0}, {"body_deg": float("nan")},
                                 {"calibration_mm": float("inf")}, {"body_lag_frames": 1.5},
                                 {"hand_swap_frames": True}, {"expression_std": "1"}])
def test_bad_settings_are_refused(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        TrackerNoise(**bad)


def test_parse_from_the_command_line():
    assert parse_tracker_noise("") == TrackerNoise()
    assert parse_tracker_noise("studio") == TrackerNoise.studio()
    assert parse_tracker_noise("studio, hand_swap_frames=0") == replace(
        TrackerNoise.studio(), hand_swap_frames=0)
    assert parse_tracker_noise("jaw_deg=2.5").jaw_deg == 2.5
    for bad in ("jaw=2", "jaw_deg", "jaw_deg=x", "body_lag_frames=1.5", "jaw_deg=-1"):
        with pytest.raises(ValueError, match="tracker noise"):
            parse_tracker_noise(bad)
    assert {f.name for f in fields(TrackerNoise)} == set(EFFECTS) | {"hand_lost_frames"}


def test_capture_writes_the_truth_beside_noisy_trackers(tmp_path, synthetic_files):
    from avatar_core.dataset import load_dataset
    from avatar_core.synth.capture import CaptureSpec, capture, true_params_path

    spec = CaptureSpec(sequences=(("smile",),), num_cameras=2, resolution=32, max_frames=3,
                       supersample=1, workers=1, tracker_noise=TrackerNoise(jaw_deg=5.0))
    ds = load_dataset(capture(tmp_path / "d", spec, model_dir=synthetic_files.root))
    seq = next(iter(ds.sequences))
    truth = dict(np.load(true_params_path(ds.root, seq)))
    tracked = ds.params(seq)
    assert not np.allclose(tracked["flame_jaw_pose"], truth["jaw_pose"])
    np.testing.assert_allclose(tracked["expression"], 0.0)  # the body tracker's
    with pytest.raises(ValueError, match="simulated"):
        CaptureSpec(sequences=(("smile",),), trackers="exact",
                    tracker_noise=TrackerNoise(jaw_deg=1.0))


def test_capture_cli_refuses_a_bad_noise_setting(tmp_path, capsys):
    from avatar_core.cli import main

    assert main(["synth", "capture", "--out", str(tmp_path / "d"), "--motions", "smile",
                 "--tracker-noise", "studio,jaw=1"]) == 2
    assert "tracker noise 'jaw=1'" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()
