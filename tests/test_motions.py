"""The motion library: plausible, continuous clips; blending and chaining; hands that meet."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from avatar_core.body.joint_limits import JOINT_LIMITS_DEG
from avatar_core.body.model_paths import BodyModelFiles
from avatar_core.body.models import SMPLXModel
from avatar_core.motion.keyframes import (
    Clip,
    Pose,
    Track,
    blend,
    chain,
    check_joint_limits,
    pose_to_params,
)
from avatar_core.motion.library import (
    CATEGORIES,
    MOTIONS,
    motion,
    motion_names,
    motion_sequence,
)
from avatar_core.motion.rig import model_rig
from avatar_core.synth import model_writer
from avatar_core.synth.model_writer import (
    GENERATOR_VERSION,
    SMPLX_SEMANTIC_VERTEX_IDS,
    ensure_models,
    generator_version,
)

EXPRESSIONS = {"neutral", "smile", "grin", "mouth_open", "jaw_left", "jaw_right", "pucker",
               "cheeks_puffed", "eyes_closed", "brows_raised", "sad", "angry"}
GESTURES = {"thumbs_up", "peace", "number_1", "number_2", "number_3", "number_4", "number_5",
            "letter_L", "heart", "clapping", "pointing", "fingertips_pushing"}
CONVERSATION = {"talk_calm", "talk_animated", "nod", "shake_head", "shrug", "look_around",
                "wave", "hands_to_face", "reach_out"}
NEW_GESTURES = ("three", "four", "L", "heart_half", "cupped")
OLD_GESTURES = ("flat", "relaxed", "fist", "point", "thumbs_up", "peace", "ok", "spread",
                "claw", "pinch")


@pytest.fixture(scope="module")
def model(smplx_data):
    return SMPLXModel(smplx_data, dtype=torch.float64)


@pytest.fixture(scope="module")
def rig(synthetic_files, model):
    return model_rig(synthetic_files, model)


def times(duration: float, dt: float) -> np.ndarray:
    return np.linspace(0.0, duration, int(math.ceil(duration / dt)) + 1)


def max_step(track: Track, rig, dt: float, start: float = 0.0, end: float | None = None) -> float:
    """Largest change of any parameter between samples dt apart over [start, end]."""
    end = track.duration if end is None else end
    prev, worst = None, 0.0
    for t in start + times(end - start, dt):
        p = track.sample(float(t), rig)
        if prev is not None:
            worst = max(worst, max(float(np.abs(p[k] - prev[k]).max()) for k in p))
        prev = p
    return worst


def posed(model, params: dict) -> tuple[np.ndarray, np.ndarray]:
    """Vertices [V, 3] and joints [55, 3] of unbatched parameters."""
    with torch.no_grad():
        out = model({k: torch.as_tensor(v)[None] for k, v in params.items()})
    return out.vertices[0].numpy(), out.joints[0].numpy()


def same(a: dict, b: dict, atol: float = 1e-12) -> bool:
    return a.keys() == b.keys() and all(np.allclose(a[k], b[k], atol=atol, rtol=0) for k in a)


# ----------------------------------------------------------------------------- the library


def test_names_and_categories():
    assert set(motion_names("expressions")) == EXPRESSIONS
    assert set(motion_names("gestures")) == GESTURES
    assert set(motion_names("conversation")) == CONVERSATION
    assert set(motion_names()) == EXPRESSIONS | GESTURES | CONVERSATION == set(MOTIONS)
    assert {MOTIONS[n].category for n in MOTIONS} == set(CATEGORIES)
    with pytest.raises(ValueError, match="unknown motion category 'dance'.*gestures"):
        motion_names("dance")


def test_unknown_motion_names_list_the_known_ones():
    with pytest.raises(ValueError, match="unknown motion 'waving_flag'; known: ") as err:
        motion("waving_flag")
    assert all(n in str(err.value) for n in ("smile", "heart", "talk_calm"))
    with pytest.raises(ValueError, match="unknown motion 'waving_flag'"):
        motion_sequence("smile,waving_flag")
    with pytest.raises(ValueError, match="no motion names"):
        motion_sequence(" , ")


def test_every_clip_is_plausible_and_starts_and_ends_neutral(rig):
    neutral = pose_to_params(Pose(), rig)
    for name in motion_names():
        clip = motion(name)
        assert isinstance(clip, Clip) and clip.name == name
        assert 1.5 <= clip.duration <= 4.0, name
        for t in times(clip.duration, 1 / 25):
            p = clip.sample(float(t), rig)
            assert all(np.isfinite(v).all() for v in p.values()), (name, t)
            assert check_joint_limits(p, rig) == [], (name, t)
        assert same(clip.sample(0.0, rig), neutral), name
        assert same(clip.sample(clip.duration, rig), neutral), name


def test_sequences_are_continuous_across_clip_boundaries(rig):
    seq = motion_sequence("smile, thumbs_up,talk")
    parts = [motion(n) for n in ("smile", "thumbs_up", "talk_calm")]
    assert seq.name == "smile+thumbs_up+talk"
    assert seq.duration == pytest.approx(sum(c.duration for c in parts) + 2 * 0.4)
    coarse, fine = max_step(seq, rig, 1 / 200), max_step(seq, rig, 1 / 400)
    # Continuous: steps are small and halve with the time step (a jump would not shrink).
    assert coarse < 0.05 and fine < 0.6 * coarse
    # Each clip plays unchanged between the transitions.
    assert same(seq.sample(parts[0].duration + 0.4 + 1.0, rig), parts[1].sample(1.0, rig))


def test_gesture_hands_are_in_front_of_the_body(model, rig):
    for name in motion_names("gestures"):
        clip = motion(name)
        _, joints = posed(model, clip.sample(clip.keyframes[1][0], rig))
        hand = joints[43]  # right middle knuckle
        assert hand[2] > 0.15, name  # in front of the chest (its surface is at z ~ 0.11)
        assert 0.15 < hand[1] < 0.75, name  # between the belly and the top of the head
        assert abs(hand[0]) < 0.3, name


# ---------------------------------------------------------------------------- two hands meet


def tips(verts: np.ndarray, side: str) -> np.ndarray:
    """Fingertip vertices [5, 3]: index, middle, pinky, ring, thumb."""
    s = "r" if side == "right" else "l"
    return verts[[SMPLX_SEMANTIC_VERTEX_IDS[f"{s}{f}"]
                  for f in ("index", "middle", "pinky", "ring", "thumb")]]


def hand_vertices(smplx_data, side: str) -> np.ndarray:
    wrist, first = (21, 40) if side == "right" else (20, 25)
    return np.flatnonzero(smplx_data.weights[:, [wrist, *range(first, first + 15)]].sum(1) > 0.5)


def hand_gap(verts: np.ndarray, right: np.ndarray, left: np.ndarray) -> float:
    """Closest distance between the two hands' vertices (chunked to bound memory)."""
    lv = verts[left]
    return min(float(np.linalg.norm(verts[right[i:i + 256], None] - lv[None], axis=-1).min())
               for i in range(0, len(right), 256))


