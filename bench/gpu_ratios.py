"""The ratios that bench/gpu_check.py measures beside its figures, each pair in the same run on
the same input: our GPU path against the CPU (or host) path it replaces.

* render: gsplat against our ``cpu`` backend on the same scene and camera (on a dry run, with
  no GPU: the ``cpu`` backend against the ``torch`` reference);
* views: ``render_views`` of N cameras in one call against N ``rasterize`` calls (measured by
  ``gpu_check.measure_render``);
* JPEG: a rendered float frame on the device to JPEG bytes as the server does it
  (``server.stream.encoders``: ``select_encoders``, ``frame_rgb``, ``encode_jpeg``), nvJPEG against
  OpenCV (which copies the frame to the host first);
* training: the device-resident step against the host-checked step
  (``Trainer(device_resident=...)``), on the same capture.

A pair that cannot run here (no nvJPEG without CUDA and torchvision) is reported with why.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable

import torch

from avatar_core.render import rasterize
from avatar_core.render.camera import Camera
from avatar_core.render.types import GaussianSet, RenderRequest


@dataclasses.dataclass
class Ratio:
    what: str
    fast: str  # the path expected to be faster, and its rate
    fast_rate: float
    slow: str
    slow_rate: float
    unit: str
    why_not: str = ""  # set when the pair could not be measured here

    @property
    def value(self) -> float:
        if self.why_not or not self.slow_rate:
            return math.nan
        return self.fast_rate / self.slow_rate


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def rate(step: Callable[[], object], device: torch.device, max_n: int, seconds: float) -> float:
    """Calls per second of ``step`` after one warm-up call, over ``max_n`` calls or
    ``seconds``, whichever ends first (at least one)."""
    step()
    sync(device)
    n, t0 = 0, time.perf_counter()
    while n < max_n and (n == 0 or time.perf_counter() - t0 < seconds):
        step()
        n += 1
        if n % 8 == 0:
            sync(device)  # bounds the queue, so the clock sees the work
    sync(device)
    return n / (time.perf_counter() - t0)


def render_backends(g: GaussianSet, cam: Camera, fast: str, fast_fps: float, slow: str,
                    max_n: int, seconds: float) -> Ratio:
    """``slow`` timed on the CPU copy of the same scene, against ``fast``'s fps measured
    already."""
    cpu = GaussianSet(*(t.cpu() for t in (g.means, g.quats, g.scales, g.opacities, g.sh)))
    req = RenderRequest(outputs=("rgb",), backend=slow)
    with torch.no_grad():
        slow_fps = rate(lambda: rasterize(cpu, cam, req), torch.device("cpu"), max_n, seconds)
    return Ratio(f"render {cam.width}x{cam.height}, {g.num} Gaussians", fast, fast_fps, slow,
                 slow_fps, "fps")


def jpeg_encoders(width: int, height: int, device: torch.device, max_n: int,
                  seconds: float) -> Ratio:
    """A smooth float frame on ``device`` to JPEG bytes, through the server's encoders with
    nvJPEG and with OpenCV chosen in turn."""
    from server.stream.encoders import encode_jpeg, frame_rgb, probe_nvjpeg, select_encoders

    y, x = torch.meshgrid(torch.linspace(0, 1, height), torch.linspace(0, 1, width),
                          indexing="ij")
    frame = torch.stack([x, y, 0.5 + 0.5 * torch.sin(6 * x * y)], -1).to(device)
    what = f"JPEG {width}x{height} from the rendered frame"

    def frames_per_s(prefer: str) -> float:
        select_encoders(prefer)
        return rate(lambda: encode_jpeg(frame_rgb(frame, "jpeg", False), 90), device, max_n,
                    seconds)

    try:
        opencv = frames_per_s("cpu")
        if device.type != "cuda" or not probe_nvjpeg():
            return Ratio(what, "nvjpeg", math.nan, "opencv", opencv, "fps",
                         why_not="no nvJPEG here (it needs CUDA and torchvision)")
        nvjpeg = frames_per_s("auto")
    finally:
        select_encoders("cpu")
    return Ratio(what, "nvjpeg", nvjpeg, "opencv", opencv, "fps")


def training_modes(its_per_s: Callable[[bool], float], resolution: int) -> Ratio:
    """``its_per_s(device_resident)`` for both settings of the same trainer recipe."""
    return Ratio(f"training step {resolution}x{resolution}", "device-resident",
                 its_per_s(True), "host-checked", its_per_s(False), "it/s")


def table(ratios: list[Ratio], dry: bool) -> list[str]:
    lines = ["| ratio | faster path | other path | faster / other |", "|---|---|---|---|"]
    for r in ratios:
        fast = "not run" if math.isnan(r.fast_rate) else f"{r.fast_rate:.1f} {r.unit}"
        slow = "not run" if math.isnan(r.slow_rate) else f"{r.slow_rate:.1f} {r.unit}"
        value = f"not measured: {r.why_not}" if r.why_not else f"{r.value:.2f}x"
        lines.append(f"| {r.what} | {r.fast}: {fast} | {r.slow}: {slow} | {value} |")
    if dry:
        lines.append("")
        lines.append("Dry run: the CPU at tiny sizes, with the backends that exist here; not "
                     "the GPU's ratios.")
    return lines
