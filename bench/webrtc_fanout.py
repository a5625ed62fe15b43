"""The CPU of sending one picture stream to N WebRTC viewers: each viewer's own encoder
(aiortc's way, ``webrtc_shared_encode`` off) against one shared encode whose bitstream every
viewer's sender packs (server/webrtc/fanout.py). No network: the encoders and packers the
server uses, fed the demo avatar's frames turning, side by side in one process, per size.

    OMP_NUM_THREADS=1 .venv/bin/python bench/webrtc_fanout.py [--sizes 128,256,512]
        [--viewers 1,4,16] [--frames 60] [--codec vp8]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import av
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from aiortc.mediastreams import VIDEO_TIME_BASE  # noqa: E402

from server.webrtc.encoders import ENCODERS, RAW_ENCODERS  # noqa: E402

LOW, HIGH = 250_000, 4_000_000


def pictures(size: int, count: int) -> list[np.ndarray]:
    """The synthetic avatar, its head turning, ``count`` frames at ``size`` px (rendered
    once, before any timing)."""
    import torch

    from avatar_core.gaussians.loading import load_avatar
    from avatar_core.render.camera import orbit
    from avatar_core.render.camera_path import framing_target
    from avatar_core.render.types import RenderRequest, to_uint8
    from avatar_core.render.views import render_views

    animator = load_avatar("synthetic").animator
    chest = framing_target(animator.body_model.joint_template)
    camera = orbit(chest, 0, 0, 1.2, width=size, height=size)
    out = []
    with torch.no_grad():
        for i in range(count):
            neck = np.zeros(3 * 21, np.float32)
            neck[3 * 14 + 1] = 0.6 * np.sin(2 * np.pi * i / count)  # the head turns
            world = animator.pose({"body_pose": torch.from_numpy(neck)[None]}).gaussians
            rgb = render_views(world, [camera], RenderRequest(backend="cpu"))[0].rgb
            out.append(to_uint8(rgb))
    return out


def video_frame(rgb: np.ndarray, index: int) -> av.VideoFrame:
    frame = av.VideoFrame.from_ndarray(rgb, format="rgb24")
    frame.pts, frame.time_base = index * 3000, VIDEO_TIME_BASE
    return frame


def per_viewer(frames: list[np.ndarray], viewers: int, mime: str) -> float:
    """CPU s of each viewer encoding every frame."""
    encoders = [ENCODERS[mime](LOW, HIGH) for _ in range(viewers)]
    start = time.process_time()
    for i, rgb in enumerate(frames):
        for encoder in encoders:
            encoder.encode(video_frame(rgb, i))
    return time.process_time() - start


def shared(frames: list[np.ndarray], viewers: int, mime: str) -> float:
    """CPU s of one encode a frame and each viewer's sender packing it."""
    encoder = RAW_ENCODERS[mime](LOW, HIGH)
    packers = [ENCODERS[mime](LOW, HIGH) for _ in range(viewers)]
    start = time.process_time()
    for i, rgb in enumerate(frames):
        payloads, _ = encoder.encode(video_frame(rgb, i))
        for packer in packers:
            packet = av.Packet(payloads[0])
            packet.pts, packet.time_base = i * 3000, VIDEO_TIME_BASE
            packer.pack(packet)
    return time.process_time() - start


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="128,256,512")
    parser.add_argument("--viewers", default="1,4,16")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--codec", default="vp8", choices=("vp8", "h264"))
    args = parser.parse_args()
    mime = f"video/{args.codec}"
    print("| size px | viewers | each viewer encodes: CPU ms a frame | one shared encode, "
          "each packs: CPU ms a frame | ratio |")
    print("|---:|---:|---:|---:|---:|")
    for size in (int(s) for s in args.sizes.split(",")):
        frames = pictures(size, args.frames)
        for viewers in (int(v) for v in args.viewers.split(",")):
            own = per_viewer(frames, viewers, mime)
            one = shared(frames, viewers, mime)
            n = len(frames)
            print(f"| {size} | {viewers} | {own / n * 1e3:.2f} | {one / n * 1e3:.2f} | "
                  f"{own / one:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
