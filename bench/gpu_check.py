"""The GPU figures of docs/gpu.md: issue 15's targets, measured on the CUDA machine.

    python bench/gpu_check.py [--out docs/gpu.md] [--json FILE] [--seconds 6]
                              [--avatar synthetic]
    python bench/gpu_check.py --dry-run --out /tmp/gpu.md   # CPU, tiny sizes: the script only

``make gpu-check`` runs it after the ``gpu`` tests (offline: bench/gpu_offline.py, with
``--seconds`` from what its deadline leaves). Four measurements, each against its target:

1. render: ``rasterize`` of a 40k-Gaussian avatar-like scene (render/scenes.py, the shared
   test scene; pass ``--package`` for a trained avatar's Gaussians) at 1920x1080 on gsplat,
   frames per second over ``--frames`` synchronised renders (target >= 300); plus
   ``render_views`` of 32 distinct 512 px views in one call against 32 single calls (the
   batching the server uses for room viewers);
2. drive -> frame: one session of a server on loopback (``python -m server``, gsplat, JPEG
   1920x1080, the encoders it chose), lockstep drives, p95 of the time from sending a drive
   to receiving the frame that shows it (target <= 20 ms);
3. viewers: one room, a performer driving at 30 Hz and 32 viewers at distinct views (512 px
   JPEG, batched rendering on), fps per viewer (target: each >= 30 x 0.95);
4. training: the trainer (the default recipe) on CUDA at 512x512 per view (a synthetic
   capture, the whole image: no crop to the subject), iterations per second after a warm-up
   (target >= 40).

Beside them, measured in the same run (bench/gpu_ratios.py): gsplat against our cpu backend on
the same scene, batched against one-by-one views, nvJPEG against OpenCV JPEG, the
device-resident training step against the host-checked one. ``--seconds`` bounds each timed
measurement (the two server runs, each training mode, each side of a ratio), so the whole run
takes about a minute of fixed costs (server start, capture, warm-ups) plus 8 x ``--seconds``.

The result replaces the part of ``--out`` between the gpu-check markers (the rest of the file
is kept), with the GPU's name (``torch.cuda.get_device_name``) and the date. Without CUDA it
exits 2 ("no CUDA device") unless ``--dry-run``, which runs every part on the CPU at tiny
sizes against nothing (targets are not judged) so that the script itself is tested; its ratio
table compares what exists there (the cpu backend against the torch reference). ``--json``
also writes every number measured.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import datetime
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import gpu_ratios  # noqa: E402
import rooms as rooms_bench  # noqa: E402
from stream import motion_frame, percentile, start_server, stop_server  # noqa: E402

from avatar_core.render import rasterize, render_views  # noqa: E402
from avatar_core.render.camera import orbit  # noqa: E402
from avatar_core.render.scenes import avatar_camera, avatar_like_scene  # noqa: E402
from avatar_core.render.types import GaussianSet, RenderRequest  # noqa: E402
from client import StreamClient  # noqa: E402
from client.rest import RestClient  # noqa: E402

BEGIN, END = "<!-- gpu-check:begin -->", "<!-- gpu-check:end -->"
TARGETS = {"render_fps": 300.0, "latency_p95_ms": 20.0, "viewers": 32, "viewer_fps": 30.0,
           "train_its": 40.0}


@dataclasses.dataclass
class Sizes:
    gaussians: int = 40_000
    width: int = 1920
    height: int = 1080
    frames: int = 200
    views: int = 32
    view_size: int = 512
    viewers: int = 32
    train_resolution: int = 512
    train_iterations: int = 200
    seconds: float = 6.0  # each timed measurement at most (the frame counts bound them too)

    @classmethod
    def dry(cls) -> Sizes:
        return cls(gaussians=500, width=64, height=48, frames=3, views=3, view_size=32,
                   viewers=2, train_resolution=32, train_iterations=3, seconds=1.0)


_sync = gpu_ratios.sync


def _on(g: GaussianSet, device: torch.device) -> GaussianSet:
    return GaussianSet(*(t.to(device) for t in (g.means, g.quats, g.scales, g.opacities, g.sh)))


def _package_gaussians(path: str) -> GaussianSet:
    """A trained avatar's Gaussians at rest pose (world space)."""
    from avatar_core.gaussians.loading import load_avatar

    loaded = load_avatar(path)
    return loaded.animator.pose({}).gaussians


