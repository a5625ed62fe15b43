"""The event loop's own lag: how late a short sleep wakes (a histogram in /metrics), and, when
asked, where the loop was when it stalled (a stack in the log).

Every packet of voice and every frame leaves through this one loop, so a callback that holds
it for 300 ms is a 300 ms gap at every listener. The probe measures that; the stall log names
the code that held it (``loop_stall_log_ms``; off by default). :class:`GcWatch` times the
cyclic garbage collector's pauses, which hold every Python thread, the loop's too.
"""

from __future__ import annotations

import asyncio
import gc
import logging
import sys
import threading
import time
import traceback
from collections.abc import Callable

from .metrics import ServerMetrics

log = logging.getLogger("telesplat.server.loop")

STACK_FRAMES = 12  # the innermost frames of a stalled loop that a log line keeps


class LoopWatch:
    """One probe task on the loop, plus (``stall_ms`` > 0) one sleeping thread that reads the
    probe's heartbeat. Neither spins: both sleep ``interval_s`` between looks."""

    def __init__(self, metrics: ServerMetrics, interval_s: float, stall_ms: float) -> None:
        self.metrics = metrics
        self.interval_s = interval_s
        self.stall_ms = stall_ms
        self.last_tick = time.monotonic()
        self.worst_ms = 0.0
        self._loop_thread: int | None = None
        self._task: asyncio.Task | None = None
        self._stop = threading.Event()
        self._sampler: threading.Thread | None = None

    def start(self) -> None:
        self._loop_thread = threading.get_ident()
        self.last_tick = time.monotonic()
        self._task = asyncio.get_running_loop().create_task(self._probe(), name="loop-watch")
        if self.stall_ms > 0:
            self._sampler = threading.Thread(target=self._sample, name="loop-stall-sampler",
                                             daemon=True)
            self._sampler.start()

    async def stop(self) -> None:
        self._stop.set()
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
        if self._sampler is not None:
            await asyncio.to_thread(self._sampler.join, 2.0)

    async def _probe(self) -> None:
        while True:
            asked = time.monotonic()
            await asyncio.sleep(self.interval_s)
            now = time.monotonic()
            lag_ms = max(0.0, (now - asked - self.interval_s) * 1e3)
            self.last_tick = now
            self.worst_ms = max(self.worst_ms, lag_ms)
            self.metrics.loop_lag_ms.observe(lag_ms)

    def _sample(self) -> None:
        """Log the loop thread's stack once per stall longer than ``stall_ms``."""
        logged_for = None
        while not self._stop.wait(min(self.interval_s, self.stall_ms / 2e3)):
            tick = self.last_tick
            held_ms = (time.monotonic() - tick) * 1e3 - self.interval_s * 1e3
            if held_ms < self.stall_ms or logged_for == tick:
                continue
            logged_for = tick
            frame = sys._current_frames().get(self._loop_thread)  # noqa: SLF001 - the stack
            if frame is None:
                continue
            stack = traceback.format_stack(frame)[-STACK_FRAMES:]
            self.metrics.loop_stalls.inc()
            log.warning("event loop held for %.0f ms so far, at:\n%s", held_ms,
                        "".join(stack).rstrip())


class GcWatch:
    """Each collection's pause to ``on_pause(generation, ms)`` (a ``gc.callbacks`` hook: two
    clock reads per collection); :meth:`into` puts them in ``telesplat_gc_pause_ms``."""

    def __init__(self, on_pause: Callable[[int, float], None]) -> None:
        self.on_pause = on_pause
        self._started = 0.0

    @classmethod
    def into(cls, metrics: ServerMetrics) -> GcWatch:
        return cls(lambda generation, ms: metrics.gc_pause_ms.labels(str(generation))
                   .observe(ms))

    def start(self) -> None:
        gc.callbacks.append(self._on_collect)

    def stop(self) -> None:
        if self._on_collect in gc.callbacks:
            gc.callbacks.remove(self._on_collect)

    def _on_collect(self, phase: str, info: dict) -> None:
        if phase == "start":  # collections never overlap: the collector holds the GIL
            self._started = time.perf_counter()
        else:
            self.on_pause(info["generation"], (time.perf_counter() - self._started) * 1e3)


def freeze_survivors() -> int:
    """Collect, then move every object still alive out of the collector's reach (gc.freeze):
    a full collection then walks only what was made since, not the hundreds of thousands of
    objects torch, numba and the avatars leave behind (docs/benchmarks.md: one full collection
    held the loop 171 ms at 16 viewers). Frozen objects are never collected, so call it when
    what is alive stays (after start-up and the warm-up). The number frozen."""
    gc.collect()
    gc.freeze()
    count = gc.get_freeze_count()
    log.info("garbage collector: %d objects frozen", count)
    return count
