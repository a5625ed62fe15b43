"""Time SSIM forward and forward+backward (the D-SSIM training loss) on CPU.

Variants, run interleaved in one process so their ratios are meaningful on a noisy machine:
`ssim` with the separable 11-tap filter, valid and same padding; the 3DGS-style reference
(one 11 x 11 grouped conv per moment, zero padding), to show what the separable filter saves;
and `l1` for scale. float32 images [B, H, W, 3]; median of `--repeats` calls after 2 warm-ups.

    .venv/bin/python bench/metrics.py [--size 512] [--batch 1] [--repeats 20]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from avatar_core.metrics.image import gaussian_kernel, l1, ssim  # noqa: E402


def ssim_2d_window(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """3DGS's utils/loss_utils.ssim on [B, H, W, C] images (full 2-D window per moment)."""
    x, y = pred.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2)  # [B, C, H, W]
    c = x.shape[1]
    g = gaussian_kernel(dtype=x.dtype)
    window = (g[:, None] @ g[None, :]).expand(c, 1, 11, 11).contiguous()  # [C, 1, 11, 11]

    def conv(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(t, window, padding=5, groups=c)

    mx, my = conv(x), conv(y)
    vx, vy, cxy = conv(x * x) - mx**2, conv(y * y) - my**2, conv(x * y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    smap = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2))
    return smap.mean()


VARIANTS: dict[str, Callable[[torch.Tensor, torch.Tensor], torch.Tensor]] = {
    "ssim, separable, valid": lambda p, g: ssim(p, g),
    "ssim, separable, same": lambda p, g: ssim(p, g, padding="same"),
    "ssim, 11x11 window (3DGS)": ssim_2d_window,
    "l1": lambda p, g: l1(p, g),
}


def bench(size: int, batch: int, repeats: int) -> dict[str, tuple[float, float]]:
    gen = torch.Generator().manual_seed(0)
    target = torch.rand(batch, size, size, 3, generator=gen)
    pred = (target + 0.05 * torch.randn(target.shape, generator=gen)).clamp(0, 1)
    times: dict[str, tuple[list[float], list[float]]] = {k: ([], []) for k in VARIANTS}
    for i in range(repeats + 2):
        for name, fn in VARIANTS.items():
            with torch.no_grad():
                t0 = time.perf_counter()
                fn(pred, target)
                t1 = time.perf_counter()
            x = pred.clone().requires_grad_(True)
            t2 = time.perf_counter()
            fn(x, target).backward()
            t3 = time.perf_counter()
            if i >= 2:  # warm-up
                times[name][0].append((t1 - t0) * 1e3)
                times[name][1].append((t3 - t2) * 1e3)
    return {k: (statistics.median(f), statistics.median(b)) for k, (f, b) in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    print(f"# {args.batch} x {args.size} x {args.size} x 3 float32, "
          f"{torch.get_num_threads()} torch threads, torch {torch.__version__}, "
          f"{platform.processor() or platform.machine()}")
    print("| variant | forward (ms) | forward + backward (ms) |")
    print("|---|---:|---:|")
    for name, (fwd, both) in bench(args.size, args.batch, args.repeats).items():
        print(f"| {name} | {fwd:.2f} | {both:.2f} |")


if __name__ == "__main__":
    main()
