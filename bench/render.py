"""Time the Gaussian rasterizer backends on an avatar-like scene: ms per frame, forward and
forward + backward, for 5k / 20k / 100k Gaussians at 256^2, 512^2 and 1024^2.

The scene (``avatar_core.render.scenes.avatar_like_scene``) puts the Gaussians on an upper
body of ellipsoids, 3 mm to 2 cm across, mostly opaque, SH degree 3, framed from 2 m with a
30 degree field of view. "forward" renders rgb without autograd (the streaming case);
"forward + backward" renders rgb from parameters that need gradients and back-propagates a
loss to them. Medians of several runs after a warm-up; backends run in the same process, so
the cpu/torch ratio is measured under the same conditions. Torch-reference cells expected to
take more than ``--budget`` seconds per frame are skipped (estimated from the previous cells'
time per evaluated pixel-splat pair).

    .venv/bin/python bench/render.py [--quick] [--budget 20] [--seconds 4]

Beside a busy machine: ``--hog N`` runs it next to N busy-loop processes; ``--wait-compare``
instead times the cpu backend's forward pass (20k Gaussians at 512x512, the streaming case) at
1 and 2 threads with OpenMP's wait policy ACTIVE and PASSIVE (a fresh process each,
interleaved passes; bench/waitpolicy.py):

    .venv/bin/python bench/render.py --wait-compare --hog 2 [--passes 3]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numba
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from avatar_core.render.rasterize import available_backends, rasterize  # noqa: E402
from avatar_core.render.rasterize_torch import isect_tiles  # noqa: E402
from avatar_core.render.scenes import avatar_camera, avatar_like_scene  # noqa: E402
from avatar_core.render.types import GaussianSet, RenderRequest  # noqa: E402
from bench import waitpolicy  # noqa: E402

FULL = [(n, s) for n in (5_000, 20_000, 100_000) for s in (256, 512, 1024)]
QUICK = [(5_000, 256), (20_000, 512)]
BWD_FACTOR = 4.0  # torch reference: forward + backward / forward, for the estimate


def _to(gs: GaussianSet, device: str) -> GaussianSet:
    return GaussianSet(*(t.to(device) for t in (gs.means, gs.quats, gs.scales, gs.opacities,
                                                gs.sh)))


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def _median_ms(run, device: str, seconds: float, warm: bool) -> float:
    """Median wall time of ``run()``: at least 3 runs within ``seconds`` (up to 15); a run
    slower than 3 s is timed once (the torch reference at large sizes)."""
    if warm:
        run()  # numba compile, caches
    times: list[float] = []
    while True:
        _sync(device)
        t0 = time.perf_counter()
        run()
        _sync(device)
        times.append(time.perf_counter() - t0)
        if times[0] > 3.0 or len(times) >= 15 or (len(times) >= 3 and sum(times) >= seconds):
            return statistics.median(times) * 1e3


def time_forward(gs, cam, backend, device, seconds, warm=True):
    req = RenderRequest(backend=backend)

    def run():
        with torch.no_grad():
            rasterize(gs, cam, req)
    return _median_ms(run, device, seconds, warm)


def time_forward_backward(gs, cam, backend, device, seconds, warm=True):
    req = RenderRequest(backend=backend)

    def run():
        params = [t.detach().clone().requires_grad_() for t in
                  (gs.means, gs.quats, gs.scales, gs.opacities, gs.sh)]
        rasterize(GaussianSet(*params), cam, req).rgb.mean().backward()
    return _median_ms(run, device, seconds, warm)


def torch_work(gs, cam) -> float:
    """Pixel-splat evaluations of the dense reference: pairs x 256 pixels per tile."""
    from avatar_core.render.projection import project_gaussians

    viewmat, K = cam.to_torch()
    with torch.no_grad():
        p = project_gaussians(gs.means, gs.quats, gs.scales, gs.opacities, viewmat, K,
                              cam.width, cam.height)
        _, ids = isect_tiles(p.means2d, p.radii, p.depths, cam.width, cam.height)
    return float(ids.numel()) * 256.0


def fmt(ms: float | None) -> str:
    if ms is None:
        return "skipped (> budget)"
    return f"{ms:,.1f}" if ms < 10_000 else f"{ms:,.0f}"


def ratio(a: float | None, b: float | None) -> str:
    return "-" if a is None or b is None else f"{a / b:,.0f}x"


def wait_child(seconds: float) -> None:
    """cpu forward, 20k Gaussians at 512x512 (warmed up): frames per second."""
    ms = time_forward(avatar_like_scene(20_000, seed=0), avatar_camera(512), "cpu", "cpu",
                      seconds)
    waitpolicy.report(1e3 / ms, "frames/s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="only 5k @ 256^2 and 20k @ 512^2")
    ap.add_argument("--budget", type=float, default=20.0,
                    help="skip torch cells estimated above this many seconds per frame")
    ap.add_argument("--seconds", type=float, default=4.0, help="timing time per cell")
    ap.add_argument("--hog", type=int, default=0, help="busy-loop processes beside the bench")
    ap.add_argument("--wait-compare", action="store_true",
                    help="1 and 2 threads x OMP_WAIT_POLICY ACTIVE / PASSIVE, one case")
    ap.add_argument("--passes", type=int, default=3, help="--wait-compare: interleaved passes")
    ap.add_argument("--wait-child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.wait_child:
        wait_child(args.seconds)
        return
    if args.wait_compare:
        print(f"cpu forward, 20k Gaussians at 512x512, beside {args.hog} busy loop(s), "
              f"{os.cpu_count()} cores", flush=True)
        print(waitpolicy.compare([str(Path(__file__).resolve()), "--seconds",
                                  str(args.seconds)], passes=args.passes, hog=args.hog))
        return
    with waitpolicy.hogs(args.hog):
        run_bench(args)


def run_bench(args: argparse.Namespace) -> None:

    backends = available_backends()
    print(f"# Rasterizer benchmark ({platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} CPUs, torch {torch.__version__} with {torch.get_num_threads()} "
          f"threads, numba {numba.__version__} with {numba.get_num_threads()} threads)\n")
    print("ms per frame, median; fwd = rgb without autograd, fwd+bwd = with gradients; "
          "speed-up = torch ms / cpu ms\n")
    cols = ["Gaussians", "image", "torch fwd", "cpu fwd", "speed-up", "torch fwd+bwd",
            "cpu fwd+bwd", "speed-up"]
    if "gsplat" in backends:
        cols += ["gsplat fwd", "gsplat fwd+bwd"]
    print("| " + " | ".join(cols) + " |")
    print("|" + "|".join("---:" if i > 1 else "---" for i in range(len(cols))) + "|")

    sec_per_unit = {"fwd": None, "bwd": None}  # torch reference, refined as cells complete
    for n, size in (QUICK if args.quick else FULL):
        gs = avatar_like_scene(n, seed=0)
        cam = avatar_camera(size)
        row: dict[str, float | None] = {}
        row["cpu fwd"] = time_forward(gs, cam, "cpu", "cpu", args.seconds)
        row["cpu fwd+bwd"] = time_forward_backward(gs, cam, "cpu", "cpu", args.seconds)

        units = torch_work(gs, cam)
        est_f = units * sec_per_unit["fwd"] if sec_per_unit["fwd"] else 0.0
        est_b = units * sec_per_unit["bwd"] if sec_per_unit["bwd"] else est_f * BWD_FACTOR
        row["torch fwd"] = row["torch fwd+bwd"] = None
        if est_f <= args.budget:
            row["torch fwd"] = time_forward(gs, cam, "torch", "cpu", 0.0, warm=False)
            sec_per_unit["fwd"] = row["torch fwd"] / 1e3 / units
            est_b = max(est_b, row["torch fwd"] / 1e3 * 2.0)
        if row["torch fwd"] is not None and est_b <= args.budget:
            row["torch fwd+bwd"] = time_forward_backward(gs, cam, "torch", "cpu", 0.0,
                                                         warm=False)
            sec_per_unit["bwd"] = row["torch fwd+bwd"] / 1e3 / units

        if "gsplat" in backends:
            g = _to(gs, "cuda")
            row["gsplat fwd"] = time_forward(g, cam, "gsplat", "cuda", args.seconds)
            row["gsplat fwd+bwd"] = time_forward_backward(g, cam, "gsplat", "cuda",
                                                          args.seconds)
        cells = [f"{n // 1000}k", f"{size}x{size}", fmt(row["torch fwd"]), fmt(row["cpu fwd"]),
                 ratio(row["torch fwd"], row["cpu fwd"]), fmt(row["torch fwd+bwd"]),
                 fmt(row["cpu fwd+bwd"]), ratio(row["torch fwd+bwd"], row["cpu fwd+bwd"])]
        if "gsplat" in backends:
            cells += [fmt(row["gsplat fwd"]), fmt(row["gsplat fwd+bwd"])]
        print("| " + " | ".join(cells) + " |", flush=True)

    print("\nTarget (cpu, 20k @ 512x512, 2 cores): fwd <= 25 ms (40 fps), "
          "fwd+bwd <= 100 ms (10 per second).")


if __name__ == "__main__":
    main()
