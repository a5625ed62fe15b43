"""The shared renderer: every session's frames run on one small pool of render threads.

Fairness is of render time, not of frames (policy ``"time"``, the default). A session never
has more than one render queued or running (its loop awaits each frame before asking for the
next), so a first-in first-out queue would serve busy sessions in turn, one frame each: a
session asking 1920x1080 PNG with alpha and depth would then take nearly all the time from one
asking 128 px JPEG. Instead the scheduler measures each job (pose, rasterize, encode) and

* serves the waiting session that used the least render time recently (decayed with a
  half-life of ``window_s``), and
* paces a session that takes more than its share (:meth:`pace_s`): with N sessions active
  in the last ``window_s`` (N > render_threads) the fair share is ``f = render_threads / N``
  of the render time. Each session has a credit of render seconds that refills at f per
  second (at most ``f * window_s`` saved up) and that each of its frames spends; a session in
  debt waits until the refill pays it back, so over time it holds f and the others the rest.
  A session within its share, or alone, is not held back, so time that nobody else wants is
  used; what a capped session leaves unused of its share stays idle.

Policy ``"frames"`` keeps the plain first-in first-out round-robin (equal frame rates).

A job is charged before it runs, not only after: when it starts, its session is debited an
estimate (the time its session's last job took) and its usage raised by as much, and when it
ends the estimate is replaced by what it really took. So while an expensive frame runs, its
session already counts as having spent it: its other jobs (a room's participants asking
different views) queue behind everyone else's and it is paced from the moment it starts,
and the render threads cannot all be taken by one session's frames. What one frame can cost
is bounded where it is made (the rasterizer's ``max_tile_pairs``), since no scheduler can
take back a thread a frame already holds.

A running job can be abandoned: ``future.cancel()`` on a running job's :class:`WorkFuture`
cannot stop it, but records the wish (``stop_asked``); the job reads it on its own thread with
:func:`abandoned` between its stages and stops there (server/stream/scene.py).

Threads: torch's intra-op pool is process-wide and numba's thread count is per calling
thread; both are set to ``threads_per_render`` so that ``render_threads`` workers do not
oversubscribe the cores (on 2 cores: 1 x 2 or 2 x 1, never 2 x 2). With ``spread`` (the
automatic choice, avatar_core/threads.py ``render_threads``), a job's numba kernels use
``spread // running`` threads: a lone frame spreads over the cores, concurrent frames get one
core each.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import itertools
import math
import threading
import time
from collections.abc import Callable, Hashable, Iterator
from dataclasses import dataclass, field
from typing import Any, Literal, TypeVar

T = TypeVar("T")
Policy = Literal["time", "frames"]
POLICIES: tuple[Policy, ...] = ("time", "frames")


def limit_threads(threads: int) -> None:
    """torch and numba threads of the calling thread's work (a worker initializer)."""
    import torch

    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)
    numba_threads(threads)


def numba_threads(threads: int) -> None:
    """numba's threads for the calling thread's parallel kernels (per thread, cheap)."""
    try:
        import numba

        threads = min(threads, numba.config.NUMBA_NUM_THREADS)
        if numba.get_num_threads() != threads:
            numba.set_num_threads(threads)
    except (ImportError, ValueError):
        pass


class WorkFuture(concurrent.futures.Future):
    """A job's future whose ``cancel()`` while the job runs asks it to stop (``stop_asked``,
    read by :func:`abandoned` on the job's thread) instead of doing nothing."""

    def __init__(self) -> None:
        super().__init__()
        self.stop_asked = False

    def cancel(self) -> bool:
        if super().cancel():
            return True
        if not self.done():
            self.stop_asked = True  # running: it stops at its next check
        return False


_running = threading.local()  # .check: the job on this thread was abandoned, () -> bool


def abandoned() -> bool:
    """Whether everyone waiting for the job running on this thread has cancelled it: a
    job polls this between its stages and stops when it is set. False outside a job."""
    check = getattr(_running, "check", None)
    return check is not None and check()


@contextlib.contextmanager
def abandon_check(check: Callable[[], bool]) -> Iterator[None]:
    """Inside, :func:`abandoned` on this thread is ``check()`` (a job running several
    waiters' work, a batch: abandoned when all of them are)."""
    previous = getattr(_running, "check", None)
    _running.check = check
    try:
        yield
    finally:
        _running.check = previous


@dataclass
class _Account:
    usage_s: float = 0.0           # render seconds, decayed to `stamp`: the serving order
    stamp: float = 0.0
    credit_s: float = math.inf     # render seconds it may take before it is paced
    credit_stamp: float = 0.0
    last_seen: float = 0.0         # last submit or finish
    total_s: float = 0.0           # all render seconds, never decayed (metrics, tests)
    last_job_s: float = 0.0        # what its last job took: the next one's estimate


