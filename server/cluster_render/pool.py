"""The gateway's render workers: ``render_actors`` Ray actors, scenes placed on them by load,
frames dispatched to them, and failover when one dies.

Placement: a new scene goes to the ready worker with the fewest active scenes (a scene is
active while frames are asked of it), ties broken by the worker's recent render time per
frame. A scene stays on its worker until the worker is lost or the scene goes idle.

Failover: a frame whose call fails with RayActorError (the actor died or became unreachable)
marks its worker lost: the worker is killed for good, its scenes are unplaced and their
participants get an ``error`` of code ``reconnecting``; the frame is asked again of another
ready worker (which opens the scene from its seats on the spot) and a replacement actor is
started in the lost one's slot. The drive state is the gateway's and travels with every
frame, so only the frames in flight are lost. If no worker is ready within
``render_actor_restart_s``, the scene's participants get an ``error`` saying so and are
closed (1013, try again later).

Fair share: each scene's frames are accounted with their workers' own timings, and a scene
that takes more than its share is paced (:meth:`RenderPool.pace_s`), as on the local render
threads (``fair_share = "time"``; ``"frames"`` paces nothing). All state here is touched on
the gateway's event loop only; frames are handed to the
sessions as concurrent futures (``asyncio.run_coroutine_threadsafe``), as the local render
threads do.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import time
import uuid
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

from ..stream.scene import Frame, FrameJob
from ..stream.scheduler import FairShare
from .worker import RenderWorker, SeatSource, WorkerConfig

log = logging.getLogger(__name__)

ACTIVE_S = 10.0          # a scene asked no frame for this long no longer counts as load
IDLE_CLOSE_S = 120.0     # ... and for this long is closed on its worker (re-opened on demand)
SWEEP_S = 5.0
RETRY_MAX_S = 30.0       # longest wait between tries to start a worker in a slot
FRAME_MS_DECAY = 0.9     # per frame: the recent render time per frame a worker reports


class RenderUnavailable(RuntimeError):
    """No render worker could take a scene within render_actor_restart_s."""


@dataclass(eq=False)
class Worker:
    slot: int
    name: str
    handle: Any
    state: str = "starting"  # starting -> ready -> lost
    pid: int | None = None
    host: str | None = None
    frames: int = 0
    frame_ms: float = 0.0    # decayed mean of the frames' pose + render + encode time
    scenes: set[str] = field(default_factory=set)
    gone: asyncio.Event = field(default_factory=asyncio.Event)

    def load(self, scenes: dict[str, RemoteScene], now: float) -> tuple[int, float]:
        active = sum(now - scenes[s].used < ACTIVE_S for s in self.scenes if s in scenes)
        return active, self.frame_ms


@dataclass(eq=False)
class RemoteScene:
    """A scene as the pool places it: its seats, who hears its notices, its worker."""

    id: str
    seats: tuple[SeatSource, ...]
    audience: Callable[[], Iterable[Any]]  # the sessions that get its notices
    kind: str                               # "room" / "session"
    worker: Worker | None = None
    used: float = field(default_factory=time.monotonic)
    failed: bool = False


class RenderPool:
    def __init__(self, settings, config: WorkerConfig) -> None:
        self.settings = settings
        self.config = config
        self.prefix = f"render-{uuid.uuid4().hex[:6]}"  # actor names: unique per gateway
        self.workers: list[Worker] = []
        self.scenes: dict[str, RemoteScene] = {}
        self.share = FairShare(settings.fair_share_window_s, max(1, settings.render_actors))
        self.lost = 0          # workers lost since start-up (metrics, tests)
        self.replaced = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._changed: asyncio.Condition | None = None
        self._tasks: set[asyncio.Task] = set()
        self._generation = 0
        self._actor_class = None
        self._actor_options: dict[str, Any] = {}
        self._stopped = False

    # -- lifetime ----------------------------------------------------------------------------

    async def start(self) -> None:
        """Connect to the cluster and start the actors (their readiness is awaited by the
        first frames, bounded by render_actor_restart_s; start-up does not wait)."""
        import ray

        from .. import cluster

        await asyncio.to_thread(cluster.connect, self.settings)
        self._loop = asyncio.get_running_loop()
        self._changed = asyncio.Condition()
        s = self.settings
        self._actor_class = ray.remote(RenderWorker)
        self._actor_options = {
            "num_cpus": s.render_actor_num_cpus, "num_gpus": s.render_actor_num_gpus,
            "namespace": cluster.NAMESPACE, "max_restarts": 0,  # replaced here, not by Ray
            "max_concurrency": 1}
        for slot in range(s.render_actors):
            self._background(self._supervise(slot), f"render-pool:slot-{slot}")
        self._background(self._sweep(), "render-pool:sweep")

    async def stop(self) -> None:
        self._stopped = True
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        for worker in self.workers:
            if worker.state != "lost":
                self._kill(worker)
        self.workers.clear()

    def _background(self, coro, name: str) -> asyncio.Task:
        task = asyncio.get_running_loop().create_task(coro, name=name)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    def _spawn(self, slot: int) -> Worker:
        self._generation += 1
        name = f"{self.prefix}-{slot}-{self._generation}"
        handle = self._actor_class.options(name=name, **self._actor_options).remote(self.config)
        worker = Worker(slot, name, handle)
        self.workers = sorted([w for w in self.workers if w.slot != slot] + [worker],
                              key=lambda w: w.slot)
        return worker

    async def _supervise(self, slot: int) -> None:
        """Keep a worker in ``slot``: start one, and a new one whenever it is lost (backing
        off while they fail to start)."""
        wait = 1.0
        while True:
            worker = None
            try:  # ready once its constructor ran (torch imported, threads set)
                worker = self._spawn(slot)
                info = await self._call(worker, worker.handle.ping.remote())
            except Exception as exc:  # noqa: BLE001 - any failure: the slot is tried again
                log.warning("render worker in slot %d did not start: %r", slot, exc)
                if worker is not None:
                    self._kill(worker)
                await self._notify()
                await asyncio.sleep(wait)
                wait = min(RETRY_MAX_S, wait * 2)
                continue
            if worker.state == "starting":
                worker.state, worker.pid, worker.host = "ready", info["pid"], info["host"]
                log.info("render worker %s ready (pid %s on %s)", worker.name, worker.pid,
                         worker.host)
                wait = 1.0
                await self._notify()
            await worker.gone.wait()
            self.replaced += 1

    def _kill(self, worker: Worker) -> None:
        import ray

        worker.state = "lost"
        worker.gone.set()
        try:
            ray.kill(worker.handle, no_restart=True)
        except Exception:  # noqa: BLE001 - already gone
            pass

    async def _notify(self) -> None:
        async with self._changed:
            self._changed.notify_all()

    def call_soon(self, fn: Callable[..., Any], *args: Any) -> None:
        """``fn(*args)`` on the gateway's loop, from any thread (nothing once stopped)."""
        if self._loop is not None and not self._loop.is_closed():
            self._loop.call_soon_threadsafe(fn, *args)

    # -- scenes -----------------------------------------------------------------------------

    def scene(self, scene_id: str, seats: tuple[SeatSource, ...],
              audience: Callable[[], Iterable[Any]], kind: str) -> RemoteScene:
        scene = self.scenes.get(scene_id)
        if scene is None or scene.seats != seats:
            scene = self.scenes[scene_id] = RemoteScene(scene_id, seats, audience, kind)
        scene.audience = audience
        return scene

    async def open(self, scene: RemoteScene) -> None:
        """Place the scene and load its avatars on its worker now (a broken package fails
        here, at the join, with the package's own error)."""
        await self._on_worker(scene, lambda w: w.handle.open.remote(scene.id, scene.seats))

    def close(self, scene: RemoteScene) -> None:
        """The scene is gone (its room closed, its session ended): its worker frees it."""
        self.share.forget(scene.id)
        if self.scenes.get(scene.id) is scene:
            del self.scenes[scene.id]
        self._unplace(scene, close=True)

    def _unplace(self, scene: RemoteScene, close: bool) -> None:
        worker, scene.worker = scene.worker, None
        if worker is None:
            return
        worker.scenes.discard(scene.id)
        if close and worker.state == "ready":
            worker.handle.close.remote(scene.id)  # fire and forget: a lost worker frees all

    # -- frames -----------------------------------------------------------------------------

    def submit(self, scene: RemoteScene, job: FrameJob) -> concurrent.futures.Future:
        """The frame of ``job``, made on the scene's worker (from any thread)."""
        return asyncio.run_coroutine_threadsafe(self.frame(scene, job), self._loop)

    async def frame(self, scene: RemoteScene, job: FrameJob) -> Frame:
        scene.used = time.monotonic()
        self.share.seen(scene.id, scene.used)
        self.scenes.setdefault(scene.id, scene)  # back after the idle sweep
        worker, frame = await self._on_worker(scene, lambda w: w.handle.render.remote(
            scene.id, scene.seats, job))
        t = frame.timings
        took = t.pose + t.render + t.encode
        self.share.add_if_known(scene.id, took / 1e3, time.monotonic())
        worker.frame_ms = (took if worker.frames == 0 else
                           FRAME_MS_DECAY * worker.frame_ms + (1 - FRAME_MS_DECAY) * took)
        worker.frames += 1
        return frame

    def release(self, scene: RemoteScene, participant: Any) -> None:
        """What a participant's frames kept on the scene's worker (stateful encoders) goes."""
        worker = scene.worker
        if worker is not None and worker.state == "ready":
            worker.handle.release.remote(scene.id, participant)  # fire and forget

    # -- fair share ---------------------------------------------------------------------------

    def pace_s(self, key: str) -> float:
        if self.settings.fair_share != "time":
            return 0.0
        return self.share.wait_s(key, time.monotonic())

    def stalled(self, key: str) -> None:
        self.share.stalled(key)

    def forget(self, key: str) -> None:
        self.share.forget(key)

    async def _on_worker(self, scene: RemoteScene, call: Callable[[Worker], Any]
                         ) -> tuple[Worker, Any]:
        """``call(worker)``'s result from the scene's worker; a worker lost meanwhile: the
        call goes to another (within render_actor_restart_s of the loss)."""
        import ray

        deadline = None  # set at the first loss: how long the call may wait for a worker
        while True:
            worker = await self._placed(scene, deadline or self._deadline())
            try:
                return worker, await self._call(worker, call(worker))
            except ray.exceptions.RayActorError:
                await self._lose(worker, "died")
                deadline = deadline or self._deadline()

    async def _call(self, worker: Worker, ref) -> Any:
        return await asyncio.wrap_future(ref.future())

    def _deadline(self) -> float:
        return time.monotonic() + self.settings.render_actor_restart_s

    async def _placed(self, scene: RemoteScene, deadline: float) -> Worker:
        """The scene's worker, placing it on the least loaded ready one (waiting for one
        until ``deadline``); RenderUnavailable when none came."""
        if self._stopped:
            raise RenderUnavailable("the server is stopping")
        async with self._changed:
            while True:
                if scene.worker is not None and scene.worker.state == "ready":
                    return scene.worker
                ready = [w for w in self.workers if w.state == "ready"]
                if ready:
                    now = time.monotonic()
                    worker = min(ready, key=lambda w: (*w.load(self.scenes, now), w.slot))
                    scene.worker, scene.failed = worker, False
                    worker.scenes.add(scene.id)
                    return worker
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                try:
                    await asyncio.wait_for(self._changed.wait(), left)
                except TimeoutError:
                    break
        message = (f"no render worker is available: none was ready within "
                   f"render_actor_restart_s = {self.settings.render_actor_restart_s:g} s; "
                   "try again later")
        self._fail(scene, message)
        raise RenderUnavailable(message)

    # -- failover ---------------------------------------------------------------------------

    async def _lose(self, worker: Worker, why: str) -> None:
        """A worker is gone: killed for good (its slot's supervisor starts a new one), its
        scenes unplaced and their participants told."""
        if worker.state == "lost":
            return
        from .notices import reconnecting

        self.lost += 1
        log.warning("render worker %s %s; its %d scene(s) move", worker.name, why,
                    len(worker.scenes))
        self._kill(worker)
        moved = [self.scenes[s] for s in sorted(worker.scenes) if s in self.scenes]
        worker.scenes.clear()
        for scene in moved:
            scene.worker = None
            for session in scene.audience():
                session.send_control(reconnecting(worker.name))
        await self._notify()

    def _fail(self, scene: RemoteScene, message: str) -> None:
        """No worker for the scene: its participants are told and closed (once)."""
        from .notices import close_unavailable

        if scene.failed:
            return
        scene.failed = True
        for session in list(scene.audience()):
            self._background(close_unavailable(session, message), "render-pool:close")

    async def _sweep(self) -> None:
        """Scenes asked nothing for IDLE_CLOSE_S are closed on their workers (a room left
        empty, a session that never started); a room's is placed again at its next frame."""
        while True:
            await asyncio.sleep(SWEEP_S)
            now = time.monotonic()
            for scene in [s for s in self.scenes.values() if now - s.used >= IDLE_CLOSE_S]:
                self.close(scene)

    # -- what an operator sees ----------------------------------------------------------------

    def placement(self) -> dict:
        now = time.monotonic()
        return {
            "backend": "ray",
            "workers": [{"name": w.name, "slot": w.slot, "state": w.state, "pid": w.pid,
                         "host": w.host, "frames": w.frames, "frame_ms": round(w.frame_ms, 2),
                         "scenes": sorted(w.scenes),
                         "active_scenes": w.load(self.scenes, now)[0]}
                        for w in self.workers],
            "scenes": {s.id: {"kind": s.kind, "worker": None if s.worker is None else
                              s.worker.name, "avatars": [seat.avatar for seat in s.seats]}
                       for s in self.scenes.values()},
            "lost": self.lost, "replaced": self.replaced,
        }