def measure_render(s: Sizes, device: torch.device, backend: str, g: GaussianSet
                   ) -> dict[str, float]:
    req = RenderRequest(outputs=("rgb",), backend=backend)
    cam = avatar_camera(s.width, s.height)
    with torch.no_grad():
        for _ in range(2):  # warm-up (kernels compiled / loaded)
            rasterize(g, cam, req)
        fps = gpu_ratios.rate(lambda: rasterize(g, cam, req), device, s.frames, s.seconds)
        cams = [orbit((0.0, 0.08, 0.0), -60.0 + 120.0 * i / max(1, s.views - 1), 5.0, 2.0,
                      width=s.view_size, height=s.view_size, fov_y_deg=30.0)
                for i in range(s.views)]
        render_views(g, cams, req)
        rasterize(g, cams[0], req)  # both paths warm
        _sync(device)
        t0 = time.perf_counter()
        render_views(g, cams, req)
        _sync(device)
        batched = time.perf_counter() - t0
        t0 = time.perf_counter()
        for cam_i in cams:
            rasterize(g, cam_i, req)
        _sync(device)
        single = time.perf_counter() - t0
    return {"render_fps": fps, "gaussians": g.num, "views_per_s_batched": s.views / batched,
            "views_per_s_single": s.views / single}


async def _latency(url: str, token: str, s: Sizes) -> list[float]:
    out = []
    async with await StreamClient.connect(url, "demo", token, timeout=120,
                                          client_name="gpu-check") as client:
        await client.request(width=s.width, height=s.height, codec="jpeg",
                             max_fps=client.limits.max_fps)
        t0 = time.monotonic()
        warm_until, end = t0 + 1.0, t0 + 1.0 + s.seconds
        while time.monotonic() < end:  # bounded by the deadline
            sent = time.monotonic()
            seq = await client.drive(motion_frame(sent - t0, 0.0))
            await client.wait_frame(seq, timeout=30)
            if sent >= warm_until:
                out.append(1000 * (time.monotonic() - sent))
    return out


async def _viewers(url: str, token: str, pid: int, s: Sizes) -> list[float]:
    rest = RestClient(url, token)
    room, watch = rooms_bench.new_room(rest, 1)
    people: list[rooms_bench.Participant] = []
    try:
        performer = await rooms_bench.join_room(url, token, room, "perform", 0, "performer")
        people.append(rooms_bench.Participant(
            await rooms_bench.setup(performer, s.view_size, {"yaw_deg": 0.0}), "performer",
            drives=True))
        for i in range(s.viewers):
            client = await rooms_bench.join_room(url, watch, room, "watch", None, f"viewer-{i}")
            yaw = -80.0 + 160.0 * i / max(1, s.viewers - 1)
            people.append(rooms_bench.Participant(
                await rooms_bench.setup(client, s.view_size, {"yaw_deg": yaw}), f"viewer-{i}",
                drives=False))
        run = await rooms_bench.measure(people, pid, s.seconds, TARGETS["viewer_fps"])
        return run.fps("viewer")
    finally:
        await rooms_bench.close_all(people)
        rest.delete_room(room)


def measure_server(s: Sizes, backend: str, avatar: str) -> dict[str, float]:
    os.environ["TELESPLAT_BACKEND"] = backend
    os.environ["TELESPLAT_DEFAULT_MAX_FPS"] = str(TARGETS["viewer_fps"])
    with tempfile.TemporaryDirectory(prefix="telesplat-gpu-check-") as tmp:
        proc, url, token = start_server(Path(tmp), 2, s.viewers + 4, avatar)
        try:
            lat = asyncio.run(_latency(url, token, s))
            fps = asyncio.run(_viewers(url, token, proc.pid, s))
        finally:
            stop_server(proc)
    return {"latency_p50_ms": percentile(lat, 50), "latency_p95_ms": percentile(lat, 95),
            "viewer_fps_mean": float(np.mean(fps)) if fps else 0.0,
            "viewer_fps_min": min(fps) if fps else 0.0, "viewers": len(fps)}