class FairShare:
    """Per-session render time: decayed usage (who goes first), credit (who must wait), and
    who is active. Credit refills at the fair share f (render seconds per second) up to
    ``f * window_s``, and each job takes what it cost; a session in debt waits until it is
    paid back. While no more sessions are active than there are threads, nobody is in debt."""

    def __init__(self, window_s: float, threads: int) -> None:
        self.window_s = window_s
        self.threads = threads
        self._accounts: dict[Hashable, _Account] = {}

    def _decayed(self, acc: _Account, now: float) -> float:
        return acc.usage_s * math.exp2(-(now - acc.stamp) / self.window_s)

    def fair(self, now: float) -> float | None:
        """Each active session's share of one second of render time; None: a thread each."""
        active = sum(now - acc.last_seen <= self.window_s for acc in self._accounts.values())
        return None if active <= self.threads else self.threads / active

    def _credit(self, acc: _Account, now: float, fair: float) -> float:
        return min(fair * self.window_s, acc.credit_s + fair * (now - acc.credit_stamp))

    def seen(self, key: Hashable, now: float) -> None:
        self._accounts.setdefault(key, _Account(stamp=now, credit_stamp=now)).last_seen = now

    def _spend(self, acc: _Account, seconds: float, now: float) -> None:
        acc.usage_s, acc.stamp = max(0.0, self._decayed(acc, now) + seconds), now
        fair = self.fair(now)
        credit = math.inf if fair is None else self._credit(acc, now, fair)
        acc.credit_s, acc.credit_stamp = credit - seconds, now

    def start(self, key: Hashable, now: float) -> float:
        """A job of ``key`` starts: it is charged its estimate now (what the key's last job
        took), which is returned, to be passed to :meth:`add` when the job ends."""
        acc = self._accounts.setdefault(key, _Account(stamp=now, credit_stamp=now))
        estimate = acc.last_job_s
        self._spend(acc, estimate, now)
        acc.last_seen = now
        return estimate

    def add(self, key: Hashable, seconds: float, now: float, charged: float = 0.0) -> None:
        """A job of ``key`` took ``seconds``; ``charged``: what :meth:`start` charged it."""
        acc = self._accounts.setdefault(key, _Account(stamp=now, credit_stamp=now))
        self._spend(acc, seconds - charged, now)
        acc.total_s += seconds
        acc.last_job_s = seconds
        acc.last_seen = now

    def add_if_known(self, key: Hashable, seconds: float, now: float,
                     charged: float = 0.0) -> None:
        """``add`` for an account still kept: a job that finishes after its session was
        forgotten does not bring the account back (it would never be forgotten again)."""
        if key in self._accounts:
            self.add(key, seconds, now, charged)

    def usage(self, key: Hashable, now: float) -> float:
        acc = self._accounts.get(key)
        return 0.0 if acc is None else self._decayed(acc, now)

    def wait_s(self, key: Hashable, now: float) -> float:
        """Seconds until this session's credit is back to zero (0: it may go now)."""
        acc, fair = self._accounts.get(key), self.fair(now)
        if acc is None or fair is None:
            return 0.0
        return max(0.0, -self._credit(acc, now, fair)) / fair

    def total(self, key: Hashable) -> float:
        acc = self._accounts.get(key)
        return 0.0 if acc is None else acc.total_s

    def stalled(self, key: Hashable) -> None:
        acc = self._accounts.get(key)
        if acc is not None:
            acc.last_seen = -math.inf  # active again at its next submit

    def forget(self, key: Hashable) -> None:
        self._accounts.pop(key, None)


@dataclass(order=True)
class _Job:
    order: int
    key: Hashable = field(compare=False)
    fn: Callable[..., Any] = field(compare=False)
    args: tuple = field(compare=False)
    future: WorkFuture = field(compare=False)


class RenderScheduler:
    """``scheduler.submit(fn, *args, key=session_id)``: ``fn`` on a render thread, in the
    order the policy gives. Jobs without a key (warm-up) are served but not accounted."""

    def __init__(self, render_threads: int = 1, threads_per_render: int = 1,
                 policy: Policy = "time", window_s: float = 2.0, spread: int = 0) -> None:
        if policy not in POLICIES:
            raise ValueError(f"unknown fair-share policy {policy!r}; expected one of {POLICIES}")
        self.render_threads = render_threads
        self.threads_per_render = threads_per_render
        self.spread = spread  # > threads_per_render: numba threads per job = spread // running
        self.policy = policy
        self.share = FairShare(window_s, render_threads)
        self._cond = threading.Condition()
        self._pending: list[_Job] = []
        self._order = itertools.count()
        self._threads: list[threading.Thread] = []
        self._closed = False
        self.queued = 0   # submitted, not yet finished
        self.running = 0

    # -- submitting ---------------------------------------------------------------------------

    def submit(self, fn: Callable[..., T], *args: Any,
               key: Hashable | None = None) -> WorkFuture:
        """``fn(*args)`` on a render thread; its future's ``cancel()`` drops it while queued
        and asks it to stop (:func:`abandoned`) while it runs."""
        future = WorkFuture()
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

    # -- fairness ------------------------------------------------------------------------------

    def pace_s(self, key: Hashable) -> float:
        """Seconds this session should wait, from now, before its next frame starts."""
        if self.policy != "time":
            return 0.0
        with self._cond:
            return self.share.wait_s(key, time.monotonic())

    def render_seconds(self, key: Hashable) -> float:
        """All render time this session's jobs took so far."""
        with self._cond:
            return self.share.total(key)

    def stalled(self, key: Hashable) -> None:
        """The session waits on its client, not on the renderer: until its next job it does
        not count as active (its share goes to the others)."""
        with self._cond:
            self.share.stalled(key)

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
                spread = self.spread // self.running
                charged = 0.0
                if job.key is not None:  # charged as it starts, settled when it ends
                    charged = self.share.start(job.key, time.monotonic())
            if self.spread > self.threads_per_render:
                numba_threads(max(self.threads_per_render, spread))
            started = time.perf_counter()
            result, error = None, None
            future = job.future
            try:
                with abandon_check(lambda f=future: f.stop_asked):
                    result = job.fn(*job.args)
            except BaseException as exc:  # noqa: BLE001 - handed to the awaiting session
                error = exc
            took = time.perf_counter() - started
            with self._cond:
                self.running -= 1
                if job.key is not None:  # accounted before the session sees the result
                    self.share.add_if_known(job.key, took, time.monotonic(), charged)
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