def test_two_hand_gestures_bring_the_hands_together(model, rig, smplx_data):
    right, left = hand_vertices(smplx_data, "right"), hand_vertices(smplx_data, "left")
    for name in ("heart", "clapping", "fingertips_pushing"):
        clip = motion(name)
        # At each keyframe: the hands never pass through each other (the left hand mirrors the
        # right, so the right one must stay on its side of the midline).
        key = []
        for t, _ in clip.keyframes:
            verts, _ = posed(model, clip.sample(t, rig))
            assert verts[right, 0].max() < 0.005, (name, t)
            key.append((hand_gap(verts, right, left), t, verts))
        gap, t, verts = min(key, key=lambda k: k[0])
        assert gap < 0.01, name  # touching
        d = np.linalg.norm(tips(verts, "right") - tips(verts, "left"), axis=1)  # [5]
        if name == "heart":
            assert d[0] < 0.03 and d[4] < 0.03  # index tips meet on top, thumb tips below
            assert tips(verts, "right")[0, 1] - tips(verts, "right")[4, 1] > 0.04
        elif name == "fingertips_pushing":
            assert (d < 0.03).all()
        else:
            _, joints = posed(model, clip.sample(t, rig))
            assert np.linalg.norm(joints[43] - joints[28]) < 0.06  # palm against palm
        assert sum(g < 0.01 for g, _, _ in key) >= (4 if name == "clapping" else 1)


def test_clapping_never_crosses_the_hands(model, rig, smplx_data):
    right = hand_vertices(smplx_data, "right")
    clip = motion("clapping")
    for t in times(clip.duration, 1 / 25):
        verts, _ = posed(model, clip.sample(float(t), rig))
        assert verts[right, 0].max() < 0.005, t