def measure_training(s: Sizes, device: torch.device) -> dict:
    """it/s of the trainer's default step on ``device`` (device-resident on CUDA) and of the
    other mode, on one synthetic capture; each timed for ``s.seconds`` at most."""
    from avatar_core.dataset import load_dataset
    from avatar_core.synth.capture import CaptureSpec, capture
    from avatar_core.synth.model_writer import write_synthetic_models
    from avatar_core.train.config import preset
    from avatar_core.train.trainer import Trainer

    with tempfile.TemporaryDirectory(prefix="telesplat-gpu-train-") as tmp:
        files = write_synthetic_models(Path(tmp) / "models", seed=0)
        spec = CaptureSpec(sequences=(("smile",),), num_cameras=4,
                           resolution=s.train_resolution, max_frames=2, supersample=1,
                           cross_identity=None)
        data = load_dataset(capture(Path(tmp) / "capture", spec, model_dir=files.root))
        base = preset("default")  # the seed's recipe (its densification starts later)
        warm = min(20, s.train_iterations)
        config = dataclasses.replace(
            base, iterations=warm + s.train_iterations + 1, device=device.type,
            data=dataclasses.replace(base.data, crop_to_subject=False))

        def its_per_s(device_resident: bool) -> float:
            out = Path(tmp) / f"out-{device_resident}"
            trainer = Trainer(data, config, out, body_model=files.root,
                              device_resident=device_resident)
            for _ in range(warm):  # views prepared, frames posed, kernels loaded
                trainer.step()
            return gpu_ratios.rate(trainer.step, device, s.train_iterations, s.seconds)

        ratio = gpu_ratios.training_modes(its_per_s, s.train_resolution)
    default = ratio.fast_rate if device.type == "cuda" else ratio.slow_rate
    return {"train_its": default, "train_ratio": ratio}


def measure_ratios(s: Sizes, device: torch.device, backend: str, g: GaussianSet,
                   m: dict) -> list[gpu_ratios.Ratio]:
    """The render and JPEG pairs, and the two ratios measured with the figures."""
    cam = avatar_camera(s.width, s.height)
    slow = "cpu" if backend == "gsplat" else "torch"
    return [
        gpu_ratios.render_backends(g, cam, backend, m["render_fps"], slow, s.frames,
                                   s.seconds),
        gpu_ratios.Ratio(f"{s.views} views of {s.view_size} px", "one render_views call",
                         m["views_per_s_batched"], "one rasterize each",
                         m["views_per_s_single"], "views/s"),
        gpu_ratios.jpeg_encoders(s.width, s.height, device, s.frames, s.seconds),
        m["train_ratio"],
    ]


def _row(name: str, target: str, value: float, unit: str, ok: bool | None) -> str:
    shown = "n/a" if value is None or (isinstance(value, float) and math.isnan(value)) \
        else f"{value:.1f} {unit}".strip()
    verdict = "" if ok is None else ("yes" if ok else "**no**")
    return f"| {name} | {target} | {shown} | {verdict} |"


def report(m: dict, s: Sizes, device_name: str, dry: bool) -> str:
    judge = (lambda ok: None) if dry else (lambda ok: bool(ok))  # noqa: E731
    date = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    lines = [
        BEGIN,
        f"Measured by `make gpu-check` on **{device_name}**, {date}"
        + (" (dry run on the CPU at tiny sizes: not the figures)" if dry else "") + ".",
        f"torch {torch.__version__}; sizes: {s.gaussians} Gaussians at {s.width}x{s.height}, "
        f"{s.viewers} viewers at {s.view_size} px, training at {s.train_resolution} px.",
        "",
        "| figure | target | measured | met |",
        "|---|---|---|---|",
        _row("render fps (1080p, 40k Gaussians)", ">= 300", m["render_fps"], "fps",
             judge(m["render_fps"] >= TARGETS["render_fps"])),
        _row("drive -> frame p95, loopback", "<= 20 ms", m["latency_p95_ms"], "ms",
             judge(m["latency_p95_ms"] <= TARGETS["latency_p95_ms"])),
        _row(f"{s.viewers} viewers of distinct views: min fps", ">= 30 each",
             m["viewer_fps_min"], "fps",
             judge(m["viewers"] >= TARGETS["viewers"]
                   and m["viewer_fps_min"] >= 0.95 * TARGETS["viewer_fps"])),
        _row("training it/s at 512x512", ">= 40", m["train_its"], "it/s",
             judge(m["train_its"] >= TARGETS["train_its"])),
        "",
        f"Also: drive -> frame p50 {m['latency_p50_ms']:.1f} ms; viewers' mean fps "
        f"{m['viewer_fps_mean']:.1f}; {s.views} views of {s.view_size} px in one "
        f"`render_views` call {m['views_per_s_batched']:.0f} views/s against "
        f"{m['views_per_s_single']:.0f} views/s one call each (ratio "
        f"{m['views_per_s_batched'] / m['views_per_s_single']:.2f}).",
        "",
        "Ratios measured in the same run, each pair on the same input:",
        "",
        *gpu_ratios.table(m["ratios"], dry),
        END,
    ]
    return "\n".join(lines)


