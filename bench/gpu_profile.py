"""Where a gsplat frame's time goes: the parts of ``rasterize`` and ``render_views`` timed
apart, beside gsplat alone on the same inputs, plus torch.profiler tables and a host-sync
count. Run by ``bench/gpu_offline.py`` (stage ``profile``) after the gsplat build.

    python bench/gpu_profile.py [--json FILE] [--gaussians 40000] [--views 32]
    python bench/gpu_profile.py --dry-run      # CPU, tiny sizes, the cpu backend

Each part: the median of ``--reps`` synchronised calls after two warm-ups (ms). The parts:

* single (1920x1080): ``rasterize`` whole; our projection's mask alone (``_mask_culled``);
  ``gsplat.rasterization`` alone on the masked inputs; and on the raw Gaussians (the floor);
* views (``--views`` cameras, 512 px): ``render_views`` whole; the kept masks camera by camera
  and batched (``kept_masks_batched``); ``gsplat_views_arguments``; ``rasterization`` alone on
  its arguments;
* training: one trainer step at 512 px (the default recipe), and its profiler table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from avatar_core.render import rasterize, render_views  # noqa: E402
from avatar_core.render.camera import orbit  # noqa: E402
from avatar_core.render.rasterize_gsplat import (  # noqa: E402
    _kept_masks,
    _mask_culled,
    gsplat_arguments,
    gsplat_views_arguments,
    kept_masks_batched,
)
from avatar_core.render.scenes import avatar_camera, avatar_like_scene  # noqa: E402
from avatar_core.render.types import GaussianSet, RenderRequest  # noqa: E402


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def median_ms(fn: Callable[[], object], device: torch.device, reps: int) -> float:
    for _ in range(2):
        fn()
    sync(device)
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        sync(device)
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def host_syncs(fn: Callable[[], object], device: torch.device) -> int:
    """How many synchronising calls one ``fn()`` makes (torch's sync debug mode)."""
    if device.type != "cuda":
        return -1
    fn()
    torch.cuda.synchronize()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            fn()
        finally:
            torch.cuda.set_sync_debug_mode("default")
    return sum("synchroniz" in str(w.message) for w in caught)


def profile_table(fn: Callable[[], object], device: torch.device, rows: int = 14) -> str:
    from torch.profiler import ProfilerActivity, profile

    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    fn()
    sync(device)
    with profile(activities=acts) as prof:
        for _ in range(3):
            fn()
        sync(device)
    avg = prof.key_averages()
    out = [avg.table(sort_by="self_cpu_time_total", row_limit=rows)]
    if device.type == "cuda":
        for key in ("self_device_time_total", "self_cuda_time_total"):
            try:
                out.append(avg.table(sort_by=key, row_limit=rows))
                break
            except Exception:  # noqa: BLE001 - the key's name changed across torch versions
                continue
    return "\n".join(out)


def compiled_mask_ms(g: GaussianSet, cam, req: RenderRequest, device: torch.device,
                     reps: int) -> dict:
    """The mask under ``torch.compile`` (fused kernels; ``reduce-overhead`` adds CUDA graphs):
    ms per call, first-call compile seconds, and whether it equals the eager mask exactly. The
    measured remedy for a launch-bound mask (docs/gpu.md), tried before it is wired in."""
    out: dict = {}
    want, want_n = _mask_culled(g, cam, req)
    for mode in ("default", "reduce-overhead"):
        name = f"mask compiled ({mode})"
        try:
            torch._dynamo.reset()
            fn = torch.compile(_mask_culled, mode=mode, dynamic=False)
            t0 = time.perf_counter()
            got, got_n = fn(g, cam, req)
            sync(device)
            out[f"{name} compile s"] = time.perf_counter() - t0
            same = int(got_n) == int(want_n) and all(
                torch.equal(getattr(got, f.name), getattr(want, f.name))
                for f in dataclasses.fields(want))
            out[f"{name} equals eager"] = float(same)
            out[name] = median_ms(lambda fn=fn: fn(g, cam, req), device, reps)
        except Exception as exc:  # noqa: BLE001 - a compile failure is a finding, not a crash
            print(f"## {name}: {type(exc).__name__}: {exc}", flush=True)
            out[name] = -1.0
    torch._dynamo.reset()
    return out


def single(g: GaussianSet, device: torch.device, backend: str, reps: int,
           size: tuple[int, int]) -> tuple[dict, str]:
    cam = avatar_camera(*size)
    req = RenderRequest(outputs=("rgb",), backend=backend)
    parts = {"rasterize": lambda: rasterize(g, cam, req),
             "mask (our projection)": lambda: _mask_culled(g, cam, req)}
    if backend == "gsplat":
        from gsplat import rasterization

        masked, _ = _mask_culled(g, cam, req)
        parts["gsplat on masked inputs"] = lambda: rasterization(
            **gsplat_arguments(masked, cam, req, 3))
        parts["gsplat on the raw Gaussians"] = lambda: rasterization(
            **gsplat_arguments(g, cam, req, 3))
    with torch.no_grad():
        ms = {k: median_ms(f, device, reps) for k, f in parts.items()}
        ms.update(compiled_mask_ms(g, cam, req, device, reps))
        ms["host syncs in rasterize"] = host_syncs(parts["rasterize"], device)
        table = profile_table(parts["rasterize"], device)
    return ms, table


def views(g: GaussianSet, device: torch.device, backend: str, n: int,
          reps: int, px: int) -> tuple[dict, str]:
    cams = [orbit((0.0, 0.35, 0.0), yaw, 5.0, 2.6, width=px, height=px)
            for yaw in torch.linspace(-80, 80, n).tolist()]
    req = RenderRequest(outputs=("rgb",), backend=backend)
    parts = {"render_views": lambda: render_views(g, cams, req),
             "masks camera by camera": lambda: _kept_masks(
                 g, cams, dataclasses.replace(req, budget=1.0)),
             "masks batched": lambda: kept_masks_batched(g, cams, req),
             "gsplat_views_arguments": lambda: gsplat_views_arguments(g, cams, req, 3)}
    if backend == "gsplat":
        from gsplat import rasterization

        kw, _ = gsplat_views_arguments(g, cams, req, 3)
        parts["gsplat alone on those arguments"] = lambda: rasterization(**kw)
    with torch.no_grad():
        ms = {k: median_ms(f, device, reps) for k, f in parts.items()}
        ms["host syncs in render_views"] = host_syncs(parts["render_views"], device)
        table = profile_table(parts["render_views"], device)
    return ms, table


def training(device: torch.device, resolution: int, steps: int,
             warm: int = 20) -> tuple[dict, str]:
    from avatar_core.dataset import load_dataset
    from avatar_core.synth.capture import CaptureSpec, capture
    from avatar_core.synth.model_writer import write_synthetic_models
    from avatar_core.train.config import preset
    from avatar_core.train.trainer import Trainer

    with tempfile.TemporaryDirectory(prefix="telesplat-gpu-profile-") as tmp:
        files = write_synthetic_models(Path(tmp) / "models", seed=0)
        spec = CaptureSpec(sequences=(("smile",),), num_cameras=4, resolution=resolution,
                           max_frames=2, supersample=1, cross_identity=None)
        data = load_dataset(capture(Path(tmp) / "capture", spec, model_dir=files.root))
        base = preset("default")
        config = dataclasses.replace(
            base, iterations=steps * 4 + 40, device=device.type,
            data=dataclasses.replace(base.data, crop_to_subject=False))
        trainer = Trainer(data, config, Path(tmp) / "out", body_model=files.root,
                          device_resident=device.type == "cuda")
        for _ in range(warm):  # views prepared, frames posed, kernels loaded
            trainer.step()
        ms = {"trainer.step": median_ms(trainer.step, device, steps),
              "host syncs in a step": host_syncs(trainer.step, device),
              "gaussians": int(trainer.gaussians.num) if hasattr(trainer, "gaussians") else -1}
        table = profile_table(trainer.step, device, rows=20)
    return ms, table


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, default=40000)
    ap.add_argument("--views", type=int, default=32)
    ap.add_argument("--reps", type=int, default=30)
    ap.add_argument("--train-steps", type=int, default=15)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--dry-run", action="store_true", help="CPU, tiny sizes, cpu backend")
    args = ap.parse_args(argv)
    cuda = torch.cuda.is_available() and not args.dry_run
    device = torch.device("cuda" if cuda else "cpu")
    backend = "gsplat" if cuda else "cpu"
    size, px = ((1920, 1080), 512) if not args.dry_run else ((192, 108), 64)
    n, nv, reps = ((args.gaussians, args.views, args.reps) if not args.dry_run
                   else (2000, 3, 2))
    g = avatar_like_scene(n, 0)
    g = GaussianSet(*(t.to(device) for t in (g.means, g.quats, g.scales, g.opacities, g.sh)))
    report: dict = {"device": torch.cuda.get_device_name() if cuda else "cpu",
                    "torch": torch.__version__, "gaussians": n, "views": nv}
    sections = [(f"single {size[0]}x{size[1]}", lambda: single(g, device, backend, reps, size)),
                (f"{nv} views of {px} px", lambda: views(g, device, backend, nv, reps, px))]
    if cuda or args.dry_run:
        res = 64 if args.dry_run else 512
        sections.append((f"training {res} px",
                         lambda: training(device, res, 2 if args.dry_run else args.train_steps,
                                          warm=1 if args.dry_run else 20)))
    for name, run in sections:
        try:
            ms, table = run()
        except Exception as exc:  # noqa: BLE001 - one broken part must not hide the others
            report[name] = {"error": f"{type(exc).__name__}: {exc}"}
            print(f"## {name}: {type(exc).__name__}: {exc}", flush=True)
            continue
        report[name] = ms
        print(f"## {name}")
        for k, v in ms.items():
            print(f"  {k:40s} {v:10.3f}")
        print(table, flush=True)
    line = json.dumps(report)
    if args.json:
        args.json.write_text(line + "\n")
    print(line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
