"""What accuracy costs in time, at render time: the Gaussian budget.

Renders the untrained synthetic avatar (one Gaussian per triangle, plus denser copies to reach
the asked count) at a front camera with the cpu backend, keeping the K most important Gaussians
(opacity x footprint) for K from 10% to 100%, and reports PSNR against the full render next to
milliseconds per frame. Writes a Markdown table and a PNG plot.

    .venv/bin/python bench/render_budget.py [--gaussians 20000] [--size 512] [--out docs]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from avatar_core.gaussians.animate import AvatarAnimator, synthetic_package  # noqa: E402
from avatar_core.gaussians.avatar import GaussianAvatar  # noqa: E402
from avatar_core.render.camera import look_at  # noqa: E402
from avatar_core.render.rasterize import rasterize  # noqa: E402
from avatar_core.render.types import RenderRequest  # noqa: E402
from avatar_core.synth.model_writer import ensure_models  # noqa: E402


def densify(avatar: GaussianAvatar, count: int, seed: int = 0) -> GaussianAvatar:
    """Spread `count` Gaussians over the triangles (random in-triangle offsets, smaller discs)."""
    g = torch.Generator().manual_seed(seed)
    reps = max(1, int(np.ceil(count / avatar.num)))
    idx = torch.arange(avatar.num).repeat(reps)[:count]
    t = avatar.tensors()
    local = t["local_means"][idx] + torch.randn(count, 3, generator=g) * torch.tensor(
        [0.25, 0.25, 0.02])
    shrink = float(np.log(np.sqrt(avatar.num / count))) if count > avatar.num else 0.0
    return GaussianAvatar(parents=t["parents"][idx], local_means=local,
                          log_scales=t["log_scales"][idx] + shrink, quats=t["quats"][idx],
                          opacity_logits=t["opacity_logits"][idx], sh=t["sh"][idx])


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a - b) ** 2).mean())
    return float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--gaussians", type=int, default=20000)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--backend", default="cpu")
    parser.add_argument("--out", type=Path, default=Path("docs"))
    args = parser.parse_args()
    files = ensure_models()
    package, model = synthetic_package(files.root)
    avatar = densify(package.avatar, args.gaussians)
    animator = AvatarAnimator(model, avatar, betas=np.asarray(package.body.betas))
    head = model.joint_template[15].numpy()
    cam = look_at(eye=(0.0, head[1] - 0.1, 1.6), target=(0.0, head[1] - 0.3, 0.0),
                  width=args.size, height=args.size, fov_y_deg=40.0)
    with torch.no_grad():
        gs = animator.pose({}).gaussians
        full = rasterize(gs, cam, RenderRequest(backend=args.backend, background=(1, 1, 1))).rgb
        rows = []
        for frac in (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0):
            req = RenderRequest(backend=args.backend, background=(1, 1, 1), budget=frac)
            times = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                out = rasterize(gs, cam, req)
                times.append((time.perf_counter() - t0) * 1e3)
            rows.append((frac, int(round(frac * gs.num)), statistics.median(times),
                         psnr(out.rgb, full)))
    print(f"# budget trade-off: {gs.num} Gaussians, {args.size}^2, backend {args.backend}, "
          f"{torch.get_num_threads()} threads")
    print("| budget | Gaussians | ms / frame | PSNR vs full (dB) |")
    print("|---:|---:|---:|---:|")
    for frac, k, ms, p in rows:
        print(f"| {frac:.0%} | {k} | {ms:.1f} | {'inf' if p == float('inf') else f'{p:.1f}'} |")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
    finite = [(ms, p, frac) for frac, _, ms, p in rows if np.isfinite(p)]
    ax.plot([r[0] for r in finite], [r[1] for r in finite], "o-")
    for ms, p, frac in finite:
        ax.annotate(f"{frac:.0%}", (ms, p), textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax.set_xlabel("milliseconds per frame")
    ax.set_ylabel("PSNR against the full render (dB)")
    ax.set_title(f"Gaussian budget: {gs.num} splats, {args.size}x{args.size}, {args.backend}")
    ax.grid(alpha=0.3)
    args.out.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(args.out / "render_budget.png")
    print(f"plot: {args.out / 'render_budget.png'}")


if __name__ == "__main__":
    main()
