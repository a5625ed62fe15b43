"""Simulated trackers: the body tracker alone is off, fusing FLAME and MANO restores the truth."""

import numpy as np
import torch

from avatar_core.body.fusion import fuse
from avatar_core.body.models import MANOModel, SMPLXModel
from avatar_core.motion.library import motion_sequence
from avatar_core.motion.rig import model_rig
from avatar_core.synth.trackers import simulate_trackers


def _split(sim):
    body = {k: v for k, v in sim.items() if not k.startswith(("flame_", "mano_"))}
    flame = {k[6:]: v for k, v in sim.items() if k.startswith("flame_")}
    hands = {s: {k[len(f"mano_{s}_"):]: v for k, v in sim.items() if k.startswith(f"mano_{s}_")}
             for s in ("left", "right")}
    return body, flame, hands


def test_fusion_of_simulated_trackers_recovers_the_truth(synthetic_files, smplx_data, mano_data):
    model = SMPLXModel(smplx_data, dtype=torch.float64)
    rig = model_rig(synthetic_files, model)
    track = motion_sequence("heart,smile,talk_calm,shrug")
    frames = [track.sample(t, rig) for t in np.linspace(0, track.duration, 16)]
    truth = {k: np.stack([p[k] for p in frames]) for k in frames[0]}
    sim = simulate_trackers(truth, smplx_data.hand_components, rng=np.random.default_rng(0))
    body, flame, hands = _split(sim)
    manos = {s: MANOModel(mano_data[s], dtype=torch.float64) for s in ("left", "right")}
    fused = fuse(body, model, flame=flame, left_hand=hands["left"], right_hand=hands["right"],
                 mano_models=manos)
    with torch.no_grad():
        v_true = model(truth).vertices
        v_fused = model(fused).vertices
        v_body = model(body).vertices
    assert (v_true - v_fused).norm(dim=-1).max() < 1e-9
    # The body tracker alone misses the face and the fingers by centimetres.
    assert (v_true - v_body).norm(dim=-1).max() > 0.01
    assert not body["expression"].any() and not body["jaw_pose"].any()


def test_hands_keep_only_the_first_pca_components(smplx_data):
    rng = np.random.default_rng(1)
    t = 3
    truth = {"betas": np.zeros(10), "expression": rng.normal(size=(t, 10)),
             "global_orient": rng.normal(0, 0.2, (t, 3)),
             "body_pose": rng.normal(0, 0.2, (t, 21, 3)),
             "jaw_pose": rng.normal(0, 0.1, (t, 3)), "leye_pose": np.zeros((t, 3)),
             "reye_pose": np.zeros((t, 3)), "transl": np.zeros((t, 3)),
             "left_hand_pose": rng.normal(0, 0.3, (t, 15, 3)),
             "right_hand_pose": rng.normal(0, 0.3, (t, 15, 3))}
    comps = smplx_data.hand_components
    sim0 = simulate_trackers(truth, comps, hand_pca=0, noise_deg=0, rng=rng)
    assert not sim0["right_hand_pose"].any()
    full = simulate_trackers(truth, comps, hand_pca=45, noise_deg=0, rng=rng)
    np.testing.assert_allclose(full["left_hand_pose"], truth["left_hand_pose"], atol=1e-9)
    np.testing.assert_allclose(full["body_pose"], truth["body_pose"])  # no noise asked
