"""Arms out of view: an arm with nothing observed below its shoulder is held, then eased to
rest (`SequenceFitConfig.hold_arms`, `observations.arm_seen`), and BlazePose's arm points on
the image's border are unused (`without_edge_arm_points`)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from avatar_core.body.skeleton import JOINT
from avatar_core.gaussians.animate import synthetic_package
from avatar_core.synth.model_writer import ensure_models
from avatar_core.track.fit import correspondence as cor
from avatar_core.track.fit.camera import WebcamCamera
from avatar_core.track.fit.fitter import neutral_params
from avatar_core.track.fit.observations import (
    POSE_ARM_POINTS,
    arm_seen,
    empty_observations,
    without_edge_arm_points,
)
from avatar_core.track.fit.sequence import SequenceFit, SequenceFitConfig
from avatar_core.track.fit.synthetic import synthetic_observations

CAMERA = WebcamCamera(640, 480, 60.0)
LEFT_ARM_ROWS = [cor.POSE_SLICE.start + i for i in POSE_ARM_POINTS["left"]]


def _hide_left_arm(obs):
    """`obs` with nothing of the left arm below the shoulder: its pose points unused (NaN,
    as a tracker leaves them) and its hand not seen."""
    out = dataclasses.replace(obs, pixels=obs.pixels.copy(), weights=obs.weights.copy(),
                              seen=dict(obs.seen))
    out.pixels[LEFT_ARM_ROWS] = np.nan
    out.weights[LEFT_ARM_ROWS] = 0.0
    out.weights[cor.LEFT_HAND_SLICE] = 0.0
    out.seen["left_hand"] = False
    return out


def test_an_arm_is_seen_by_anything_below_its_shoulder():
    obs = empty_observations((640, 480))
    assert not arm_seen(obs, "left") and not arm_seen(obs, "right")
    obs.weights[cor.POSE_SLICE.start + 13] = 1.0  # the left elbow
    assert arm_seen(obs, "left") and not arm_seen(obs, "right")
    obs.seen["right_hand"] = True
    assert arm_seen(obs, "right")


def test_arm_points_on_the_border_are_dropped_and_nothing_else():
    obs = empty_observations((640, 480))
    rows = {name: cor.POSE_SLICE.start + i for name, i in
            (("l_elbow", 13), ("r_elbow", 14), ("l_wrist", 15), ("l_shoulder", 11))}
    obs.pixels[rows["l_elbow"]] = (300, 475)     # on the bottom edge
    obs.pixels[rows["r_elbow"]] = (320, 400)     # well inside
    obs.pixels[rows["l_wrist"]] = (2, 200)       # on the left edge
    obs.pixels[rows["l_shoulder"]] = (300, 478)  # not an arm point: kept
    obs.weights[list(rows.values())] = 1.0
    out = without_edge_arm_points(obs, 0.02 * 640)
    assert out.weights[rows["l_elbow"]] == 0 and out.weights[rows["l_wrist"]] == 0
    assert out.weights[rows["r_elbow"]] == 1 and out.weights[rows["l_shoulder"]] == 1
    assert (obs.weights[list(rows.values())] == 1).all()  # the input untouched
    assert without_edge_arm_points(obs, 0.0) is obs
    obs.pixels[rows["r_elbow"]] = np.nan  # a NaN point (unused) is no border point
    obs.weights[rows["r_elbow"]] = 0.0
    out = without_edge_arm_points(obs, 12.8)
    assert out.weights[rows["r_elbow"]] == 0 and out.weights[rows["l_shoulder"]] == 1


def test_bad_arm_settings_are_refused(setup):
    from avatar_core.track.fit.fitter import FitConfig

    model, betas = setup
    with pytest.raises(ValueError, match="edge_margin"):
        SequenceFit(model, betas, SequenceFitConfig(edge_margin=0.6))
    with pytest.raises(ValueError, match="arm_prior"):
        SequenceFit(model, betas, SequenceFitConfig(fit=FitConfig(arm_prior=float("nan"))))
    with pytest.raises(ValueError, match="arm_prior"):
        SequenceFit(model, betas, SequenceFitConfig(fit=FitConfig(arm_prior=-1.0)))


@pytest.fixture(scope="module")
def setup():
    files = ensure_models()
    package, model = synthetic_package(files.root, 0)
    return model, np.asarray(package.body.betas)


def _raised(model) -> dict[str, np.ndarray]:
    p = neutral_params(model)
    p["transl"] = np.array([0.0, -0.35, -0.9])
    p["body_pose"][JOINT["left_shoulder"] - 1] = [0.0, 0.3, -0.4]
    p["body_pose"][JOINT["left_elbow"] - 1] = [0.0, -1.4, 0.0]
    return p


def test_an_arm_out_of_view_holds_then_eases_to_rest(setup):
    model, betas = setup
    cfg = SequenceFitConfig(hold_s=0.5, relax_s=1.0, smoothing=False, gaze=False,
                            hold_arms=True)
    rows = [JOINT[j] - 1 for j in ("left_shoulder", "left_elbow")]
    fit = SequenceFit(model, betas, cfg)
    obs, _ = synthetic_observations(fit.fitter, _raised(model), CAMERA)
    fit.step(obs, 0.0)
    fitted = fit.current["body_pose"][rows].copy()
    assert np.abs(fitted - neutral_params(model)["body_pose"][rows]).max() > 0.5
    hidden = _hide_left_arm(obs)
    held = fit.step(hidden, 0.3).params["body_pose"][rows]
    np.testing.assert_allclose(held, fitted)  # within hold_s: the last confident state
    for t in np.arange(0.4, 2.0, 0.1):
        fit.step(hidden, float(t))
    rest = fit.step(hidden, 2.0).params["body_pose"][rows]
    np.testing.assert_allclose(rest, neutral_params(model)["body_pose"][rows], atol=1e-12)
    # A frame with nothing at all, then the arm back in view: it follows the fit again.
    assert fit.step(empty_observations((640, 480)), 2.1).fit is None
    back = fit.step(obs, 2.2).params["body_pose"][rows]
    assert np.abs(back - rest).max() > 0.1
    # Off (the default): the unobserved arm stays wherever the fit leaves it.
    free = SequenceFit(model, betas, dataclasses.replace(cfg, hold_arms=False))
    free.step(obs, 0.0)
    for t in np.arange(0.1, 2.0, 0.1):
        free.step(hidden, float(t))
    drift = free.step(hidden, 2.0).params["body_pose"][rows]
    assert np.abs(drift - neutral_params(model)["body_pose"][rows]).max() > 0.1
