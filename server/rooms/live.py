"""An occupied room: seats (drive state, performer, hold/ease), participants, presence.

Everything here runs on the event loop. A drive applied to a seat wakes every participant's
render loop; each then renders (or shares) the newest state. A performer who leaves: the seat
holds its last pose for ``room_seat_hold_s``, then eases back to rest over ``room_seat_ease_s``.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from protocol import Presence, SeatPresence, Voice

from ..stream.drive import DriveState, rest_value
from ..stream.scene import Scene
from .registry import Room, SeatSpec
from .voice import publish_message

if TYPE_CHECKING:
    from ..stream.session import Session
    from ..stream.tracking import SessionTracker
    from .voice import SeatVoice

log = logging.getLogger(__name__)

EASE_STEP_S = 1 / 20   # easing back to rest: a new pose this often
KEEP_ON_EASE = frozenset({"betas", "shape"})  # identity, not pose: kept until the reset
CLOSE_GONE = 4410


def _toward_rest(family: str, name: str, value: np.ndarray, weight: float) -> np.ndarray:
    """``weight`` of the way from the rest value to ``value`` (1: ``value``, 0: at rest)."""
    rest = rest_value(family, name, value)
    return rest + (value - rest) * weight


@dataclass
class Seat:
    spec: SeatSpec
    drive: DriveState = field(default_factory=DriveState)
    performer: Session | None = None
    holding: bool = False
    release: asyncio.Task | None = None  # hold, then ease to rest
    voice: SeatVoice | None = None  # its performer's voice (server/rooms/voice.py), on first use
    on_speaking: Callable[[], None] | None = None  # its voice started speaking

    @property
    def index(self) -> int:
        return self.spec.index


class JoinRefused(Exception):
    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code, self.message = code, message


class LiveRoom:
    def __init__(self, room: Room, scene: Scene, settings) -> None:
        self.room = room
        self.scene = scene
        self.settings = settings
        self.seats = [Seat(spec, on_speaking=self._speaking_started) for spec in room.seats]
        self.participants: list[Session] = []
        self.closed = False
        self._closing: set[asyncio.Task] = set()
        self._speaking_task: asyncio.Task | None = None
        self.voice_mix: Any = None  # the room's mixed voice, while someone asked (voice_mix.py)
        self.video_fanout: Any = None  # its WebRTC viewers' shared encodes (webrtc/fanout.py)
        self._announced: tuple[bool, ...] = (False,) * len(self.seats)
        self._announced_at = -float("inf")

    # -- seats ----------------------------------------------------------------------------------

    def seat(self, index: int) -> Seat | None:
        return next((s for s in self.seats if s.index == index), None)

    def snapshot(self) -> tuple[DriveState, ...]:
        return tuple(s.drive.copy() for s in self.seats)

    def voice(self, performer: Session, message: Voice) -> str:
        """A performer's ``voice`` message to its seat's listeners; the outcome."""
        return publish_message(self.seat(performer.seat_index), performer, message,
                               self.settings, performer.metrics)

    def seat_changed(self) -> None:
        """A seat's drive changed: every participant renders the new state."""
        for p in self.participants:
            p.wake()

    # -- an avatar replaced in place ------------------------------------------------------------

    def replace_scene(self, scene: Scene, tracker: Callable[[Session], SessionTracker | None],
                      sh_degree: tuple[int, int] | None = None) -> None:
        """Show ``scene`` (this room's seats with an avatar reloaded) from now on. Every
        participant switches to it and keeps its connection; ``tracker(participant)`` gives
        a performer its new webcam tracker (None: the old one stays); ``sh_degree``: see
        :meth:`Session.switch_scene`. A seat whose
        parameter shapes changed goes back to the rest pose. The old scene is closed once no
        thread renders for it any more."""
        old, self.scene = self.scene, scene
        for seat, before, after in zip(self.seats, old.shapes, scene.shapes, strict=True):
            if before != after:
                seat.drive.families = {family: {} for family in seat.drive.families}
                seat.drive.version += 1
        pending = [f for p in self.participants if (f := p.render_work()) is not None]
        for p in self.participants:
            p.switch_scene(scene, tracker(p), sh_degree)
        _when_done(pending, old.close)

    # -- joining and leaving ----------------------------------------------------------------------

    def default_name(self, role: str) -> str:
        """The display name of a participant that gave none: "performer", or "viewer N" with
        the smallest N no one here has (call it just before ``join``, with no await between,
        so that two viewers never get the same one)."""
        if role == "perform":
            return "performer"
        taken = {p.name for p in self.participants}
        return next(f"viewer {n}" for n in range(1, len(taken) + 2)
                    if f"viewer {n}" not in taken)

    def join(self, participant: Session) -> None:
        if self.closed:
            raise JoinRefused("gone", f"room {self.room.id!r} was closed")
        if len(self.participants) >= self.settings.max_participants_per_room:
            raise JoinRefused("busy", f"room {self.room.id!r} has "
                                      f"{len(self.participants)} participants, the most it "
                                      "may have (max_participants_per_room)")
        if participant.role == "perform":
            seat = self.seat(participant.seat_index)
            if seat.performer is not None:
                raise JoinRefused("forbidden", f"seat {seat.index} is performed by "
                                               f"{seat.performer.name!r} already")
            seat.performer = participant
            self._stop_release(seat)
        self.participants.append(participant)
        self.room.empty_since = None

    def leave(self, participant: Session) -> None:
        if participant not in self.participants:
            return
        self.participants.remove(participant)
        if participant.role == "perform":
            seat = self.seat(participant.seat_index)
            if seat.performer is participant:
                seat.performer = None
                self._start_release(seat)
        if not self.participants:
            self.room.empty_since = time.monotonic()
            if self.closed or self.room.private:  # nobody comes back: the scene goes
                self.closed = True
                participant.after_work(self._dispose)
        self.broadcast(self.presence("leave", participant))

    # -- presence -------------------------------------------------------------------------------

    def presence(self, event: str = "update", who: Session | None = None) -> Presence:
        seats = [SeatPresence(index=s.index, avatar=s.spec.avatar,
                              performer=None if s.performer is None else s.performer.name,
                              holding=s.holding,
                              speaking=s.voice is not None and s.voice.speaking)
                 for s in self.seats]
        return Presence(room=self.room.id, seats=seats,
                        viewers=sum(p.role == "watch" for p in self.participants),
                        event=event, who=None if who is None else who.name,
                        role=None if who is None else who.role)

    def speaking(self) -> tuple[bool, ...]:
        return tuple(s.voice is not None and s.voice.speaking for s in self.seats)

    def _speaking_started(self) -> None:
        """A seat's voice began speaking: presence follows it until nobody speaks (a task
        only while someone speaks; a silent room wakes nobody)."""
        if self.room.private or self.closed:
            return
        if self._speaking_task is None or self._speaking_task.done():
            self._speaking_task = asyncio.get_running_loop().create_task(
                self._follow_speaking(), name=f"room {self.room.id} speaking")

    async def _follow_speaking(self) -> None:
        interval = self.settings.voice_presence_interval_s
        while not self.closed:
            wait = self._announced_at + interval - time.monotonic()
            if wait > 0:  # the bound on presence updates, across restarts of this task
                await asyncio.sleep(wait)
            now = self.speaking()
            if now != self._announced:
                self._announced, self._announced_at = now, time.monotonic()
                self.broadcast(self.presence("update"))
            if not any(now):
                return
            await asyncio.sleep(interval)

    def broadcast(self, message: Presence) -> None:
        if self.room.private:
            return  # a plain session: nobody else to tell
        for p in self.participants:
            p.send_control(message)

    # -- a performer gone: hold, ease to rest ---------------------------------------------------

    def _start_release(self, seat: Seat) -> None:
        self._stop_release(seat)
        seat.holding = True
        seat.release = asyncio.get_running_loop().create_task(self._release(seat))

    def _stop_release(self, seat: Seat) -> None:
        if seat.release is not None:
            seat.release.cancel()
            seat.release = None
        seat.holding = False

    async def _release(self, seat: Seat) -> None:
        s = self.settings
        await asyncio.sleep(s.room_seat_hold_s)
        held = {family: dict(values) for family, values in seat.drive.families.items()}
        steps = max(1, round(s.room_seat_ease_s / EASE_STEP_S))
        for step in range(1, steps):
            weight = 1.0 - step / steps
            seat.drive.families = {
                family: {name: value if name in KEEP_ON_EASE else _toward_rest(
                    family, name, np.asarray(value), weight) for name, value in values.items()}
                for family, values in held.items()}
            seat.drive.version += 1
            self.seat_changed()
            await asyncio.sleep(s.room_seat_ease_s / steps)
        seat.drive.families = {family: {} for family in held}  # the rest pose
        seat.drive.version += 1
        seat.holding = False
        seat.release = None
        self.seat_changed()
        self.broadcast(self.presence("update"))

    # -- closing --------------------------------------------------------------------------------

    def close(self, message: str) -> None:
        """The room is gone: everyone gets error ``gone`` and close code 4410."""
        self.closed = True
        if self._speaking_task is not None:
            self._speaking_task.cancel()
        for seat in self.seats:
            if seat.release is not None:
                seat.release.cancel()
        if not self.participants:
            self._dispose()
        for p in list(self.participants):
            task = asyncio.get_running_loop().create_task(
                p.close_with("gone", message, CLOSE_GONE))
            self._closing.add(task)
            task.add_done_callback(self._closing.discard)

    def _dispose(self) -> None:
        """Closed and empty: the scene goes (here, or on its render worker)."""
        self.scene.close()


def _when_done(futures: list[concurrent.futures.Future], fn: Callable[[], None]) -> None:
    """``fn()`` once every future is done (at once when none is pending)."""
    left = [len(futures)]
    if not futures:
        fn()
        return

    def one_done(_: concurrent.futures.Future) -> None:
        left[0] -= 1
        if not left[0]:
            fn()

    for future in futures:
        future.add_done_callback(one_done)
