"""Frame stamps: a frame's drive ``seq`` written into its pixels, read back after any codec.

For latency measurements over transports that carry no per-frame metadata to the page (a
WebRTC video track): the sender stamps each frame with the seq of the newest drive it shows,
the receiver reads it from the decoded picture and matches it with the drive it sent. A stamp
is one strip of 32 square cells along the top-left edge: 4 marker bits (1010), the 24-bit
seq (most significant first), 4 check bits (the sum of the seq's six nibbles, mod 16,
inverted); a 1 is
black, a 0 white. Cells are ``width // 32`` px (2 to 8), so they survive VP8 / H.264 at low bit
rates; the reader averages each cell's centre and thresholds it. Pure numpy.
"""

from __future__ import annotations

import numpy as np

CELLS = 32
MARKER = (1, 0, 1, 0)
SEQ_BITS = 24
MIN_CELL, MAX_CELL = 2, 8


def cell_size(width: int) -> int:
    """The cell side (px) of a stamp in a frame ``width`` px wide; ValueError if too narrow."""
    size = min(MAX_CELL, width // CELLS)
    if size < MIN_CELL:
        raise ValueError(f"a frame stamp needs a frame at least {CELLS * MIN_CELL} px wide, "
                         f"not {width}")
    return size


def _bits(seq: int) -> list[int]:
    seq &= (1 << SEQ_BITS) - 1
    data = [(seq >> (SEQ_BITS - 1 - i)) & 1 for i in range(SEQ_BITS)]
    # Inverted, so that a flat white (or black) strip never reads as a valid stamp.
    check = ~sum((seq >> (4 * i)) & 0xF for i in range(SEQ_BITS // 4)) & 0xF
    return [*MARKER, *data, *((check >> (3 - i)) & 1 for i in range(4))]


def stamp(rgb: np.ndarray, seq: int) -> np.ndarray:
    """Write ``seq`` (its low 24 bits; -1 reads back as 0xFFFFFF) into ``rgb`` [H, W, 3]
    uint8, in place; returns it."""
    if rgb.ndim != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"stamp wants an [H, W, C] uint8 image, got {rgb.dtype} {rgb.shape}")
    size = cell_size(rgb.shape[1])
    if rgb.shape[0] < size:
        raise ValueError(f"a frame stamp needs a frame at least {size} px high")
    for i, bit in enumerate(_bits(seq)):
        rgb[:size, i * size:(i + 1) * size] = 0 if bit else 255
    return rgb


def read_stamp(rgb: np.ndarray) -> int | None:
    """The seq stamped into ``rgb`` [H, W, 3] (any dtype 0..255), or None when there is no
    valid stamp (no marker, a wrong check, a frame too small)."""
    if rgb.ndim != 3 or rgb.shape[2] < 3:
        return None
    try:
        size = cell_size(rgb.shape[1])
    except ValueError:
        return None
    if rgb.shape[0] < size:
        return None
    lo, hi = size // 4, size - size // 4  # the cell's centre: edges bleed after a codec
    strip = rgb[lo:hi, :CELLS * size, :3].astype(np.float32).mean(axis=(0, 2))  # [32 * size]
    cells = strip.reshape(CELLS, size)[:, lo:hi].mean(axis=1)  # [32]
    bits = [int(v < 128) for v in cells]
    if tuple(bits[:4]) != MARKER:
        return None
    seq = int("".join(map(str, bits[4:4 + SEQ_BITS])), 2)
    return seq if _bits(seq) == bits else None
