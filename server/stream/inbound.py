"""What a session receives, bounded before it costs: bytes per second, objects per message, and
large messages decoded off the event loop.

Bytes per second are bounded by backpressure, not by dropping: past its budget a session's
receiver waits before it reads on, and uvicorn stops reading a WebSocket while its message
waits, so the sender's TCP window fills and it slows down; the frames it sends are not
received (and cost nothing) faster than the budget.

Why: the event loop serves every session and ``/v1/health``; one large message decoded on it
stalls them all. msgpack holds the GIL while it unpacks, so a worker thread alone does not
help: the object count is bounded first (``protocol.scan``), which bounds the unpack, and the
remaining validation of large messages runs in a thread.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass
from typing import Any

from protocol import Limits, ProtocolError, decode_client
from protocol.scan import check_object_count


@dataclass(frozen=True)
class InboundLimits:
    max_message_objects: int = 16384
    decode_offload_bytes: int = 64 * 1024
    max_bytes_per_s: float = 16 * 2**20
    max_burst_bytes: float = 16 * 2**20


class ByteBudget:
    """A token bucket over bytes: ``rate`` per second, at most ``burst`` saved up."""

    def __init__(self, rate: float, burst: float) -> None:
        self.rate = rate
        self.capacity = burst
        self.available = burst
        self.stamp = time.monotonic()

    def reserve(self, size: int) -> float:
        """Take ``size`` bytes; seconds to wait before using them (0: at once). The budget may
        go into debt, which later reservations wait out."""
        now = time.monotonic()
        self.available = min(self.capacity, self.available + (now - self.stamp) * self.rate)
        self.stamp = now
        self.available -= size
        return max(0.0, -self.available / self.rate)


def decode_bounded(data: bytes, limits: Limits, max_objects: int) -> Any:
    """``decode_client`` after the object count is checked (cheap: a message of fewer bytes
    than ``max_objects`` cannot hold more objects)."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError("bad_message", "messages are binary msgpack frames")
    if len(data) > limits.max_message_bytes:
        raise ProtocolError("too_large", f"message of {len(data)} bytes exceeds the limit "
                                         f"{limits.max_message_bytes}")
    if len(data) > max_objects:
        check_object_count(data, max_objects)
    return decode_client(data, limits)


class InboundDecoder:
    """One session's inbound path: the byte budget, then a bounded decode (threaded if large)."""

    def __init__(self, limits: Limits, inbound: InboundLimits) -> None:
        self.limits = limits
        self.inbound = inbound
        self.budget = ByteBudget(inbound.max_bytes_per_s,
                                 max(inbound.max_burst_bytes, limits.max_message_bytes))

    async def decode(self, data: bytes) -> Any:
        """The message, or ProtocolError; waits first while the session is over its byte
        budget (the socket is not read meanwhile)."""
        delay = self.budget.reserve(len(data))
        if delay > 0:
            await asyncio.sleep(delay)
        if len(data) >= self.inbound.decode_offload_bytes:
            return await asyncio.to_thread(decode_bounded, data, self.limits,
                                           self.inbound.max_message_objects)
        return decode_bounded(data, self.limits, self.inbound.max_message_objects)