def write_section(path: Path, section: str) -> None:
    """Replace the marked section of ``path`` (kept otherwise), or append it."""
    text = path.read_text() if path.exists() else "# GPU\n"
    if BEGIN in text and END in text:
        head, rest = text.split(BEGIN, 1)
        tail = rest.split(END, 1)[1]
        text = head + section + tail
    else:
        text = text.rstrip("\n") + "\n\n" + section + "\n"
    path.write_text(text)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "gpu.md")
    parser.add_argument("--json", type=Path, default=None, help="also write every number here")
    parser.add_argument("--seconds", type=float, default=None,
                        help="each timed measurement at most (default 6, dry 1)")
    parser.add_argument("--avatar", default="synthetic", help="the server's demo avatar")
    parser.add_argument("--package", default=None, help="render a trained avatar package")
    parser.add_argument("--dry-run", action="store_true",
                        help="CPU, tiny sizes, targets not judged (tests the script)")
    args = parser.parse_args(argv)
    if not args.dry_run and not torch.cuda.is_available():
        print("gpu_check: no CUDA device (torch.cuda.is_available() is False); run it on a "
              "CUDA machine, or with --dry-run to test the script", file=sys.stderr)
        return 2
    sizes = Sizes.dry() if args.dry_run else Sizes()
    if args.seconds is not None:
        sizes = dataclasses.replace(sizes, seconds=args.seconds)
    device = torch.device("cpu" if args.dry_run else "cuda")
    backend = "cpu" if args.dry_run else "gsplat"
    name = "CPU (dry run)" if args.dry_run else torch.cuda.get_device_name(device)
    g = avatar_like_scene(sizes.gaussians, 0) if args.package is None \
        else _package_gaussians(args.package)
    g = _on(g, device)
    m: dict = {}
    t0 = time.perf_counter()
    m.update(measure_render(sizes, device, backend, g))
    print(f"render: {m['render_fps']:.1f} fps ({time.perf_counter() - t0:.0f} s)", flush=True)
    m.update(measure_server(sizes, backend, args.avatar))
    print(f"server: p95 {m['latency_p95_ms']:.1f} ms, viewers min {m['viewer_fps_min']:.1f} fps"
          f" ({time.perf_counter() - t0:.0f} s)", flush=True)
    m.update(measure_training(sizes, device))
    print(f"training: {m['train_its']:.1f} it/s ({time.perf_counter() - t0:.0f} s)", flush=True)
    m["ratios"] = measure_ratios(sizes, device, backend, g, m)
    for r in m["ratios"]:
        print(f"ratio {r.what}: {r.value:.2f} {r.why_not}".rstrip(), flush=True)
    write_section(args.out, report(m, sizes, name, args.dry_run))
    print(f"wrote {args.out} ({time.perf_counter() - t0:.0f} s)")
    if args.json is not None:
        write_json(args.json, m, sizes, name, args.dry_run)
        print(f"wrote {args.json}")
    return 0


def write_json(path: Path, m: dict, s: Sizes, device_name: str, dry: bool) -> None:
    def number(v: float) -> float | None:  # NaN is not JSON: what was not measured is null
        return None if isinstance(v, float) and math.isnan(v) else v

    figures = {k: number(v) for k, v in m.items() if isinstance(v, int | float)}
    ratios = [{k: number(v) for k, v in (dataclasses.asdict(r) | {"ratio": r.value}).items()}
              for r in m["ratios"]]
    doc = {"device": device_name, "dry_run": dry, "torch": torch.__version__,
           "sizes": dataclasses.asdict(s), "figures": figures, "targets": TARGETS,
           "ratios": ratios}
    path.write_text(json.dumps(doc, indent=1, allow_nan=False) + "\n")


if __name__ == "__main__":
    sys.exit(main())
