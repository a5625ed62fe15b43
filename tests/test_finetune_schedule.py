"""Fine-tuning rates scaled to the run (FineTuneConfig.schedule = "budget")."""

import math

import pytest

from avatar_core.train.config import (
    ConfigError,
    FineTuneConfig,
    config_from_dict,
    config_to_dict,
)
from avatar_core.train.optim import DEFAULT_PARAM_LRS


def test_fixed_keeps_the_papers_rates_throughout():
    cfg = FineTuneConfig()
    assert cfg.schedule == "fixed"
    for it in (1, 500, 2_000):
        assert cfg.lrs_at(it, 2_000, 80) == dict(DEFAULT_PARAM_LRS)


@pytest.mark.parametrize(("iterations", "frames"), [(2_000, 80), (600, 3), (50_000, 1_000)])
def test_budget_rates_let_each_delta_travel_its_reach(iterations, frames):
    cfg = FineTuneConfig(schedule="budget", start=0.25, final=0.1)
    rates = [cfg.lrs_at(it, iterations, frames) for it in range(1, iterations + 1)]
    first = math.floor(0.25 * iterations)
    assert all(v == 0.0 for r in rates[:first] for v in r.values())  # Gaussians settle first
    # each iteration updates one frame's delta: a frame's share of all steps is 1 / frames
    per_frame = {k: sum(r[k] for r in rates) / frames for k in cfg.lrs()}
    for key, reach in cfg.reach().items():
        assert per_frame[key] == pytest.approx(reach, rel=0.02), key
    active = rates[first:]
    assert active[-1]["body_pose"] == pytest.approx(0.1 * active[0]["body_pose"])
    decay = [r["expression"] for r in active]
    assert all(a >= b for a, b in zip(decay[:-1], decay[1:], strict=True))


def test_budget_rates_scale_with_the_run_length():
    cfg = FineTuneConfig(schedule="budget")
    short = cfg.lrs_at(1_000, 1_000, 100)["body_pose"]
    long = cfg.lrs_at(10_000, 10_000, 100)["body_pose"]
    assert short == pytest.approx(10 * long)
    # the paper's rate would move a pose by 0.002 deg in 5,000 iterations over 120 frames
    assert cfg.lrs_at(1_001, 5_000, 120)["body_pose"] > 100 * DEFAULT_PARAM_LRS["body_pose"]


def test_a_run_shorter_than_the_frames_still_reaches_at_most_reach():
    cfg = FineTuneConfig(schedule="budget", start=0.0, final=1.0)
    total = sum(cfg.lrs_at(it, 10, 1_000)["transl"] for it in range(1, 11))
    assert total == pytest.approx(10 * cfg.reach_transl)  # <= reach per frame drawn once


@pytest.mark.parametrize(("changes", "key"), [
    ({"schedule": "cosine"}, "finetune.schedule"), ({"start": 1.0}, "finetune.start"),
    ({"final": 0.0}, "finetune.final"), ({"reach_transl": -1.0}, "finetune.transl"),
    ({"reach_body_pose_deg": float("nan")}, "finetune.body_pose")])
def test_bad_schedules_are_refused_by_name(changes, key):
    with pytest.raises(ConfigError, match=key):
        FineTuneConfig(**changes)


def test_schedule_round_trips_through_a_config_file_dict():
    cfg = config_from_dict({"preset": "quick", "finetune": {"schedule": "budget",
                                                            "reach_expression": 0.5}})
    assert cfg.finetune.schedule == "budget" and cfg.finetune.reach_expression == 0.5
    assert config_from_dict(config_to_dict(cfg)) == cfg
    with pytest.raises(ValueError, match="frames and iterations"):
        cfg.finetune.lrs_at(1, 100, 0)


def test_the_trainer_follows_the_budget_schedule(synthetic_files, tmp_path):
    """Rates zero while the Gaussians settle, then the schedule's; the deltas then move by
    about the rate per update (Adam), and only from then."""
    import dataclasses

    import torch

    from avatar_core.synth.capture import CaptureSpec, capture
    from avatar_core.train.config import preset
    from avatar_core.train.trainer import Trainer

    spec = CaptureSpec(sequences=(("smile",),), num_cameras=3, resolution=32, max_frames=2,
                       supersample=1, cross_identity=None)
    data = capture(tmp_path / "d", spec, model_dir=synthetic_files.root)
    base = preset("test")
    cfg = dataclasses.replace(base, iterations=20, densify=dataclasses.replace(
        base.densify, enabled=False), finetune=FineTuneConfig(schedule="budget", start=0.5))
    trainer = Trainer(data, cfg, tmp_path / "out", body_model=synthetic_files.root)
    assert trainer.num_frames == 2
    trainer.train(stop_at=10)
    moved = [float(d.detach().abs().max()) for s in trainer.deltas.values() for d in s.values()]
    assert max(moved) == 0.0  # nothing moves during the first half
    trainer.train(stop_at=11)
    want = cfg.finetune.lrs_at(11, 20, 2)
    got = {g["name"].rsplit("/", 1)[1]: g["lr"] for g in trainer.param_optimizer.param_groups}
    assert got == want and want["body_pose"] > 0
    pose = trainer.deltas["smile"]["body_pose"]
    assert 0 < float(pose.detach().abs().max()) <= 1.5 * want["body_pose"]
    assert torch.isfinite(pose).all()
