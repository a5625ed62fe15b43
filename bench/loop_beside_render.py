"""How late an asyncio event loop wakes while another thread renders back to back: does the
renderer (the CPU backend's numba kernels, torch) keep the GIL from the loop that carries the
server's sessions and voices?

    NUMBA_NUM_THREADS=2 .venv/bin/python bench/loop_beside_render.py [--size 512]
        [--gaussians 20000] [--seconds 5]

Prints the renders done and the loop's wake lateness (2 ms sleeps): median, p99 and max ms,
without and then with the rendering thread.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import threading
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from avatar_core.render.rasterize import rasterize  # noqa: E402
from avatar_core.render.scenes import avatar_camera, avatar_like_scene  # noqa: E402
from avatar_core.render.types import RenderRequest  # noqa: E402

SLEEP_S = 0.002


async def lateness(seconds: float) -> np.ndarray:
    """ms each 2 ms sleep woke past its time, for ``seconds``."""
    late = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        t0 = time.monotonic()
        await asyncio.sleep(SLEEP_S)
        late.append((time.monotonic() - t0 - SLEEP_S) * 1e3)
    return np.asarray(late)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--gaussians", type=int, default=20_000)
    ap.add_argument("--seconds", type=float, default=5.0)
    args = ap.parse_args()
    scene, camera = avatar_like_scene(args.gaussians), avatar_camera(args.size, args.size)
    request = RenderRequest()
    with torch.no_grad():
        rasterize(scene, camera, request)  # compiled and warm
    stop = threading.Event()
    renders = [0]

    def render_loop() -> None:
        with torch.no_grad():
            while not stop.is_set():
                rasterize(scene, camera, request)
                renders[0] += 1

    print("| rendering thread | renders | loop wake late ms: median / p99 / max |")
    print("|---|---:|---|")
    for rendering in (False, True):
        thread = threading.Thread(target=render_loop) if rendering else None
        renders[0] = 0
        stop.clear()
        if thread:
            thread.start()
        late = asyncio.run(lateness(args.seconds))
        stop.set()
        if thread:
            thread.join()
        print(f"| {'yes' if rendering else 'no'} | {renders[0]} | {np.median(late):.1f} / "
              f"{np.percentile(late, 99):.1f} / {late.max():.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
