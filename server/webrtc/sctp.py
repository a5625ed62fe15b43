"""Data-channel bytes budgeted before aiortc reassembles them.

aiortc's SCTP stack reassembles data-channel messages in Python on the event loop: every DATA
chunk is acknowledged (a SACK per packet) and, while its message is incomplete, re-walked on
every arrival (quadratic in the fragments of a message). Left alone, one 16 MiB message costs
seconds of event-loop time before any limit of ours sees it, and a flood of tiny messages
costs a SACK, a reassembly and a session wake-up each. So each peer's SCTP transport gets a
:class:`SctpGuard` between aiortc's packet parser and its reassembly: the DATA and
FORWARD-TSN handlers are wrapped on that one transport instance (no aiortc class or module
is changed, so other peers and other aiortc users in the process are untouched). If aiortc's
internals moved, the guard is not installed, a warning says so, and the peer keeps aiortc's
own behaviour (the session's limits still apply, after reassembly).

Every DATA chunk, on arrival, before aiortc sees it:

1. **Message size.** The fragments of one message have consecutive TSNs (RFC 9260 6.9), so
   the guard follows each stream's message as it grows, in order. One past
   ``max_message_bytes`` (which the SDP answer advertises as ``a=max-message-size``) makes
   the peer refused: what aiortc holds of it is freed, every later chunk dropped, and
   ``on_too_large`` called (the peer closes; server/webrtc/peer.py). Fragments sent out of
   order escape this count, not the window: such a message never completes.
2. **Streams.** At most ``max_streams`` stream ids (aiortc keeps a reassembly per id for
   ever, and walks them all on every FORWARD TSN); chunks naming more are dropped.
3. **Window.** Chunks held (waiting here, or in aiortc's reassembly) stay within
   ``window_bytes``, the receive window advertised in INIT and every SACK, each chunk
   costing ``max(its bytes, MIN_CHUNK_COST)`` (so a message of 1-byte fragments is not
   cheap to reassemble). Past it a chunk is dropped *unacknowledged*, as a receiver with a
   full window does (RFC 9260 6.2): nothing is lost, the sender retransmits it later.
4. **Rates.** A first fragment takes a token of the message bucket (``messages_per_s``), and
   every chunk its cost of the byte bucket (``bytes_per_s``). A chunk the buckets cannot
   pay yet waits here (in order, within the window) and is handed to aiortc, and
   acknowledged, once they can: the sender's unacknowledged data fills its congestion
   window and it slows to the budget, as a WebSocket sender does when the server reads its
   socket more slowly.

So a flooder costs a parse and a check per chunk past the window (no reassembly, no SACK, no
session work), and the event loop spends on any one peer at most what its budgets pay for.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from aiortc import RTCSctpCapabilities
from aiortc.rtcsctptransport import DataChunk, InboundStream
from aiortc.utils import uint32_gte

log = logging.getLogger(__name__)

MIN_CHUNK_COST = 1024  # bytes a chunk costs at least (a full one carries ~1.1 KiB)
DRAIN_INTERVAL_S = 0.05  # waiting chunks are handed over in batches at most this often
FIRST_FRAG, LAST_FRAG = 0x02, 0x01  # DATA chunk flags B and E (RFC 9260 3.3.1)
FORWARD_TSN_ENTRY_COST = 4  # bytes per stream entry of a FORWARD TSN chunk (RFC 3758)
HOOKS = ("_receive_data_chunk", "_receive_forward_tsn_chunk", "_send_sack")
STATE = ("_inbound_streams", "_advertised_rwnd", "_last_received_tsn", "_sack_misordered",
         "_sack_needed")
REASONS = ("closed", "streams", "window", "duplicate")
SEND_QUEUES = ("_data_channel_queue", "_outbound_queue", "_sent_queue")  # unsent or unacked
FLUSH_POLL_S = 0.01


@dataclass(frozen=True)
class GuardLimits:
    max_message_bytes: int    # largest message, advertised as a=max-message-size
    bytes_per_s: float        # chunk bytes (at least MIN_CHUNK_COST each) per second
    burst_bytes: float
    messages_per_s: float     # messages begun per second
    burst_messages: float
    window_bytes: int         # bytes held (waiting + in reassembly), the receive window
    max_streams: int          # stream ids with a reassembly

    @classmethod
    def from_settings(cls, settings: Any) -> GuardLimits:
        s = settings
        rate = s.limits.max_messages_per_s
        return cls(max_message_bytes=s.webrtc_max_message_bytes,
                   bytes_per_s=s.webrtc_max_inbound_bytes_per_s,
                   burst_bytes=max(s.webrtc_max_inbound_bytes_per_s,
                                   2 * s.webrtc_max_message_bytes),
                   messages_per_s=rate, burst_messages=max(1.0, rate),
                   window_bytes=s.webrtc_receive_window_bytes,
                   max_streams=s.webrtc_max_sctp_streams)


class Bucket:
    """A token bucket: ``rate`` per second, at most ``burst`` saved up."""

    def __init__(self, rate: float, burst: float) -> None:
        self.rate = rate
        self.capacity = burst
        self.tokens = burst
        self.stamp = time.monotonic()

    def wait(self, amount: float, now: float) -> float:
        """Seconds until ``amount`` (at most the burst) is there; 0: now."""
        self.tokens = min(self.capacity, self.tokens + (now - self.stamp) * self.rate)
        self.stamp = now
        return max(0.0, min(amount, self.capacity) - self.tokens) / self.rate

    def take(self, amount: float) -> None:
        self.tokens -= min(amount, self.capacity)


def _cost(chunk: Any) -> int:
    return max(len(chunk.user_data), MIN_CHUNK_COST)


@dataclass
class _Waiting:
    handler: Callable[[Any], Any]
    chunk: Any
    cost: int
    tsn: int | None  # DATA chunks


class SctpGuard:
    """One peer's SCTP receive budget (see the module docstring)."""

    def __init__(self, limits: GuardLimits, on_too_large: Callable[[int], None], *,
                 metrics: Any = None, name: str = "") -> None:
        self.limits = limits
        self.on_too_large = on_too_large
        self.metrics = metrics
        self.name = name
        self.installed = False
        self.refused = False            # a message past max_message_bytes: nothing more
        self.stopped = False            # the peer is closing: nothing more
        self.messages = Bucket(limits.messages_per_s, limits.burst_messages)
        self.bytes = Bucket(limits.bytes_per_s, limits.burst_bytes)
        self._runs: dict[int, tuple[int, int]] = {}  # stream -> (next TSN, bytes so far)
        self._held: dict[int, int] = {}  # stream -> cost aiortc holds in its reassembly
        self._reassembling = 0          # all streams
        self._waiting: deque[_Waiting] = deque()
        self._waiting_cost = 0
        self._waiting_tsns: set[int] = set()
        self._drain: asyncio.Task | None = None
        # counters (per peer; the metrics sum them over peers)
        self.peak_held = 0              # waiting + reassembling, the most seen
        self.accepted_chunks = 0        # handed to aiortc
        self.accepted_bytes = 0         # their user data: what aiortc reassembled
        self.accepted_messages = 0      # first fragments among them
        self.delayed = 0                # chunks that waited for the rate budgets
        self.largest_message = 0        # the largest message seen growing (in order)
        self.dropped: Counter[str] = Counter()        # chunks, by reason
        self.dropped_bytes: Counter[str] = Counter()  # their user data
        self._sctp: Any = None
        self._data: Any = None
        self._forward: Any = None

    @property
    def held(self) -> int:
        return self._reassembling + self._waiting_cost

    # -- installing -----------------------------------------------------------------------------

    def install(self, sctp: Any) -> bool:
        """Wrap ``sctp``'s (an aiortc RTCSctpTransport, not started yet) chunk handlers and set
        its receive window and max-message-size; False (and a warning) when aiortc's internals
        are not what this was written against."""
        missing = [n for n in HOOKS + STATE + ("getCapabilities",) if not hasattr(sctp, n)]
        missing += [f"DataChunk.{n}" for n in ("tsn", "flags", "stream_id", "user_data")
                    if not hasattr(DataChunk(), n)]
        missing += [] if hasattr(InboundStream(), "reassembly") else ["InboundStream.reassembly"]
        if missing:
            log.warning("aiortc's SCTP transport lacks %s: data-channel messages are "
                        "reassembled before any of webrtc_max_message_bytes, "
                        "webrtc_receive_window_bytes, webrtc_max_inbound_bytes_per_s, "
                        "webrtc_max_sctp_streams (the session's limits apply after)",
                        ", ".join(missing))
            return False
        self._sctp = sctp
        self._data = sctp._receive_data_chunk
        self._forward = sctp._receive_forward_tsn_chunk
        sctp._receive_data_chunk = self._receive_data_chunk
        sctp._receive_forward_tsn_chunk = self._receive_forward_tsn_chunk
        sctp._advertised_rwnd = self.limits.window_bytes  # sent in INIT / INIT-ACK, SACKs
        capabilities = RTCSctpCapabilities(maxMessageSize=self.limits.max_message_bytes)
        sctp.getCapabilities = lambda: capabilities  # this instance's a=max-message-size
        self.installed = True
        return True

    async def flush(self, timeout_s: float) -> bool:
        """Wait, at most ``timeout_s``, until what the server sent on the association is
        acknowledged (a last ``too_large`` must not die in aiortc's queues when the peer's
        teardown aborts the association); False when the time ran out."""
        sctp = self._sctp
        if sctp is None or not all(hasattr(sctp, n) for n in SEND_QUEUES):
            return True
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        while any(getattr(sctp, n) for n in SEND_QUEUES):
            if loop.time() >= deadline:
                return False
            await asyncio.sleep(FLUSH_POLL_S)
        return True

    def stop(self) -> None:
        """The peer is closing: nothing more is handed to aiortc."""
        self.stopped = True
        self._clear_waiting()
        if self._drain is not None:
            self._drain.cancel()

    # -- aiortc's handlers, wrapped ---------------------------------------------------------------

    async def _receive_data_chunk(self, chunk: Any) -> None:
        size = len(chunk.user_data)
        if self.refused or self.stopped:
            self._drop("closed", size)
            return
        stream, tsn, flags = chunk.stream_id, chunk.tsn, chunk.flags
        if tsn in self._waiting_tsns:
            self._drop("duplicate", size)  # a retransmission of one waiting here
            return
        new = self._is_new(tsn)
        # 1. The message this chunk begins or continues in order, and its size so far.
        run = None
        if new:
            if flags & FIRST_FRAG:
                run = size
            else:
                previous = self._runs.get(stream)
                if previous is not None and previous[0] == tsn:
                    run = previous[1] + size
        if run is not None:
            self.largest_message = max(self.largest_message, run)
            if run > self.limits.max_message_bytes:
                self._refuse(stream, run, size)
                return
        # 2. Streams.
        if stream not in self._held and len(self._held) >= self.limits.max_streams:
            self._drop("streams", size)
            return
        # 3. The window. The last fragment of a message followed in order may overshoot it
        # (it frees the window; one chunk per stream at most, as no message begins while the
        # window is full).
        cost = max(size, MIN_CHUNK_COST)
        completes = run is not None and flags & (FIRST_FRAG | LAST_FRAG) == LAST_FRAG
        if self.held + cost > self.limits.window_bytes and not completes:
            self._drop("window", size)
            return
        if run is not None:
            if flags & LAST_FRAG:
                self._runs.pop(stream, None)
            else:
                self._runs[stream] = ((tsn + 1) % 2**32, run)
        self._held.setdefault(stream, 0)
        # 4. The rates: now, or in order once the budgets allow.
        item = _Waiting(self._data, chunk, cost, tsn)
        if not self._waiting and self._pays(item, time.monotonic()):
            await self._hand(item)
        else:
            self._wait(item)

    async def _receive_forward_tsn_chunk(self, chunk: Any) -> None:
        """FORWARD TSN (partial reliability) skips data and names streams: budgeted as bytes,
        in order with the data waiting, and it may not name more streams than allowed."""
        if self.refused or self.stopped:
            self._drop("closed", 0)
            return
        streams = {stream for stream, _ in getattr(chunk, "streams", ())}
        if len(self._held.keys() | streams) > self.limits.max_streams:
            self._drop("streams", 0)
            return
        for stream in streams:
            self._held.setdefault(stream, 0)
        item = _Waiting(self._forward, chunk,
                        MIN_CHUNK_COST + FORWARD_TSN_ENTRY_COST * len(streams), None)
        if not self._waiting and self._pays(item, time.monotonic()):
            await self._hand(item)
        else:
            self._wait(item)

    # -- paying, waiting, handing over -------------------------------------------------------------

    def _begins(self, item: _Waiting) -> bool:
        return (item.tsn is not None and bool(item.chunk.flags & FIRST_FRAG)
                and self._is_new(item.tsn))

    def _due(self, item: _Waiting, now: float) -> float:
        """Seconds until the budgets can pay for ``item``."""
        wait = self.bytes.wait(item.cost, now)
        if self._begins(item):
            wait = max(wait, self.messages.wait(1, now))
        return wait

    def _pays(self, item: _Waiting, now: float) -> bool:
        if self._due(item, now) > 0:
            return False
        if self._begins(item):
            self.messages.take(1)
            self.accepted_messages += 1
        self.bytes.take(item.cost)
        return True

    async def _hand(self, item: _Waiting) -> None:
        """``item`` to aiortc's own handler; then what aiortc holds is counted again (only
        this chunk more, unless aiortc delivered or pruned something)."""
        if item.tsn is not None:
            self.accepted_chunks += 1
            self.accepted_bytes += len(item.chunk.user_data)
            stream = item.chunk.stream_id
            inbound = self._sctp._inbound_streams.get(stream)
            before = None if inbound is None else len(inbound.reassembly)
            await item.handler(item.chunk)
            if before is not None and len(inbound.reassembly) == before + 1:
                self._reassembling += item.cost
                self._held[stream] = self._held.get(stream, 0) + item.cost
                self.peak_held = max(self.peak_held, self.held)
            else:
                self._recount(stream)
        else:
            await item.handler(item.chunk)
            self._runs.clear()  # skipped data breaks the in-order runs; the window holds
            for stream in list(self._held):
                self._recount(stream)

    def _wait(self, item: _Waiting) -> None:
        self._waiting.append(item)
        self._waiting_cost += item.cost
        if item.tsn is not None:
            self._waiting_tsns.add(item.tsn)
        self.delayed += 1
        self.peak_held = max(self.peak_held, self.held)
        if self._drain is None or self._drain.done():
            self._drain = asyncio.get_running_loop().create_task(
                self._drain_waiting(), name=f"sctp guard {self.name}")

    async def _drain_waiting(self) -> None:
        """Hand the waiting chunks over in order as the budgets allow, acknowledging each
        batch (the packet that brought them was acknowledged without them)."""
        try:
            while self._waiting and not (self.refused or self.stopped):
                delay = self._due(self._waiting[0], time.monotonic())
                if delay > 0:
                    await asyncio.sleep(max(delay, DRAIN_INTERVAL_S))
                    continue
                while self._waiting and self._pays(self._waiting[0], time.monotonic()):
                    item = self._waiting.popleft()
                    self._waiting_cost -= item.cost
                    if item.tsn is not None:
                        self._waiting_tsns.discard(item.tsn)
                    await self._hand(item)
                    if self.refused or self.stopped:
                        return
                if self._sctp._sack_needed:
                    await self._sctp._send_sack()
        except ConnectionError:
            self.stop()  # the association is gone
        except Exception:
            log.exception("WebRTC peer %s: the data-channel guard failed; its waiting chunks "
                          "are dropped", self.name)
            self.stop()

    # -- bookkeeping ------------------------------------------------------------------------------

    def _is_new(self, tsn: int) -> bool:
        """Not received before (a retransmission of an acknowledged chunk is not)."""
        last = self._sctp._last_received_tsn
        return not ((last is not None and uint32_gte(last, tsn))
                    or tsn in self._sctp._sack_misordered)

    def _recount(self, stream: int) -> None:
        """What aiortc holds for ``stream`` now (it delivers and prunes on its own)."""
        inbound = self._sctp._inbound_streams.get(stream)
        cost = 0 if inbound is None else sum(map(_cost, inbound.reassembly))
        self._reassembling += cost - self._held.get(stream, 0)
        self._held[stream] = cost
        self.peak_held = max(self.peak_held, self.held)

    def _clear_waiting(self) -> None:
        self._waiting.clear()
        self._waiting_tsns.clear()
        self._waiting_cost = 0

    def _drop(self, reason: str, size: int) -> None:
        if not self.dropped[reason]:
            log.info("WebRTC peer %s: dropping data-channel chunks (%s)", self.name, reason)
        self.dropped[reason] += 1
        self.dropped_bytes[reason] += size
        if self.metrics is not None:
            self.metrics.webrtc_dc_dropped_chunks.labels(reason).inc()
            self.metrics.webrtc_dc_dropped_bytes.labels(reason).inc(size)

    def _refuse(self, stream: int, size: int, chunk_size: int) -> None:
        self.refused = True
        self._clear_waiting()
        inbound = self._sctp._inbound_streams.get(stream)
        if inbound is not None:
            inbound.reassembly.clear()  # the peer is closing: free what it sent at once
        self._recount(stream)
        self._drop("closed", chunk_size)
        log.warning("WebRTC peer %s: a data-channel message passed %d bytes, more than "
                    "webrtc_max_message_bytes (%d); closing the peer", self.name, size,
                    self.limits.max_message_bytes)
        if self.metrics is not None:
            self.metrics.webrtc_dc_too_large.inc()
        self.on_too_large(size)

    def summary(self) -> str:
        dropped = ", ".join(f"{self.dropped[r]} {r}" for r in REASONS if self.dropped[r])
        return (f"{self.accepted_messages} messages, {self.accepted_chunks} chunks "
                f"({self.accepted_bytes} B) reassembled, {self.delayed} chunks delayed, peak "
                f"held {self.peak_held} B" + (f"; dropped {dropped}" if dropped else ""))
