"""The quality budget's torch reference and its numpy twin choose the same Gaussians."""

import math

import numpy as np
import pytest
import torch

from avatar_core.render.budget import budget_count, drop_over_budget_np, select_rendered
from avatar_core.render.camera import look_at
from avatar_core.render.project_cpu import project_np
from avatar_core.render.projection import Projected
from avatar_core.render.scenes import random_scene

CAM = look_at((0.0, 0.0, 2.5), (0.0, 0.0, 0.0), width=64, height=48, fov_y_deg=40.0)


def test_budget_count():
    assert budget_count(None, 10) == 10
    assert budget_count(3, 10) == 3
    assert budget_count(30, 10) == 10
    assert budget_count(0, 10) == 0
    assert budget_count(0.25, 10) == math.ceil(2.5)
    assert budget_count(1.0, 10) == 10


def _projected(seed: int, n: int = 300):
    """The numba projection of a random scene, as numpy arrays and as a torch ``Projected``
    (both twins then rank the very same numbers)."""
    gs = random_scene(n, seed)
    arrays = project_np(*(t.float().numpy() for t in (gs.means, gs.quats, gs.scales,
                                                        gs.opacities)),
                        CAM.viewmat(), CAM.K, CAM.width, CAM.height)
    m2, co, de, rad, op = arrays
    proj = Projected(means2d=torch.from_numpy(m2), conics=torch.from_numpy(co),
                     depths=torch.from_numpy(de), radii=torch.from_numpy(rad),
                     opacities=torch.from_numpy(op), valid=torch.from_numpy(rad > 0))
    return arrays, proj


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("budget", [None, 0, 1, 17, 10**6, 0.1, 0.5, 1.0])
def test_numpy_twin_keeps_the_reference_selection(seed, budget):
    (_, co, _, rad, op), proj = _projected(seed)
    sel, n_visible = select_rendered(proj, budget)
    radii = rad.copy()
    n_vis_np, n_kept = drop_over_budget_np(co, op, radii, budget)
    assert n_vis_np == n_visible > 0
    assert n_kept == sel.numel()
    assert np.array_equal(np.flatnonzero(radii > 0), sel.numpy())
    # only over-budget Gaussians lose their radius; the kept ones keep theirs
    assert np.array_equal(radii[radii > 0], rad[radii > 0])


def test_ties_keep_the_lower_index():
    conics = np.tile(np.array([[1.0, 0.0, 1.0]], np.float32), (5, 1))
    opacities = np.full(5, 0.5, np.float32)
    radii = np.array([3, 0, 3, 3, 3], np.int32)
    proj = Projected(means2d=torch.zeros(5, 2), conics=torch.from_numpy(conics),
                     depths=torch.ones(5), radii=torch.from_numpy(radii),
                     opacities=torch.from_numpy(opacities), valid=torch.from_numpy(radii > 0))
    sel, _ = select_rendered(proj, 2)
    assert sel.tolist() == [0, 2]
    drop_over_budget_np(conics, opacities, radii, 2)
    assert np.flatnonzero(radii).tolist() == [0, 2]
