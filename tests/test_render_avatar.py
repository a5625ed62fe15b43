"""The real avatar through both backends: the cpu rasterizer matches the torch reference."""

import numpy as np
import torch

from avatar_core.gaussians.animate import AvatarAnimator, synthetic_package
from avatar_core.render.camera import look_at
from avatar_core.render.rasterize import rasterize
from avatar_core.render.types import RenderRequest


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a - b) ** 2).mean())
    return float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)


def test_cpu_matches_torch_on_the_posed_synthetic_avatar(synthetic_files):
    package, model = synthetic_package(synthetic_files.root, identity=1)
    animator = AvatarAnimator(model, package.avatar, betas=np.asarray(package.body.betas))
    head = model.joint_template[15].numpy()
    cam = look_at(eye=(0.3, head[1], 1.2), target=head - np.array([0, 0.25, 0]),
                  width=72, height=56, fov_y_deg=40.0)
    params = {"jaw_pose": [0.3, 0.0, 0.0], "expression": np.linspace(-1, 1, 10),
              "body_pose": np.random.default_rng(0).normal(0, 0.2, (21, 3))}
    with torch.no_grad():
        gaussians = animator.pose(params).gaussians
        outs = {b: rasterize(gaussians, cam, RenderRequest(outputs=("rgb", "alpha", "depth"),
                                                            background=(1, 1, 1), backend=b))
                for b in ("cpu", "torch")}
    assert outs["cpu"].alpha.mean() > 0.2  # the avatar fills a good part of the frame
    assert _psnr(outs["cpu"].rgb, outs["torch"].rgb) >= 50.0
    assert torch.allclose(outs["cpu"].alpha, outs["torch"].alpha, atol=1e-4)
    covered = outs["torch"].alpha > 0.5
    assert torch.allclose(outs["cpu"].depth[covered], outs["torch"].depth[covered], rtol=1e-4)