# -------------------------------------------------------------------------- blend and chain

RAMP = Clip("ramp", ((0.0, Pose()), (1.0, Pose({"neck": (0.3, 0.0, 0.0)}, {"smile": 1.0}))))
OTHER = Clip("other", ((0.0, Pose({"jaw": (0.2, 0.0, 0.0)}, right_hand="fist")),
                       (2.0, Pose(expression={"frown": 1.0}, left_hand="spread"))))


def test_blend_weights_reproduce_the_inputs_and_hold_the_shorter_track(rig):
    for t in (0.0, 0.4, 1.0, 1.7, 2.0):
        assert same(blend("a", RAMP, OTHER, 0.0).sample(t, rig), RAMP.sample(t, rig))
        assert same(blend("b", RAMP, OTHER, 1.0).sample(t, rig), OTHER.sample(t, rig))
        half = blend("h", RAMP, OTHER, 0.5).sample(t, rig)
        a, b = RAMP.sample(t, rig), OTHER.sample(t, rig)
        assert same(half, {k: 0.5 * (a[k] + b[k]) for k in a})
    assert blend("x", RAMP, OTHER, 0.5).duration == 2.0
    # Past its end the ramp holds its last pose.
    assert same(blend("a", RAMP, OTHER, 0.0).sample(1.8, rig), RAMP.sample(1.0, rig))
    fade = blend("fade", RAMP, OTHER, lambda t: t / 2.0)
    assert same(fade.sample(0.0, rig), RAMP.sample(0.0, rig))
    assert same(fade.sample(2.0, rig), OTHER.sample(2.0, rig))
    assert max_step(fade, rig, 1 / 200) < 0.05


def test_blend_rejects_weights_outside_0_1(rig):
    with pytest.raises(ValueError, match="weight must lie in"):
        blend("bad", RAMP, OTHER, 1.5)
    with pytest.raises(ValueError, match="outside"):
        blend("bad", RAMP, OTHER, lambda t: 2.0 * t).sample(1.0, rig)


def test_chain_crossfades_any_tracks_continuously(rig):
    # A blend and a chain (not clips) whose end and start poses differ.
    a = blend("a", RAMP, OTHER, 0.3)
    b = chain("b", [OTHER, RAMP], crossfade=0.2)
    c = chain("ab", [a, b], crossfade=0.5)
    assert c.duration == pytest.approx(a.duration + 0.5 + b.duration)
    end = a.duration
    assert same(c.sample(end, rig), a.sample(a.duration, rig))
    assert same(c.sample(end + 0.5, rig), b.sample(0.0, rig))
    assert same(c.sample(end + 0.5 + 1.0, rig), b.sample(1.0, rig))
    assert not same(a.sample(a.duration, rig), b.sample(0.0, rig))  # there is a gap to bridge
    coarse, fine = max_step(c, rig, 1 / 200), max_step(c, rig, 1 / 400)
    assert coarse < 0.05 and fine < 0.6 * coarse
    # Before and after: clamped to the ends.
    assert same(c.sample(-1.0, rig), a.sample(0.0, rig))
    assert same(c.sample(c.duration + 1.0, rig), b.sample(b.duration, rig))
    with pytest.raises(ValueError, match="at least one"):
        chain("empty", [])


# ---------------------------------------------------------------------------- joint limits


def test_joint_limits_report_each_violation(rig):
    p = pose_to_params(Pose(), rig)
    assert check_joint_limits(p, rig) == []
    p["body_pose"][19 - 1] = (0.0, np.radians(170.0), 0.0)  # right elbow
    p["jaw_pose"] = np.array([np.radians(40.0), 0.0, 0.0])
    p["expression"][rig.expression_names.index("smile")] = 2.0
    p["transl"] = np.array([np.nan, 0.0, 0.0])
    problems = check_joint_limits(p, rig)
    assert len(problems) == 4
    text = "\n".join(problems)
    for part in ("right_elbow: 170.0 deg exceeds the limit of 150", "jaw: 40.0 deg",
                 "smile: 2.00 outside [-1.5, 1.5]", "transl: not finite"):
        assert part in text
    assert JOINT_LIMITS_DEG["neck"] == 50 and JOINT_LIMITS_DEG["right_index2"] == 110


