"""Keyframed clips: complete parameters, eased interpolation, clear errors."""

import numpy as np
import pytest

from avatar_core.motion.keyframes import Clip, Pose, Rig, chain, pose_to_params

RIG = Rig(("smile", "blink_left"), {"relaxed": np.zeros((15, 3)), "fist": np.ones((15, 3))},
          {"left": np.zeros((15, 3)), "right": np.zeros((15, 3))})


def test_pose_to_params_is_complete_and_mirrors_the_left_hand():
    p = pose_to_params(Pose({"jaw": (0.3, 0, 0), "neck": (0, 0.2, 0)}, {"smile": 1.0},
                            left_hand="fist"), RIG)
    assert p["body_pose"].shape == (21, 3) and p["jaw_pose"][0] == 0.3
    assert p["expression"].tolist() == [1.0, 0.0]
    assert np.allclose(p["left_hand_pose"], np.tile([1.0, -1.0, -1.0], (15, 1)))


def test_sampling_eases_between_keyframes_and_clamps():
    clip = Clip("c", ((0.0, Pose()), (1.0, Pose(expression={"smile": 1.0}))))
    values = [clip.sample(t, RIG)["expression"][0] for t in np.linspace(-1, 2, 31)]
    assert values[0] == 0.0 and values[-1] == 1.0
    assert all(b >= a for a, b in zip(values, values[1:], strict=False))
    assert clip.sample(0.5, RIG)["expression"][0] == pytest.approx(0.5)


def test_chain_and_errors():
    a = Clip("a", ((0.0, Pose()), (1.0, Pose())))
    c = chain("ab", [a, a])
    assert c.duration == pytest.approx(2.4)
    with pytest.raises(ValueError):
        Clip("bad", ((0.5, Pose()),))
    with pytest.raises(KeyError, match="unknown joint"):
        pose_to_params(Pose({"tail": (0, 0, 0)}), RIG)
    with pytest.raises(KeyError, match="unknown gesture"):
        pose_to_params(Pose(right_hand="wave"), RIG)
