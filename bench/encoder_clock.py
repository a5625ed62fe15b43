"""What a WebRTC video frame's timestamp does to its picture (issue 30, the capture clock).

On ``webrtc_sender_clock = capture`` a frame's RTP timestamp is the capture instant of the
drive it shows: frames held while the picture's lag grows come one tick apart, and a new
drive after a slow render jumps ahead. aiortc's encoders hand that timestamp to the codec,
whose rate control budgets each frame's bits by the time since the last. Ours
(server/webrtc/encoders.py) give the codec the time of sending and keep the frame's own
timestamp for the wire. Side by side in one run: the same ``--frames`` moving pictures
(stamped, ``--size`` px), sent at 30 fps, with three timestamp patterns, through aiortc's VP8
encoder as is and through ours; decoded by aiortc's decoder; PSNR against the source, bytes a
frame and frame stamps read back.

    .venv/bin/python bench/encoder_clock.py [--size 64] [--frames 150]
"""

from __future__ import annotations

import argparse
import fractions
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from protocol.stamp import read_stamp, stamp  # noqa: E402

TIME_BASE = fractions.Fraction(1, 90000)
SEND_STEP_S = 1 / 30


def picture(i: int, size: int) -> np.ndarray:
    """Smooth gradients and a moving disc, stamped with ``i``: [size, size, 3] uint8."""
    yy, xx = np.mgrid[:size, :size]
    cx = size / 2 + size / 4 * np.sin(i / 7)
    disc = ((xx - cx) ** 2 + (yy - size / 2) ** 2) < (size / 5) ** 2
    rgb = np.stack([(xx * 3 + i) % 256, (yy * 2) % 256, 255 * disc], -1).astype(np.uint8)
    return stamp(rgb, i)


def patterns(frames: int) -> dict[str, list[int]]:
    """Timestamps (90 kHz) of ``frames`` frames sent 1/30 s apart."""
    even = [i * 3000 for i in range(frames)]
    stuck, pts = [], 0
    for i in range(frames):  # two 0.8 s stretches held one tick apart (the lag grew)
        pts += 1 if 40 <= i % 100 < 64 else 3000
        stuck.append(pts)
    jumps, pts = [], 0
    for i in range(frames):  # a new drive every 6 frames, 0.5 s on; repeats glued to it
        pts += 45_000 if i % 6 == 0 else 1
        jumps.append(pts)
    return {"even (send clock)": even, "held stretches": stuck, "jumps + held repeats": jumps}


class SendClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        self.now += SEND_STEP_S
        return self.now


def run(encoder, stamps: list[int], size: int) -> tuple[float, float, float, int]:
    """(mean PSNR dB, min PSNR dB, mean bytes a frame, stamps read)."""
    import av
    from aiortc.codecs.vpx import Vp8Decoder, vp8_depayload
    from aiortc.jitterbuffer import JitterFrame

    decoder = Vp8Decoder()
    psnrs, sizes, read = [], [], 0
    for i, pts in enumerate(stamps):
        source = picture(i, size)
        frame = av.VideoFrame.from_ndarray(source, format="rgb24")
        frame.pts, frame.time_base = pts, TIME_BASE
        payloads, timestamp = encoder.encode(frame)
        data = b"".join(vp8_depayload(p) for p in payloads)
        sizes.append(len(data))
        for out in decoder.decode(JitterFrame(data=data, timestamp=timestamp)):
            got = out.to_ndarray(format="rgb24").astype(np.float64)
            mse = float(np.mean((got - source) ** 2))
            psnrs.append(10 * np.log10(255**2 / max(mse, 1e-9)))
            read += read_stamp(out.to_ndarray(format="rgb24")) == i
    return float(np.mean(psnrs)), float(np.min(psnrs)), float(np.mean(sizes)), read


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--frames", type=int, default=150)
    args = parser.parse_args()
    from aiortc.codecs.vpx import Vp8Encoder

    from server.webrtc.encoders import ClampedVp8Encoder

    print(f"VP8, {args.size} px, {args.frames} frames sent at 30 fps\n")
    print("| timestamps | encoder | PSNR mean | PSNR min | bytes/frame | stamps read |")
    print("|---|---|---:|---:|---:|---:|")
    for name, stamps in patterns(args.frames).items():
        for label, encoder in (("aiortc's", Vp8Encoder()),
                               ("ours (sending time)",
                                ClampedVp8Encoder(250_000, 1_500_000, clock=SendClock()))):
            mean, low, size, read = run(encoder, stamps, args.size)
            print(f"| {name} | {label} | {mean:.1f} dB | {low:.1f} dB | {size:.0f} | "
                  f"{read}/{len(stamps)} |")


if __name__ == "__main__":
    main()
