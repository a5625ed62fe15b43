"""The shared renderer: every session's frames run on one small pool of render threads.

Fairness: a session never has more than one render queued or running (its loop awaits each
frame before asking for the next), and the queue is first-in first-out, so with N busy
sessions each one gets every N-th slot: round-robin, equal frame rates, no session able to
crowd out another. A slow client only delays its own loop (it waits on its socket, holding
no render slot).

Threads: torch's intra-op pool is process-wide and numba's thread count is per calling
thread; both are set to ``threads_per_render`` so that ``render_threads`` workers do not
oversubscribe the cores (on 2 cores: 1 x 2 or 2 x 1, never 2 x 2).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import threading
from collections.abc import Callable
from typing import Any, TypeVar

T = TypeVar("T")


def limit_threads(threads: int) -> None:
    """torch and numba threads of the calling thread's work (a pool initializer)."""
    import torch

    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)
    try:
        import numba

        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    except (ImportError, ValueError):
        pass


class RenderScheduler:
    """``await scheduler.run(fn, *args)``: ``fn`` on a render thread, first come first served."""

    def __init__(self, render_threads: int = 1, threads_per_render: int = 1) -> None:
        self.render_threads = render_threads
        self.threads_per_render = threads_per_render
        self._pool = concurrent.futures.ThreadPoolExecutor(
            max_workers=render_threads, thread_name_prefix="render",
            initializer=limit_threads, initargs=(threads_per_render,))
        self._lock = threading.Lock()
        self.queued = 0   # submitted, not yet finished
        self.running = 0

    def submit(self, fn: Callable[..., T], *args: Any) -> concurrent.futures.Future[T]:
        with self._lock:
            self.queued += 1

        def job() -> T:
            with self._lock:
                self.running += 1
            try:
                return fn(*args)
            finally:
                with self._lock:
                    self.running -= 1

        future = self._pool.submit(job)
        future.add_done_callback(self._done)
        return future

    def _done(self, _: concurrent.futures.Future) -> None:
        with self._lock:
            self.queued -= 1

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        """Cancelling the awaiting task cancels a job that has not started yet."""
        return await asyncio.wrap_future(self.submit(fn, *args))

    def shutdown(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)
