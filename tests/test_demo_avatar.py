"""The demo avatar of `make run`: built by the real pipeline (capture -> train -> package) on
first use, returned from the cache afterwards. A tiny recipe keeps the test to seconds."""

import json

import numpy as np

import avatar_core.demo
from avatar_core.demo import DEMO_VERSION, DemoRecipe, ensure_demo_avatar
from avatar_core.gaussians.loading import load_avatar
from avatar_core.gaussians.package import save_package
from avatar_core.pipeline import render_frames
from avatar_core.render.camera import orbit
from avatar_core.render.types import RenderRequest
from avatar_core.train.config import preset

TINY = DemoRecipe(motions="smile", resolution=48, frames=2, preset="test", iterations=12)


def test_demo_avatar_built_once_then_cached(tmp_path, synthetic_files):
    events = []
    path = ensure_demo_avatar(tmp_path, lambda *e: events.append(e), TINY,
                              model_dir=synthetic_files.root)
    stages = {stage for stage, _, _ in events}
    assert stages == {"capture", "train"}
    assert events[-1] == ("train", 12, 12)
    manifest = json.loads((path / "avatar.json").read_text())
    assert manifest["metadata"]["trained"] is True
    assert manifest["metadata"]["demo_version"] == DEMO_VERSION
    assert not (tmp_path / ".avatar-staging").exists()

    again = []
    assert ensure_demo_avatar(tmp_path, lambda *e: again.append(e), TINY,
                              model_dir=synthetic_files.root) == path
    assert again == []  # cached: no capture, no training

    loaded = load_avatar(str(path), synthetic_files.root)
    target = loaded.animator.body_model.joint_template[12].cpu().numpy()
    cam = orbit(target, yaw_deg=0.0, pitch_deg=0.0, distance=2.7, width=64, height=64,
                fov_y_deg=30.0)
    (img,) = render_frames(loaded, [{}], [cam], RenderRequest())
    assert img.shape == (64, 64, 3) and np.ptp(img) > 50  # the avatar is in the picture


def test_the_servers_trained_demo_comes_from_the_demo_cache(tmp_path, monkeypatch,
                                                           synthetic_files):
    """`demo_avatar = "trained"`: the registry never trains (the server builds it in the
    background, tests/test_demo_build.py); it takes the demo cache's package when the builder
    has put one there (here an untrained package installed as the builder installs it), and
    registers the synthetic stand-in otherwise."""
    from avatar_core.demo import install_package
    from server.registry import DEMO_ID, AvatarRegistry

    def never(*args, **kwargs):
        raise AssertionError("the registry must not build the demo avatar")

    monkeypatch.setattr(avatar_core.demo, "ensure_demo_avatar", never)
    cache = tmp_path / "cache"
    registry = AvatarRegistry(tmp_path / "avatars", body_models=synthetic_files.root)
    stand_in = registry.register_demo("trained", cache=cache)
    assert stand_in.id == DEMO_ID
    assert stand_in.metadata["trained"] is False and stand_in.metadata["stand_in"] is True

    package = save_package(load_avatar("synthetic", synthetic_files.root).package,
                           tmp_path / "built")
    install_package(cache, package)
    record = registry.register_demo("trained", cache=cache)
    assert record.id == DEMO_ID and record.owner == "public"
    assert record.source == "demo:trained" and record.metadata["trained"] is True


def test_demo_preset_is_a_compressed_quick_schedule():
    demo, quick = preset("demo"), preset("quick")
    assert demo.iterations < quick.iterations
    d = demo.densify
    assert d.from_iter < d.until_iter <= demo.iterations
    assert demo.lr.position_max_steps == demo.iterations
    assert demo.finetune.enabled and demo.data.fusion  # the full recipe, shorter
    # with the fixes for the demo's artefacts (issue 26)
    assert demo.data.lower_body == "background" and not demo.data.random_background
    assert d.opacity_reset_interval > demo.iterations  # no reset: it cleared the armpits
