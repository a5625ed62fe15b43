"""Renders of one avatar state from several views, batched into one rasterizer call.

A room's viewers who see the same drive state with the same request but from different views
each need a render of their own. While the render threads are busy such renders wait in the
scheduler's queue; here they wait in one batch instead: the first render of a batch key
(state versions + request) schedules one job, later ones join it until it starts (or holds
``max_views``), and the job renders them all with ``render_views`` (one gsplat call on CUDA).
Under no load a batch holds one view and starts at once, so batching adds no latency; it
pays only where a batched call is cheaper than its views one by one (gsplat), which is why
the server turns it on only there by default (setting ``render_batch_views``).
"""

from __future__ import annotations

import concurrent.futures
import threading
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from typing import Generic, TypeVar

import torch

from avatar_core.render.rasterize import available_backends
from avatar_core.render.types import GaussianSet

from .scheduler import RenderScheduler, WorkFuture, abandon_check

Item = TypeVar("Item")
Result = TypeVar("Result")

DEFAULT_BATCH_VIEWS = 32  # views per batch where batching pays (gsplat)


def batch_views(setting: int | None, backend: str) -> int:
    """Views per batch: the setting, or with None (auto) ``DEFAULT_BATCH_VIEWS`` when renders
    go to gsplat (:func:`render_device`: the avatar is posed on the CPU, rendered on CUDA) and
    1 (no batching: the cpu kernels gain nothing from it and would lose the parallel render
    threads) otherwise."""
    if setting is not None:
        return setting
    return DEFAULT_BATCH_VIEWS if render_device(backend) is not None else 1


def render_device(backend: str) -> torch.device | None:
    """Where the server renders: CUDA when the backend is gsplat (or auto, with gsplat and a
    CUDA device here); None: where the avatar is posed (the CPU, numba)."""
    if backend == "gsplat" or (backend == "auto" and "gsplat" in available_backends()):
        return torch.device("cuda")
    return None


class DeviceCopies:
    """The newest posed states on the render device: one upload per state (posing stays on
    the CPU, where the numba binding is fast), shared by every view rendered of it."""

    def __init__(self, device: torch.device | None, keep: int = 2) -> None:
        self.device, self.keep = device, keep
        self._lock = threading.Lock()
        self._copies: dict[Hashable, GaussianSet] = {}

    def get(self, key: Hashable, gaussians: GaussianSet) -> GaussianSet:
        if self.device is None or gaussians.means.device == self.device:
            return gaussians
        with self._lock:
            copy = self._copies.get(key)
            if copy is None:
                copy = GaussianSet(*(t.to(self.device) for t in (
                    gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities,
                    gaussians.sh)))
                self._copies[key] = copy
                while len(self._copies) > self.keep:
                    self._copies.pop(next(iter(self._copies)))
            return copy


@dataclass
class _Batch(Generic[Item, Result]):
    key: Hashable
    items: list[Item] = field(default_factory=list)
    futures: list[concurrent.futures.Future] = field(default_factory=list)


@dataclass
class BatchCounters:
    batches: int = 0   # jobs run (rasterizer calls)
    items: int = 0     # renders they served; items - batches renders were saved
    largest: int = 0   # most renders in one batch


class ViewBatches(Generic[Item, Result]):
    """Items of one batch key, run together by ``run(items) -> results`` (same order) on the
    scheduler. Each item gets its own future: cancelling it drops the item (if its batch has
    not started), never the batch; once every item of a running batch is cancelled, the
    batch is abandoned (``scheduler.abandoned``)."""

    def __init__(self, run: Callable[[list[Item]], list[Result]], max_views: int) -> None:
        if max_views < 1:
            raise ValueError(f"max_views must be >= 1, got {max_views}")
        self._run_items = run
        self.max_views = max_views
        self.counters = BatchCounters()
        self._lock = threading.Lock()
        self._open: dict[Hashable, _Batch] = {}  # key -> the batch not started yet

    def submit(self, scheduler: RenderScheduler, key: Hashable, item: Item, *,
               share_key: Hashable | None = None) -> WorkFuture:
        future = WorkFuture()  # cancelled while its batch runs: asks it to stop
        with self._lock:
            batch = self._open.get(key)
            new = batch is None
            if new:
                batch = self._open[key] = _Batch(key)
            batch.items.append(item)
            batch.futures.append(future)
            if len(batch.items) >= self.max_views:
                del self._open[key]  # full: the next render of this key opens another
        if new:
            try:
                job = scheduler.submit(self._run, batch, key=share_key)
            except BaseException:  # shut down: no later render may join a batch never run
                with self._lock:
                    if self._open.get(key) is batch:
                        del self._open[key]
                raise
            job.add_done_callback(lambda done: _fail_unfinished(done, batch.futures))
        return future

    def _run(self, batch: _Batch) -> None:
        with self._lock:  # started: later renders open a new batch
            if self._open.get(batch.key) is batch:
                del self._open[batch.key]
        live = [(item, fut) for item, fut in zip(batch.items, batch.futures, strict=True)
                if fut.set_running_or_notify_cancel()]
        if not live:
            return
        try:
            with abandon_check(lambda: all(fut.stop_asked for _, fut in live)):
                results = self._run_items([item for item, _ in live])
            if len(results) != len(live):
                raise RuntimeError(f"a batch of {len(live)} gave {len(results)} results")
        except BaseException as exc:  # noqa: BLE001 - handed to every waiting viewer
            for _, fut in live:
                fut.set_exception(exc)
            return
        with self._lock:
            c = self.counters
            c.batches += 1
            c.items += len(live)
            c.largest = max(c.largest, len(live))
        for (_, fut), result in zip(live, results, strict=True):
            fut.set_result(result)


def _fail_unfinished(job: concurrent.futures.Future, futures: list) -> None:
    """The batch's job was cancelled (scheduler shut down) or failed outside ``run``: its
    items' futures must not wait forever."""
    if not (job.cancelled() or job.exception() is not None):
        return
    error = job.exception() if not job.cancelled() else concurrent.futures.CancelledError()
    for fut in futures:
        if fut.done() or not (fut.running() or fut.set_running_or_notify_cancel()):
            continue
        try:
            fut.set_exception(error)
        except concurrent.futures.InvalidStateError:
            pass  # finished meanwhile
