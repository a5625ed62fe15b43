"""The shared renderer: every session's frames run on one small pool of render threads.

Fairness is of render time, not of frames (policy ``"time"``, the default). A session never
has more than one render queued or running (its loop awaits each frame before asking for the
next), so a first-in first-out queue would serve busy sessions in turn, one frame each: a
session asking 1920x1080 PNG with alpha and depth would then take nearly all the time from one
asking 128 px JPEG. Instead the scheduler measures each job (pose, rasterize, encode) and

* serves the waiting session that used the least render time recently (decayed with a
  half-life of ``window_s``), and
* paces a session that takes more than its share (:meth:`pace_s`): with N sessions active
  in the last ``window_s`` the fair share is ``f = render_threads / N`` of the render time; a
  session whose recent share reaches f (``PACE_FROM`` of it) leaves ``c / f`` seconds between
  the starts of its frames (c: what its frames cost), so it gets f and the others the rest.
  A session below its share, or alone, is not held back, so time that nobody else wants is
  used.

Policy ``"frames"`` keeps the plain first-in first-out round-robin (equal frame rates).

Threads: torch's intra-op pool is process-wide and numba's thread count is per calling
thread; both are set to ``threads_per_render`` so that ``render_threads`` workers do not
oversubscribe the cores (on 2 cores: 1 x 2 or 2 x 1, never 2 x 2).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import itertools
import math
import threading
import time
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from typing import Any, Literal, TypeVar

T = TypeVar("T")
Policy = Literal["time", "frames"]
POLICIES: tuple[Policy, ...] = ("time", "frames")
COST_SMOOTHING = 0.3  # weight of the newest job in a session's cost average
PACE_FROM = 0.9       # a session is paced from this fraction of its fair share on (hysteresis:
                      # paced to exactly its share, it stays paced instead of overshooting)


def limit_threads(threads: int) -> None:
    """torch and numba threads of the calling thread's work (a worker initializer)."""
    import torch

    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)
    try:
        import numba

        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    except (ImportError, ValueError):
        pass


@dataclass
class _Account:
    usage_s: float = 0.0     # render seconds, decayed to `stamp`
    stamp: float = 0.0
    cost_s: float = 0.0      # moving average of one job's seconds
    last_seen: float = 0.0   # last submit or finish
    total_s: float = 0.0     # all render seconds, never decayed (metrics, tests)
    jobs: int = 0


class FairShare:
    """Per-session render time: decayed usage, the cost of a job, who is active."""

    def __init__(self, window_s: float) -> None:
        self.window_s = window_s
        self._accounts: dict[Hashable, _Account] = {}

    def _decayed(self, acc: _Account, now: float) -> float:
        return acc.usage_s * math.exp2(-(now - acc.stamp) / self.window_s)

    def seen(self, key: Hashable, now: float) -> None:
        self._accounts.setdefault(key, _Account(stamp=now)).last_seen = now

    def add(self, key: Hashable, seconds: float, now: float) -> None:
        acc = self._accounts.setdefault(key, _Account(stamp=now))
        acc.usage_s, acc.stamp = self._decayed(acc, now) + seconds, now
        acc.cost_s = seconds if acc.jobs == 0 else \
            (1 - COST_SMOOTHING) * acc.cost_s + COST_SMOOTHING * seconds
        acc.total_s += seconds
        acc.jobs += 1
        acc.last_seen = now

    def usage(self, key: Hashable, now: float) -> float:
        acc = self._accounts.get(key)
        return 0.0 if acc is None else self._decayed(acc, now)

    def share(self, key: Hashable, now: float) -> float:
        """Recent fraction of the time this session's jobs ran (steady usage p decays to
        p * window_s / ln 2)."""
        return self.usage(key, now) * math.log(2) / self.window_s

    def active(self, now: float) -> int:
        return sum(now - acc.last_seen <= self.window_s for acc in self._accounts.values())

    def cost(self, key: Hashable) -> float:
        acc = self._accounts.get(key)
        return 0.0 if acc is None else acc.cost_s

    def total(self, key: Hashable) -> float:
        acc = self._accounts.get(key)
        return 0.0 if acc is None else acc.total_s

    def forget(self, key: Hashable) -> None:
        self._accounts.pop(key, None)


@dataclass(order=True)
class _Job:
    order: int
    key: Hashable = field(compare=False)
    fn: Callable[..., Any] = field(compare=False)
    args: tuple = field(compare=False)
    future: concurrent.futures.Future = field(compare=False)