def test_joint_limits_see_fingers_with_the_mean_hand(rig):
    p = pose_to_params(Pose(), rig)
    # Relative to the mean hand this is within the limit; the absolute rotation is not.
    mean = rig.hand_mean["right"][3]  # middle1
    p["right_hand_pose"][3] = np.radians(105.0) * mean / np.linalg.norm(mean)
    assert check_joint_limits(p) == []
    assert any(m.startswith("right_middle1:") for m in check_joint_limits(p, rig))


# ------------------------------------------------------------------------------- gestures


def test_new_gestures_are_written(synthetic_files, model, rig):
    with np.load(synthetic_files.gestures) as g:
        assert set(NEW_GESTURES + OLD_GESTURES) <= set(g.files)
        poses = {k: g[k] for k in g.files}
    assert all(p.shape == (15, 3) and np.isfinite(p).all() for p in poses.values())
    manifest = json.loads(synthetic_files.manifest.read_text())
    assert manifest["generator_version"] == GENERATOR_VERSION
    assert set(NEW_GESTURES) <= set(manifest["hand_poses"])

    def shape(name):
        verts, joints = posed(model, {"right_hand_pose": poses[name] - rig.hand_mean["right"]})
        return tips(verts, "right"), joints

    flat_tips, flat_joints = shape("flat")
    reach = np.linalg.norm(flat_tips - flat_joints[21], axis=1)  # [5]
    # Numbers 1-5: how many of the four long fingers are straight; the thumb out only for 5.
    for count, name in enumerate(("point", "peace", "three", "four", "spread"), start=1):
        t, j = shape(name)
        straight = np.linalg.norm(t[:4] - j[21], axis=1) > 0.9 * reach[:4]
        assert straight.sum() == min(count, 4), name
        thumb_to_palm = np.linalg.norm(t[4] - j[43])
        assert (thumb_to_palm > 0.08) == (count == 5), name
    t, j = shape("three")
    assert np.linalg.norm(t[4] - j[47]) < 0.03  # the thumb tip holds the curled pinky
    t, j = shape("L")
    index, thumb = t[0] - j[40], t[4] - j[52]
    angle = np.degrees(np.arccos(index @ thumb / np.linalg.norm(index) / np.linalg.norm(thumb)))
    assert angle > 65 and np.linalg.norm(t[0] - j[21]) > 0.9 * reach[0]
    for name in ("heart_half", "cupped"):  # curved, fingers together
        t, j = shape(name)
        d = np.linalg.norm(t[:4] - j[21], axis=1)
        assert (d < 0.99 * reach[:4]).all() and (d > 0.6 * reach[:4]).all(), name
        assert np.linalg.norm(t[0] - t[2]) < np.linalg.norm(flat_tips[0] - flat_tips[2]), name


# -------------------------------------------------------------------------- the model cache


def test_ensure_models_rewrites_a_stale_cache(tmp_path, monkeypatch):
    calls = []

    def fake_writer(out, *, seed=0):
        calls.append(seed)
        root = Path(out)
        (root / "identities").mkdir(parents=True, exist_ok=True)
        (root / "identities" / "identity_0.npz").write_bytes(b"new identity")
        (root / "gestures.npz").write_bytes(b"new gestures")
        (root / "manifest.json").write_text(json.dumps({"generator_version": GENERATOR_VERSION,
                                                        "seed": seed}))
        return BodyModelFiles(root)

    monkeypatch.setattr(model_writer, "write_synthetic_models", fake_writer)
    root = tmp_path / "cache"
    files = ensure_models(root, seed=3)  # nothing there yet
    assert calls == [3] and generator_version(files) == GENERATOR_VERSION
    ensure_models(root, seed=3)  # current: left alone
    assert calls == [3]

    stale = {"generator": "telesplat.synth.model_files", "seed": 3}  # before versions existed
    for manifest in (json.dumps(stale), json.dumps({**stale, "generator_version": 1}), "{oops",
                     None):
        (root / "gestures.npz").write_bytes(b"old gestures")
        (root / "notes.txt").write_text("mine")
        if manifest is None:
            (root / "manifest.json").unlink()
        else:
            (root / "manifest.json").write_text(manifest)
        n = len(calls)
        files = ensure_models(root, seed=3)
        assert len(calls) == n + 1, manifest
        assert (root / "gestures.npz").read_bytes() == b"new gestures"
        assert generator_version(files) == GENERATOR_VERSION
        assert (root / "notes.txt").read_text() == "mine"  # other files are left alone
        assert sorted(p.name for p in root.iterdir()) == [
            "gestures.npz", "identities", "manifest.json", "notes.txt"]  # no scratch left
