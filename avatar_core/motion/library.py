"""A library of named motions: facial expressions, hand gestures and conversation.

Every motion is a keyframed `Clip` of 1.5-4 s that starts and ends in the neutral stance
(`Pose()`: relaxed arms and hands, neutral face), so any sequence of them chains smoothly, and
that stays within `JOINT_LIMITS_DEG` (body/joint_limits.py). Gestures are made by the right
hand; two-hand gestures use the mirror image of the right arm for the left, so the hands meet
on the midline (x = 0).

The arm angles of the gesture key poses were fitted by least squares on the synthetic body
(hand orientation and position in front of the chest, fingertips or palms on the midline for
two-hand gestures, forearm outside the torso) and are checked by the tests against the
synthetic model: rounding them or changing the body's proportions must keep hands meeting.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np

from ..body.joint_limits import RELAXED_ARMS
from ..body.skeleton import swap_left_right
from .keyframes import Chain, Clip, Pose, Track, chain

CATEGORIES = ("expressions", "gestures", "conversation")
ALIASES = MappingProxyType({"talk": "talk_calm"})  # short names accepted by `motion`
_ARM_JOINTS = ("right_collar", "right_shoulder", "right_elbow", "right_wrist")
# Right-arm key poses (collar, shoulder, elbow, wrist axis-angles), fitted on the synthetic body.
_ARMS = MappingProxyType({
    # Flat palms facing +x, fingers forward-up: palms and fingers on the midline (the thumbs
    # graze each other), and 24 cm apart.
    "clap_closed": ((0.029, 0.028, 0.134), (0.218, 0.828, 1.156), (-0.083, 1.675, 0.000),
                    (-0.001, 0.142, -0.592)),
    "clap_open": ((0.032, -0.014, 0.135), (0.221, 0.589, 1.089), (-0.355, 1.827, 0.000),
                  (-0.002, 0.173, -0.273)),
    # `cupped` fingertips on the midline, fingers pointing up and forward.
    "steeple": ((-0.007, 0.007, 0.176), (0.196, 0.500, 1.184), (0.290, 1.779, -0.001),
                (0.026, 0.346, -0.694)),
    # `heart_half` with index and thumb tips on the midline, in front of the chest.
    "heart": ((-0.010, -0.007, 0.161), (-0.525, 0.411, 1.086), (0.776, 1.790, -0.002),
              (0.075, 0.547, -0.526)),
    # Palm toward the camera, fingers up, beside the chin: numbers and letters.
    "sign": ((-0.017, -0.143, 0.189), (-0.916, 0.207, 0.987), (0.958, 1.952, -0.013),
             (0.465, 0.094, -0.783)),
    # Fist in front of the chest, thumb up, knuckles forward.
    "thumbs_up": ((0.001, -0.143, -0.061), (0.166, 0.342, 1.501), (-0.239, 1.937, 0.000),
                  (-0.021, -0.466, 0.305)),
    # Index pointing forward at shoulder height.
    "pointing": ((-0.027, 0.062, 0.085), (0.006, 0.818, 0.175), (-0.027, 1.420, 0.000),
                 (-0.000, -0.617, -0.086)),
    # Shoulder raised by the collar (negative z lifts the right one), forearms forward and
    # out, palms up.
    "shrug": ((0.0, 0.0, -0.25), (-0.443, 0.107, 1.823), (-1.718, 0.953, 0.0),
              (-0.165, -0.292, 0.616)),
    # An open hand raised in front of the belly, palm up and in: talking with the hands.
    "explain": ((-0.175, 0.160, 0.118), (-0.032, 0.363, 1.559), (-1.128, 1.253, 0.012),
                (-0.035, -0.141, 0.189)),
})  # fmt: skip


@dataclass(frozen=True)
class MotionSpec:
    category: str
    make: Callable[[], Clip]


# ---------------------------------------------------------------------------------------------
# Building blocks


def arm(key: str) -> dict[str, tuple[float, ...]]:
    """The right-arm joints of a fitted key pose."""
    return dict(zip(_ARM_JOINTS, _ARMS[key], strict=True))


def mirrored(joints: Mapping[str, Sequence[float]]) -> dict[str, tuple[float, ...]]:
    """The same rotations on the other side of the body: (x, y, z) -> (x, -y, -z)."""
    return {swap_left_right(k): (v[0], -v[1], -v[2]) for k, v in joints.items()}


def both_arms(key: str) -> dict[str, tuple[float, ...]]:
    return {**arm(key), **mirrored(arm(key))}


def _lerp_joints(a: Mapping[str, Sequence[float]], b: Mapping[str, Sequence[float]],
                 w: float) -> dict[str, tuple[float, ...]]:
    """Joint rotations between a and b (missing joints are at rest, arms relaxed)."""
    def value(src, k):
        return np.asarray(src.get(k, RELAXED_ARMS.get(k, (0.0, 0.0, 0.0))), dtype=np.float64)
    return {k: tuple((1.0 - w) * value(a, k) + w * value(b, k)) for k in {*a, *b}}


def _hold(name: str, pose: Pose, rise: float = 0.6, hold: float = 1.2,
          fall: float = 0.6) -> Clip:
    """Neutral -> pose, held, -> neutral."""
    return Clip(name, ((0.0, Pose()), (rise, pose), (rise + hold, pose),
                       (rise + hold + fall, Pose())))


def _face(name: str, expression: Mapping[str, float],
          joints: Mapping[str, Sequence[float]] | None = None) -> Clip:
    return _hold(name, Pose(dict(joints or {}), dict(expression)), 0.5, 1.0, 0.5)


def _right_hand(name: str, arm_key: str, gesture: str, expression=None, joints=None) -> Clip:
    return _hold(name, Pose({**arm(arm_key), **(joints or {})}, dict(expression or {}),
                            right_hand=gesture), 0.7, 1.3, 0.6)


def _envelope(t: float, duration: float, ramp: float = 0.5) -> float:
    """0 at both ends, 1 in between, smooth ramps: keeps procedural clips neutral at the ends."""
    x = min(t, duration - t, ramp) / ramp
    x = min(max(x, 0.0), 1.0)
    return x * x * (3.0 - 2.0 * x)


# ---------------------------------------------------------------------------------------------
# Expressions


def _neutral() -> Clip:
    blink = Pose(expression={"blink_left": 1.0, "blink_right": 1.0})
    # One blink, late in the clip: its middle (where previews look) is the plain face.
    return Clip("neutral", ((0.0, Pose()), (1.0, Pose()), (1.1, blink), (1.22, Pose()),
                            (1.6, Pose())))


def _sad() -> Clip:
    # Inner brows up, mouth corners down, gaze and head lowered.
    return _face("sad", {"frown": 0.9, "brows_raise": 0.45, "lips_part": 0.1},
                 {"head": (0.15, 0.0, 0.05), "left_eye_smplhf": (0.12, 0.0, 0.0),
                  "right_eye_smplhf": (0.12, 0.0, 0.0)})


def _angry() -> Clip:
    # Brows pulled down, lips pressed with the teeth bared a little, head pushed forward.
    return _face("angry", {"brows_lower": 1.0, "frown": 0.6, "grin": 0.3, "pucker": 0.15},
                 {"neck": (0.12, 0.0, 0.0), "head": (-0.06, 0.0, 0.0)})


# ---------------------------------------------------------------------------------------------
# Gestures


def _heart() -> Clip:
    return _hold("heart", Pose(both_arms("heart"), {"smile": 0.7}, left_hand="heart_half",
                               right_hand="heart_half"), 0.8, 1.4, 0.7)


def _fingertips_pushing() -> Clip:
    # Press, ease off a little, press again: the fingertips stay on each other.
    pose = Pose(both_arms("steeple"), left_hand="cupped", right_hand="cupped")
    return Clip("fingertips_pushing", ((0.0, Pose()), (0.8, pose), (1.4, pose), (1.8, pose),
                                       (2.4, pose), (3.1, Pose())))


def _clapping() -> Clip:
    open_, closed = (Pose(both_arms(k), {"smile": 0.6}, left_hand="flat", right_hand="flat")
                     for k in ("clap_open", "clap_closed"))
    keys = [(0.0, Pose()), (0.7, open_)]
    for i in range(4):  # four claps at 2.5 Hz
        keys += [(0.9 + 0.4 * i, closed), (1.1 + 0.4 * i, open_)]
    keys.append((keys[-1][0] + 0.7, Pose()))
    return Clip("clapping", tuple(keys))


def _wave() -> Clip:
    # Right hand raised beside the head, palm to the camera, waving from the wrist at 2.5 Hz.
    # The shoulder turns the arm outward 90 deg (then lifts it 20 deg above the horizontal)
    # so that the elbow's own flexion raises the forearm: Rz(-0.35) Rx(-pi/2).
    up = {"right_shoulder": (-1.553, 0.275, -0.275), "right_elbow": (0.0, 1.6, 0.0)}
    sway = [Pose({**up, "right_wrist": (0.0, s, 0.0)}, {"smile": 0.6}, right_hand="spread")
            for s in (-0.35, 0.35)]
    keys = [(0.0, Pose()), (0.7, sway[0])]
    for i in range(4):
        keys += [(0.9 + 0.4 * i, sway[1]), (1.1 + 0.4 * i, sway[0])]
    keys.append((keys[-1][0] + 0.7, Pose()))
    return Clip("wave", tuple(keys))


def _hands_to_face() -> Clip:
    # Both flat hands beside the chin (the `sign` arm, mirrored): hands at the face.
    return _hold("hands_to_face", Pose(both_arms("sign"), {"lips_part": 0.2},
                                       left_hand="flat", right_hand="flat"), 0.7, 1.2, 0.7)


def _reach_out() -> Clip:
    # The right arm stretched out sideways a little above the shoulder: in a head-and-
    # shoulders or waist-up webcam frame the hand leaves the image and comes back.
    out = {"right_shoulder": (0.0, -0.3, -0.2), "right_elbow": (0.0, 0.15, 0.0)}
    look = {"head": (0.0, -0.25, 0.0)}  # toward the hand
    return _hold("reach_out", Pose({**out, **look}, right_hand="spread"), 0.8, 1.0, 0.8)


def _pointing() -> Clip:
    # Look where the finger points (forward and a little to the subject's right).
    look = {"head": (0.0, -0.12, 0.0)}
    return _right_hand("pointing", "pointing", "point", joints=look)


# ---------------------------------------------------------------------------------------------
# Conversation


def _nod() -> Clip:
    down, up = Pose({"neck": (0.12, 0.0, 0.0), "head": (0.2, 0.0, 0.0)}), Pose(
        {"neck": (0.0, 0.0, 0.0), "head": (-0.05, 0.0, 0.0)})
    return Clip("nod", ((0.0, Pose()), (0.35, down), (0.7, up), (1.05, down), (1.4, up),
                        (1.75, down), (2.2, Pose())))


def _shake_head() -> Clip:
    def turn(s):
        return Pose({"neck": (0.0, 0.15 * s, 0.0), "head": (0.0, 0.25 * s, 0.0)},
                    {"frown": 0.3})
    return Clip("shake_head", ((0.0, Pose()), (0.35, turn(1)), (0.75, turn(-1)), (1.15, turn(1)),
                               (1.55, turn(-1)), (2.1, Pose())))


def _shrug() -> Clip:
    # Shoulders up, palms up, head tilted, brows raised, mouth corners down.
    pose = Pose({**both_arms("shrug"), "head": (0.0, 0.0, 0.18)},
                {"brows_raise": 0.9, "frown": 0.5}, left_hand="spread", right_hand="spread")
    return _hold("shrug", pose, 0.6, 0.9, 0.7)


def _look_around() -> Clip:
    def look(yaw, pitch=0.0):
        eyes = (0.5 * pitch, 0.25 * np.sign(yaw), 0.0)
        return Pose({"neck": (0.3 * pitch, 0.3 * yaw, 0.0), "head": (0.7 * pitch, 0.7 * yaw, 0.0),
                     "left_eye_smplhf": eyes, "right_eye_smplhf": eyes})
    return Clip("look_around", ((0.0, Pose()), (0.7, look(0.7)), (1.3, look(0.7, -0.12)),
                                (2.2, look(-0.7)), (2.8, look(-0.7, 0.1)), (3.5, Pose())))


def _talk(name: str, seed: int, duration: float, jaw: float, lively: float) -> Clip:
    """Speech: the jaw and lips open and close per syllable (0.12-0.24 s), the head nods and
    tilts slowly, the torso sways; `lively` scales head, torso and brow motion and lets the
    right hand, then the left, rise into an open-palm gesture."""
    rng = np.random.default_rng(seed)  # a fixed seed: the same clip every time
    times = [0.0, 0.35]
    while times[-1] < duration - 0.6:  # syllables until the closing ramp; bounded by duration
        times.append(times[-1] + float(rng.uniform(0.12, 0.24)))
    times += [duration]
    keys = []
    for i, t in enumerate(times):
        env = _envelope(t, duration, 0.35)
        # Syllable nuclei open the mouth, boundaries nearly close it.
        opening = float(rng.uniform(0.45, 1.0)) if 0 < i < len(times) - 1 and i % 2 else 0.08
        opening *= env
        slow = 2.0 * np.pi * t
        joints = {
            "jaw": (jaw * opening, 0.0, 0.0),
            "neck": (lively * 0.05 * np.sin(slow / 1.7) * env, lively * 0.06 * np.sin(slow / 2.9)
                     * env, 0.0),
            "head": (lively * 0.06 * np.sin(slow / 1.1 + 0.5) * env, 0.0,
                     lively * 0.05 * np.sin(slow / 2.3) * env),
            "spine3": (0.0, lively * 0.04 * np.sin(slow / 3.1) * env,
                       lively * 0.03 * np.sin(slow / 2.6 + 1.0) * env),
        }
        if lively > 1.0:  # the hands join in: right, then left
            joints.update(_lerp_joints({}, arm("explain"), _bump(t, 0.8, 2.2)))
            joints.update(_lerp_joints({}, mirrored(arm("explain")), _bump(t, 2.3, 3.5)))
        expression = {"lips_part": 0.6 * opening, "smile": 0.25 * env,
                      "brows_raise": lively * 0.25 * max(np.sin(slow / 1.3), 0.0) * env}
        keys.append((t, Pose(joints, expression)))
    keys[0], keys[-1] = (0.0, Pose()), (duration, Pose())
    return Clip(name, tuple(keys))


def _bump(t: float, start: float, end: float, ramp: float = 0.5) -> float:
    """Smoothly 0 -> 1 over [start, start + ramp], 1 -> 0 over [end - ramp, end]."""
    return _envelope(t - start, end - start, ramp) if start <= t <= end else 0.0


# ---------------------------------------------------------------------------------------------
# The registry


def _registry() -> dict[str, MotionSpec]:
    e, g, c = CATEGORIES
    face = {
        "smile": {"smile": 1.0}, "grin": {"grin": 1.0, "smile": 0.3},
        "pucker": {"pucker": 1.0}, "cheeks_puffed": {"cheek_puff": 1.0},
        "eyes_closed": {"blink_left": 1.0, "blink_right": 1.0},
        "brows_raised": {"brows_raise": 1.0},
    }
    jaw = {"mouth_open": (0.35, 0.0, 0.0), "jaw_left": (0.06, 0.16, 0.0),
           "jaw_right": (0.06, -0.16, 0.0)}
    out = {"neutral": MotionSpec(e, _neutral)}
    for name, expression in face.items():
        out[name] = MotionSpec(e, lambda n=name, x=expression: _face(n, x))
    for name, aa in jaw.items():
        out[name] = MotionSpec(e, lambda n=name, aa=aa: _face(n, {"lips_part": 0.6},
                                                               {"jaw": aa}))
    out["sad"], out["angry"] = MotionSpec(e, _sad), MotionSpec(e, _angry)

    hand = {"thumbs_up": ("thumbs_up", "thumbs_up", {"smile": 0.5}),
            "peace": ("sign", "peace", {"smile": 0.4}),
            **{f"number_{i + 1}": ("sign", gesture, {}) for i, gesture in
               enumerate(("point", "peace", "three", "four", "spread"))},
            "letter_L": ("sign", "L", {})}
    for name, (arm_key, gesture, expression) in hand.items():
        out[name] = MotionSpec(g, lambda n=name, a=arm_key, h=gesture, x=expression:
                               _right_hand(n, a, h, x))
    out.update(heart=MotionSpec(g, _heart), clapping=MotionSpec(g, _clapping),
               pointing=MotionSpec(g, _pointing),
               fingertips_pushing=MotionSpec(g, _fingertips_pushing))

    out.update(talk_calm=MotionSpec(c, lambda: _talk("talk_calm", 11, 4.0, 0.16, 1.0)),
               talk_animated=MotionSpec(c, lambda: _talk("talk_animated", 23, 4.0, 0.24, 2.0)),
               nod=MotionSpec(c, _nod), shake_head=MotionSpec(c, _shake_head),
               shrug=MotionSpec(c, _shrug), look_around=MotionSpec(c, _look_around),
               # The arms away from the chest (beside the head, the face, out sideways): the
               # webcam protocol's hands entering and leaving the frame.
               wave=MotionSpec(c, _wave), hands_to_face=MotionSpec(c, _hands_to_face),
               reach_out=MotionSpec(c, _reach_out))
    return out


MOTIONS: Mapping[str, MotionSpec] = MappingProxyType(_registry())


def motion_names(category: str | None = None) -> tuple[str, ...]:
    """Names of the library's motions, all or those of one category (see `CATEGORIES`)."""
    if category is not None and category not in CATEGORIES:
        raise ValueError(f"unknown motion category '{category}'; known: {', '.join(CATEGORIES)}")
    return tuple(n for n, spec in MOTIONS.items() if category in (None, spec.category))


