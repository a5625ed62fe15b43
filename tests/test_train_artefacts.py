"""The recipe's fixes for the demo avatar's artefacts (issue 26), on a tiny synthetic capture:
lower-body pixels supervised as background (the hem), a random background per iteration
(floaters), unseen triangles coloured from their neighbours (armpits), and that the fixes
keep a resumed run identical to an uninterrupted one."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from avatar_core.dataset import load_dataset
from avatar_core.synth.capture import CaptureSpec, capture
from avatar_core.train.config import ConfigError, DataConfig, config_from_dict, preset
from avatar_core.train.data import composite, loss_weights, prepare_view
from avatar_core.train.posing import fill_unseen_colors
from avatar_core.train.trainer import Trainer


@pytest.fixture(scope="module")
def dataset(synthetic_files, tmp_path_factory):
    out = tmp_path_factory.mktemp("artefacts") / "capture"
    spec = CaptureSpec(sequences=(("smile",),), num_cameras=4, resolution=64, max_frames=2,
                       supersample=1, cross_identity=None)
    return load_dataset(capture(out, spec, model_dir=synthetic_files.root))


def _lower(view) -> np.ndarray:
    return (view.parts >= 0) & ~view.upper_body_mask


def test_lower_body_as_background_supervises_the_legs_as_empty(dataset):
    view = dataset.view(*dataset.views("train")[0])
    lower = _lower(view)
    assert lower.any()
    bg = (0.2, 0.4, 0.6)
    ignore = prepare_view(view, DataConfig(background=bg, crop_to_subject=False), "cpu")
    empty = prepare_view(view, DataConfig(background=bg, crop_to_subject=False,
                                          lower_body="background"), "cpu")
    # ignored: weight 0 there; as background: weight 1 and the background colour
    assert (ignore.weight.numpy()[lower] == 0).all()
    assert (empty.weight.numpy()[lower] == 1).all()
    assert np.allclose(empty.target.numpy()[lower], bg)
    assert (empty.alpha.numpy()[lower] == 0).all()
    # the 1 px rim grown onto the other pixels (mixed colours) stays out of the loss
    rim = (loss_weights(view.parts, view.upper_body_ids, lower.shape) == 0) & ~lower
    assert rim.any() and (empty.weight.numpy()[rim] == 0).all()
    # everything else is untouched
    rest = ~lower & ~rim
    assert torch.equal(empty.target[torch.from_numpy(rest)],
                       ignore.target[torch.from_numpy(rest)])
    # the crop still frames the upper body only
    a = prepare_view(view, DataConfig(), "cpu")
    b = prepare_view(view, DataConfig(lower_body="background"), "cpu")
    assert a.crop == b.crop


def test_a_view_recomposited_on_another_background_is_the_composite_there(dataset):
    view = dataset.view(*dataset.views("train")[1])
    prepared = prepare_view(view, DataConfig(crop_to_subject=False), "cpu")
    other = (0.1, 0.9, 0.3)
    expected = composite(view.rgb, view.alpha, other)
    assert np.allclose(prepared.on_background(other).numpy(), expected, atol=1e-6)
    assert prepared.on_background(prepared.background) is prepared.target


@pytest.mark.parametrize("values, key", [
    ({"data": {"lower_body": "legs"}}, "data.lower_body"),
    ({"data": {"random_background": 1}}, "data.random_background"),
    ({"init_unseen": "black"}, "init_unseen"),
])
def test_bad_artefact_options_name_the_key(values, key):
    with pytest.raises(ConfigError, match=key):
        config_from_dict({"preset": "test", **values})


def _config(**data):
    cfg = preset("test")
    return dataclasses.replace(
        cfg, iterations=12, checkpoint_interval=6, data=dataclasses.replace(cfg.data, **data),
        densify=dataclasses.replace(cfg.densify, from_iter=3, interval=3,
                                    opacity_reset_interval=9))


def test_random_background_is_drawn_per_iteration_from_the_seed(dataset, synthetic_files,
                                                                tmp_path):
    fixed = Trainer(dataset, _config(), tmp_path / "f", body_model=synthetic_files.root)
    assert {fixed.background(i) for i in range(1, 6)} == {fixed.config.data.background}
    rand = Trainer(dataset, _config(random_background=True), tmp_path / "r",
                   body_model=synthetic_files.root)
    colours = [rand.background(i) for i in range(1, 50)]
    assert len(set(colours)) == len(colours)
    assert all(0 <= c <= 1 for rgb in colours for c in rgb)
    assert colours == [rand.background(i) for i in range(1, 50)]  # no hidden state
    spread = np.asarray(colours)
    assert spread.min() < 0.1 and spread.max() > 0.9  # the whole range, not near white


def test_the_fixes_train_and_resume_bit_identically(dataset, synthetic_files, tmp_path):
    cfg = _config(random_background=True, lower_body="background")
    straight = Trainer(dataset, cfg, tmp_path / "a", body_model=synthetic_files.root)
    straight.train()
    first = Trainer(dataset, cfg, tmp_path / "b", body_model=synthetic_files.root)
    assert first.train(stop_at=6) is None
    resumed = Trainer.resume(tmp_path / "b", dataset)
    resumed.train()
    for k in straight.state:
        assert torch.equal(straight.state[k], resumed.state[k]), k
    assert straight.skipped == 0


def test_unseen_triangles_take_their_neighbours_colour_within_their_part():
    # a strip of 6 triangles over vertices 0..7 (each shares an edge with the next); parts
    # 0 0 0 0 | 1 1; only the first and the last are seen
    faces = np.array([[i, i + 1, i + 2] for i in range(6)])
    parts = np.array([0, 0, 0, 0, 1, 1])
    nan = [np.nan] * 3
    colors = np.array([[1.0, 0.0, 0.0], nan, nan, nan, nan, [0.0, 0.0, 1.0]])
    out = fill_unseen_colors(colors, faces, parts)
    assert np.isfinite(out).all()
    assert np.allclose(out[:4], [1.0, 0.0, 0.0])  # part 0 from its red triangle only
    assert np.allclose(out[4:], [0.0, 0.0, 1.0])  # part 1 from its blue one
    assert np.array_equal(out[[0, 5]], colors[[0, 5]])  # seen ones untouched
    # a part no view saw stays NaN (the caller makes it grey); so do triangles out of reach
    lonely = fill_unseen_colors(colors, faces, np.array([0, 0, 0, 2, 1, 1]))
    assert np.isnan(lonely[3]).all() and np.isfinite(np.delete(lonely, 3, 0)).all()
    ring = fill_unseen_colors(colors, faces, parts, max_rings=1)
    assert np.isfinite(ring[1]).all() and np.isnan(ring[3]).all()


def test_training_starts_unseen_triangles_from_their_neighbours(dataset, synthetic_files,
                                                                tmp_path):
    from avatar_core.gaussians.avatar import DEFAULT_COLOR
    from avatar_core.render.sh import rgb_to_sh0

    grey = rgb_to_sh0(torch.tensor(DEFAULT_COLOR))
    still_grey = {}
    for mode in ("grey", "neighbours"):
        cfg = dataclasses.replace(_config(), init_unseen=mode)
        trainer = Trainer(dataset, cfg, tmp_path / mode, body_model=synthetic_files.root)
        still_grey[mode] = int((trainer.state["sh0"][:, 0] == grey).all(1).sum())
    assert still_grey["grey"] > 0  # 4 cameras leave triangles unseen
    assert still_grey["neighbours"] < still_grey["grey"] / 10
