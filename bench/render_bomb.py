"""A render bomb before and after the render cost bound, side by side in one run.

The bomb is an avatar with every value inside ``GaussianRanges``: the synthetic avatar with
every log-scale at 6 (the largest allowed; ``--gaussians N`` repeats its splats up to N),
seen from the default orbit (what a session starts with). "before" renders it with the pair
bound off (``max_tile_pairs`` 2**62: the code path of the rasterizer before the bound, which
allocated every pair), "after" with the server's default ``max_tile_pairs``.

1. **One frame** on the cpu backend, each mode in a fresh process (numba compiled and warmed
   on a small frame first): the frame's time, the process's peak RSS increase during it
   (``/proc/self/clear_refs`` then ``VmHWM``), the (Gaussian, tile) pairs composited and the
   pairs the tile lists allocated.
2. **A server** (``python -m server``, one render thread, the synthetic demo avatar) per
   mode, with the bomb uploaded (its upload checks raised so that it gets in): a well-behaved
   session (``--cheap-size`` px JPEG, driven at 30 Hz) alone, then beside a session
   streaming the bomb at ``--size`` (driven at 30 Hz too); its fps in each phase, the bomb
   session's fps, and the server's peak RSS. Skip with ``--no-server``.

    .venv/bin/python bench/render_bomb.py [--size 1920x1080] [--gaussians 16016]
        [--log-scale 6] [--seconds 20] [--cheap-size 256] [--modes before,after]
        [--no-server]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

UNBOUNDED = 2**62  # "before": no pair bound (every pair allocated, as the code did)
DRIVE_HZ = 30.0
WARMUP_S = 2.0


def default_bound() -> int:
    from server.config import Settings

    return Settings.model_fields["max_tile_pairs"].default


def bomb_package(n: int, log_scale: float):
    """The synthetic avatar's package with every log-scale at ``log_scale``, its splats
    repeated (same parents) up to ``n``."""
    import torch

    from avatar_core.gaussians.loading import load_avatar

    package = load_avatar("synthetic").package
    fields = package.avatar.tensors()
    reps = -(-n // package.avatar.num)
    fields = {k: torch.cat([v] * reps)[:n].clone() for k, v in fields.items()}
    fields["log_scales"][:] = log_scale
    return type(package)(**{**package.__dict__, "avatar": type(package.avatar)(**fields)})


def _status_kib(field: str, pid: str = "self") -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return 0


# -- 1. one frame, in a child process ------------------------------------------------------------


def child(args) -> None:
    import torch

    from avatar_core.body.cache import StageCache
    from avatar_core.gaussians.animate import AvatarAnimator
    from avatar_core.gaussians.loading import load_avatar
    from avatar_core.render.camera_path import framing_target
    from avatar_core.render.rasterize import rasterize
    from avatar_core.render.types import RenderRequest
    from protocol import Orbit, View
    from server.stream.scene import view_camera

    torch.set_num_threads(1)
    loaded = load_avatar("synthetic")
    model = loaded.animator.body_model
    package = bomb_package(args.gaussians, args.log_scale)
    animator = AvatarAnimator(model, package.avatar, betas=loaded.animator.betas,
                              cache=StageCache(enabled=False))
    with torch.no_grad():
        gaussians = animator.pose().gaussians
    w, h = args.size
    chest = framing_target(model.joint_template)
    camera = view_camera(View(orbit=Orbit()), w, h, chest)
    small = view_camera(View(orbit=Orbit()), 64, 64, chest)
    request = RenderRequest(backend="cpu", max_tile_pairs=args.child_bound)
    rasterize(loaded.animator.pose().gaussians, small, request)  # compile, warm up
    Path("/proc/self/clear_refs").write_text("5")  # peak RSS := current RSS
    rss0 = _status_kib("VmRSS")
    t0 = time.perf_counter()
    out = rasterize(gaussians, camera, request)
    seconds = time.perf_counter() - t0
    peak = _status_kib("VmHWM")
    st = out.stats
    print(json.dumps({"seconds": seconds, "peak_mib": (peak - rss0) / 1024,
                      "tile_pairs": st["tile_pairs"], "allocated": st["pairs_allocated"],
                      "rendered": st["n_rendered"], "visible": st["n_visible"]}))


def one_frame(mode: str, bound: int, args) -> dict:
    cmd = [sys.executable, __file__, "--child", str(UNBOUNDED if mode == "before" else bound),
           "--size", f"{args.size[0]}x{args.size[1]}", "--gaussians", str(args.gaussians),
           "--log-scale", str(args.log_scale)]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1",
           "PYTHONPATH": str(ROOT)}
    done = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=args.frame_timeout)
    if done.returncode != 0:
        return {"error": (done.stderr or done.stdout)[-300:].strip() or
                f"exit {done.returncode} (killed?)"}
    return json.loads(done.stdout.strip().splitlines()[-1])


# -- 2. a server ---------------------------------------------------------------------------------


async def _session_fps(client, seconds: float, phase: float) -> float:
    from stream import frames_until, motion_frame, paced

    t0 = time.monotonic()
    measure_from, end = t0 + WARMUP_S, t0 + WARMUP_S + seconds
    driver = asyncio.create_task(paced(
        DRIVE_HZ, end, {}, lambda _: client.drive(motion_frame(time.monotonic() - t0, phase))))
    frames = 0
    try:
        async for _ in frames_until(client, end):
            frames += time.monotonic() >= measure_from
    finally:
        driver.cancel()
    return frames / seconds


async def _measure(url: str, token: str, bomb_id: str, pid: int,
                   args) -> tuple[float, float, float, float]:
    from client import StreamClient

    async with await StreamClient.connect(url, "demo", token, timeout=120,
                                          client_name="cheap") as cheap:
        await cheap.request(width=args.cheap_size, height=args.cheap_size, codec="jpeg",
                            max_fps=30)
        alone = await _session_fps(cheap, args.seconds, 0.0)
        rss_alone = _status_kib("VmHWM", str(pid)) / 1024  # the server's peak so far
        async with await StreamClient.connect(url, bomb_id, token, timeout=120,
                                              client_name="bomb") as big:
            await big.request(width=args.size[0], height=args.size[1], codec="jpeg",
                              max_fps=30)
            shared, bomb = await asyncio.gather(_session_fps(cheap, args.seconds, 0.0),
                                                _session_fps(big, args.seconds, 1.0))
    return alone, shared, bomb, rss_alone


def server_run(mode: str, bound: int, bomb_zip: Path, args) -> dict:
    import httpx
    from stream import start_server, stop_server

    os.environ.update({
        "TELESPLAT_MAX_TILE_PAIRS": str(UNBOUNDED if mode == "before" else bound),
        "TELESPLAT_MAX_AVATAR_TILE_PAIRS": str(UNBOUNDED),  # the bomb gets in
        "TELESPLAT_GAUSSIAN_RANGES": json.dumps({"max_splat_body_ratio": 1e9}),
        "TELESPLAT_TORCH_THREADS": "1", "TELESPLAT_STARTUP_ROOM": "false",
        "TELESPLAT_FAIR_SHARE_WINDOW_S": "2.0"})
    with tempfile.TemporaryDirectory() as tmp:
        proc, url, token = start_server(Path(tmp), 1, 4, "synthetic")
        try:
            with httpx.Client(base_url=url, timeout=300,
                              headers={"Authorization": f"Bearer {token}"}) as c:
                r = c.post("/v1/avatars", content=bomb_zip.read_bytes(),
                           headers={"content-type": "application/zip"})
                r.raise_for_status()
                bomb_id = r.json()["id"]
            alone, shared, bomb, rss_alone = asyncio.run(
                _measure(url, token, bomb_id, proc.pid, args))
            peak = _status_kib("VmHWM", str(proc.pid)) / 1024
            return {"alone": alone, "shared": shared, "bomb": bomb, "peak_mib": peak,
                    "peak_alone_mib": rss_alone, "alive": proc.poll() is None}
        finally:
            stop_server(proc)


# -- main ----------------------------------------------------------------------------------------


def _size(text: str) -> tuple[int, int]:
    w, h = text.lower().split("x")
    return int(w), int(h)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=_size, default=(1920, 1080))
    parser.add_argument("--gaussians", type=int, default=16016)
    parser.add_argument("--log-scale", type=float, default=6.0)
    parser.add_argument("--seconds", type=float, default=20.0, help="measured per phase")
    parser.add_argument("--cheap-size", type=int, default=256)
    parser.add_argument("--modes", default="before,after")
    parser.add_argument("--no-server", action="store_true")
    parser.add_argument("--frame-timeout", type=float, default=600.0)
    parser.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child is not None:
        args.child_bound = args.child
        child(args)
        return 0
    bound = default_bound()
    modes = args.modes.split(",")
    w, h = args.size
    print(f"\n{platform.processor() or platform.machine()}, {os.cpu_count()} cores, load "
          f"{os.getloadavg()[0]:.1f}; bomb: {args.gaussians} Gaussians of log-scale "
          f"{args.log_scale:g} (synthetic avatar), default orbit, {w}x{h}, cpu backend; "
          f"after: max_tile_pairs {bound}\n")
    print("| mode | frame s | peak RSS MiB | pairs composited | pairs allocated | "
          "splats rendered |")
    print("|---|---:|---:|---:|---:|---:|")
    for mode in modes:
        r = one_frame(mode, bound, args)
        if "error" in r:
            print(f"| {mode} | failed: {r['error']} |")
            continue
        print(f"| {mode} | {r['seconds']:.2f} | {r['peak_mib']:.0f} | {r['tile_pairs']:,} | "
              f"{r['allocated']:,} | {r['rendered']:,} of {r['visible']:,} |", flush=True)
    if args.no_server:
        return 0
    from avatar_core.gaussians.package import save_package

    with tempfile.TemporaryDirectory() as tmp:
        bomb_zip = save_package(bomb_package(args.gaussians, args.log_scale),
                                Path(tmp) / "bomb.zip")
        print(f"\nserver, 1 render thread; well-behaved: {args.cheap_size} px JPEG, bomb "
              f"session: {w}x{h} JPEG, both driven at {DRIVE_HZ:g} Hz, {args.seconds:g} s "
              "measured per phase\n")
        print("| mode | well-behaved fps alone | beside the bomb | bomb fps | "
              "server peak RSS MiB, before the bomb session -> after |")
        print("|---|---:|---:|---:|---:|")
        for mode in modes:
            r = server_run(mode, bound, bomb_zip, args)
            print(f"| {mode} | {r['alone']:.1f} | {r['shared']:.1f} | {r['bomb']:.2f} | "
                  f"{r['peak_alone_mib']:.0f} -> {r['peak_mib']:.0f}"
                  f"{'' if r['alive'] else ' (died)'} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