def motion(name: str) -> Clip:
    """The library's clip called `name` (or one of its `ALIASES`)."""
    spec = MOTIONS.get(ALIASES.get(name, name))
    if spec is None:
        known = ", ".join((*MOTIONS, *ALIASES))
        raise ValueError(f"unknown motion '{name}'; known: {known}")
    return spec.make()


def motion_sequence(names: str | Sequence[str], crossfade: float = 0.4) -> Chain:
    """Motions played one after another with eased transitions; `names` is a sequence or a
    comma-separated string ('smile,thumbs_up,talk')."""
    if isinstance(names, str):
        names = [n.strip() for n in names.split(",") if n.strip()]
    if not names:
        raise ValueError("no motion names given")
    return chain("+".join(names), [motion(n) for n in names], crossfade)


def demo_clip() -> Track:
    """The body demo's clip and the render command's 'demo' motion (not among `MOTIONS`):
    gestures and expressions, about eleven seconds long."""
    look = {"neck": (0.0, 0.0, 0.0)}
    wave_up = {"left_shoulder": (0.0, 0.0, 0.35), "left_elbow": (0.0, -0.3, 1.6)}
    wave_a = {**wave_up, "left_wrist": (0.0, 0.0, 0.35)}
    wave_b = {**wave_up, "left_wrist": (0.0, 0.0, -0.35)}
    show = {"right_shoulder": (0.0, 0.0, 1.0), "right_elbow": (0.0, 2.1, 0.0),
            "right_wrist": (-0.3, 0.0, 0.0)}
    face = Clip("face", (
        (0.0, Pose(look)),
        (0.8, Pose(look, {"smile": 1.0})),
        (1.6, Pose({"jaw": (0.35, 0.0, 0.0)}, {"lips_part": 0.8})),
        (2.4, Pose(look, {"blink_left": 1.0, "blink_right": 1.0, "brows_raise": 0.3})),
        (3.0, Pose(look, {"brows_raise": 1.2, "pucker": 0.8})),
        (3.8, Pose({"head": (0.0, 0.45, 0.0)}, {"cheek_puff": 1.0, "brows_lower": 0.8})),
        (4.6, Pose({"head": (0.0, -0.45, 0.1)}, {"frown": 1.0, "grin": 0.0})),
    ))
    hands = Clip("hands", (
        (0.0, Pose(wave_a, left_hand="spread")),
        (0.4, Pose(wave_b, left_hand="spread")),
        (0.8, Pose(wave_a, left_hand="spread")),
        (1.2, Pose(wave_b, {"grin": 0.8}, left_hand="spread")),
        (2.0, Pose(show, {"smile": 0.8}, right_hand="thumbs_up")),
        (2.8, Pose(show, right_hand="peace")),
        (3.6, Pose(show, right_hand="point")),
        (4.4, Pose(show, right_hand="fist")),
        (5.2, Pose(look)),
    ))
    return chain("body demo", [face, hands])


# What a `--motion NAME` may name, besides a file: the engine's own two ('demo': `demo_clip`,
# 'rest': the rest pose) and every library clip and alias (what the server serves).
ENGINE_CLIPS = ("demo", "rest")


def clip_names() -> tuple[str, ...]:
    """Every built-in clip name a `--motion` takes: `ENGINE_CLIPS`, `MOTIONS`, `ALIASES`."""
    return (*ENGINE_CLIPS, *MOTIONS, *ALIASES)


def unknown_clip_message(spec: str, *, files: bool = True) -> str:
    """The error for a `--motion` that is neither a built-in clip nor (``files``) a file."""
    what = "a built-in clip nor a .json / .npz file" if files else "a built-in clip"
    return f"motion {spec!r} is neither {what}; built-in clips: {', '.join(clip_names())}"