class RenderScheduler:
    """``await scheduler.run(fn, *args, key=session_id)``: ``fn`` on a render thread, in the
    order the policy gives. Jobs without a key (warm-up) are served but not accounted."""

    def __init__(self, render_threads: int = 1, threads_per_render: int = 1,
                 policy: Policy = "time", window_s: float = 2.0) -> None:
        if policy not in POLICIES:
            raise ValueError(f"unknown fair-share policy {policy!r}; expected one of {POLICIES}")
        self.render_threads = render_threads
        self.threads_per_render = threads_per_render
        self.policy = policy
        self.share = FairShare(window_s)
        self._cond = threading.Condition()
        self._pending: list[_Job] = []
        self._order = itertools.count()
        self._threads: list[threading.Thread] = []
        self._closed = False
        self.queued = 0   # submitted, not yet finished
        self.running = 0

    # -- submitting ---------------------------------------------------------------------------

    def submit(self, fn: Callable[..., T], *args: Any,
               key: Hashable | None = None) -> concurrent.futures.Future[T]:
        future: concurrent.futures.Future[T] = concurrent.futures.Future()
        with self._cond:
            if self._closed:
                raise RuntimeError("the render scheduler is shut down")
            if not self._threads:
                self._start_threads()
            if key is not None:
                self.share.seen(key, time.monotonic())
            self.queued += 1
            self._pending.append(_Job(next(self._order), key, fn, args, future))
            self._cond.notify()
        future.add_done_callback(self._done)
        return future

    def _done(self, _: concurrent.futures.Future) -> None:
        with self._cond:
            self.queued -= 1

    async def run(self, fn: Callable[..., T], *args: Any, key: Hashable | None = None) -> T:
        """Cancelling the awaiting task cancels a job that has not started yet."""
        return await asyncio.wrap_future(self.submit(fn, *args, key=key))

    # -- fairness ------------------------------------------------------------------------------

    def pace_s(self, key: Hashable) -> float:
        """Seconds to leave between the starts of this session's frames for its fair share."""
        if self.policy != "time":
            return 0.0
        with self._cond:
            now = time.monotonic()
            active = self.share.active(now)
            if active <= self.render_threads:
                return 0.0  # a thread each
            fair = self.render_threads / active
            if self.share.share(key, now) < PACE_FROM * fair:
                return 0.0
            return self.share.cost(key) / fair

    def render_seconds(self, key: Hashable) -> float:
        """All render time this session's jobs took so far."""
        with self._cond:
            return self.share.total(key)

    def forget(self, key: Hashable) -> None:
        """The session ended: it no longer counts as active."""
        with self._cond:
            self.share.forget(key)

    def _next_job(self) -> _Job:
        if self.policy == "frames":
            job = min(self._pending)
        else:
            now = time.monotonic()
            job = min(self._pending, key=lambda j: (
                0.0 if j.key is None else self.share.usage(j.key, now), j.order))
        self._pending.remove(job)
        return job

    # -- workers -------------------------------------------------------------------------------

    def _start_threads(self) -> None:
        for i in range(self.render_threads):
            thread = threading.Thread(target=self._worker, name=f"render_{i}", daemon=True)
            thread.start()
            self._threads.append(thread)

    def _worker(self) -> None:
        limit_threads(self.threads_per_render)
        while True:
            with self._cond:
                while not self._pending and not self._closed:
                    self._cond.wait()
                if not self._pending:
                    return
                job = self._next_job()
                if not job.future.set_running_or_notify_cancel():
                    continue  # cancelled while queued
                self.running += 1
            started = time.perf_counter()
            result, error = None, None
            try:
                result = job.fn(*job.args)
            except BaseException as exc:  # noqa: BLE001 - handed to the awaiting session
                error = exc
            took = time.perf_counter() - started
            with self._cond:
                self.running -= 1
                if job.key is not None:  # accounted before the session sees the result
                    self.share.add(job.key, took, time.monotonic())
            if error is not None:
                job.future.set_exception(error)
            else:
                job.future.set_result(result)

    def shutdown(self) -> None:
        """Cancel what waits, let running jobs finish, stop the workers."""
        with self._cond:
            self._closed = True
            pending, self._pending = self._pending, []
            self._cond.notify_all()
        for job in pending:
            job.future.cancel()
        for thread in self._threads:
            thread.join()
