"""Opus packets checked without decoding: RFC 6716 section 3.4's rules R1-R7.

The server forwards a performer's Opus packets as they came; this check is what keeps garbage
from reaching viewers. It reads only the TOC byte and the frame-length bytes, so it costs
microseconds, and it gives the packet's duration (for the bit-rate bound).
"""

from __future__ import annotations

MAX_FRAME_BYTES = 1275        # R2: one frame's compressed size at most
MAX_PACKET_DURATION_MS = 120  # R5: a code-3 packet holds at most 120 ms of audio

# A frame's duration in tenths of ms per TOC configuration (RFC 6716 table 2): SILK (0-11),
# hybrid (12-15), CELT (16-31).
_FRAME_TENTHS = ([100, 200, 400, 600] * 3 + [100, 200] * 2 + [25, 50, 100, 200] * 4)


class OpusPacketError(ValueError):
    """A packet that is not a well-formed Opus packet."""


def _frame_length(data: bytes, at: int) -> tuple[int, int]:
    """A frame length (1 or 2 bytes, section 3.2.1) at ``at``: (length, bytes used)."""
    if at >= len(data):
        raise OpusPacketError("the packet ends inside a frame length")
    first = data[at]
    if first < 252:
        return first, 1
    if at + 1 >= len(data):
        raise OpusPacketError("the packet ends inside a two-byte frame length")
    return first + 4 * data[at + 1], 2


def packet_duration_ms(data: bytes) -> float:
    """The audio duration of a valid Opus packet in ms; OpusPacketError when it is not one."""
    if not data:
        raise OpusPacketError("an empty packet (R1)")
    toc = data[0]
    frame_ms = _FRAME_TENTHS[toc >> 3] / 10
    code = toc & 0x3
    body = len(data) - 1
    if code == 0:
        if body > MAX_FRAME_BYTES:
            raise OpusPacketError(f"a {body}-byte frame (more than {MAX_FRAME_BYTES}, R2)")
        return frame_ms
    if code == 1:
        if body % 2 or body // 2 > MAX_FRAME_BYTES:
            raise OpusPacketError("code 1 needs two frames of equal size (R3)")
        return 2 * frame_ms
    if code == 2:
        first, used = _frame_length(data, 1)
        if first > body - used or body - used - first > MAX_FRAME_BYTES:
            raise OpusPacketError("code 2's first frame runs past the packet (R4)")
        return 2 * frame_ms
    return _code3_duration(data, frame_ms)


def _code3_duration(data: bytes, frame_ms: float) -> float:
    if len(data) < 2:
        raise OpusPacketError("code 3 without its frame-count byte (R6)")
    count, vbr, padded = data[1] & 0x3F, data[1] & 0x80, data[1] & 0x40
    if count == 0 or count * frame_ms > MAX_PACKET_DURATION_MS:
        raise OpusPacketError(f"code 3 with {count} frames of {frame_ms} ms (R5)")
    at, padding = 2, 0
    while padded:  # each 255 adds 254 bytes of padding and another length byte
        if at >= len(data):
            raise OpusPacketError("the packet ends inside its padding length (R6)")
        value = data[at]
        at += 1
        padding += 254 if value == 255 else value
        padded = value == 255
    left = len(data) - at - padding
    if left < 0:
        raise OpusPacketError("the padding runs past the packet (R6)")
    if vbr:
        for _ in range(count - 1):
            size, used = _frame_length(data, at)
            at += used
            left -= used + size
            if size > MAX_FRAME_BYTES or left < 0:
                raise OpusPacketError("a VBR frame runs past the packet (R7)")
        if left > MAX_FRAME_BYTES:
            raise OpusPacketError("the last VBR frame is too long (R7)")
    elif left % count or left // count > MAX_FRAME_BYTES:
        raise OpusPacketError("CBR frames of unequal or excessive size (R6)")
    return count * frame_ms
