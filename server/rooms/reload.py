"""An avatar replaced in place (the trained demo swapped in for its stand-in,
server/jobs/demo_build.py): every scene that shows it is reopened with the new one, and its
participants (performers and viewers, of rooms and plain sessions alike) keep their
connections, get an ``avatar`` message and then frames of the new avatar. Runs on the event
loop, one room at a time, under the room's ``opening`` lock (a join waits for it)."""

from __future__ import annotations

import asyncio
import logging
from functools import partial
from typing import TYPE_CHECKING

from protocol import AvatarReplaced

from .join import avatar_info

if TYPE_CHECKING:
    from ..context import ServerContext
    from ..registry import AvatarRecord
    from .registry import Room

log = logging.getLogger(__name__)


def _rooms_showing(ctx: ServerContext, avatar_id: str) -> list[Room]:
    """Rooms with a runtime that seat ``avatar_id``: the registry's (pinned or recently
    joined ones too) and the private rooms of plain sessions."""
    rooms = {id(r): r for r in ctx.rooms.live_rooms()}
    for session in list(ctx.sessions.values()):
        rooms.setdefault(id(session.live.room), session.live.room)
    return [r for r in rooms.values() if r.live is not None and not r.live.closed
            and any(spec.avatar == avatar_id for spec in r.seats)]


async def reload_avatar(ctx: ServerContext, avatar_id: str,
                        previous: AvatarRecord | None = None) -> int:
    """Reopen every live scene that shows ``avatar_id`` (already replaced in the registry;
    ``previous``: the record it replaced); the number of rooms reloaded. A room that fails
    to reload keeps its old scene."""
    ctx.forget_models(avatar_id)
    record = ctx.registry.get(avatar_id)
    try:  # the page labels its sliders from these, as from the welcome's
        names = (await asyncio.to_thread(ctx.rig, avatar_id)).expression_names
    except Exception:  # noqa: BLE001 - a broken package fails below, where it is reported
        names = ()
    message = AvatarReplaced(avatar=avatar_info(record, names), seats=[])
    sh_degree = None if previous is None else (previous.sh_degree, record.sh_degree)
    reloaded = 0
    for room in _rooms_showing(ctx, avatar_id):
        seats = [spec.index for spec in room.seats if spec.avatar == avatar_id]
        async with room.opening:
            live = room.live
            if live is None or live.closed:
                continue
            try:
                scene = await ctx.render.open_scene(ctx, room, live.scene.kind)
                await asyncio.to_thread(ctx.registry.open, avatar_id)  # trackers: cheap now
            except Exception:  # noqa: BLE001 - the room goes on showing the old avatar
                log.exception("room %s: cannot reload avatar %s", room.id, avatar_id)
                continue
            if live.closed:  # emptied meanwhile (a plain session ended)
                scene.close()
                continue
            live.replace_scene(scene, partial(_new_tracker, ctx, avatar_id, seats), sh_degree)
            notice = message.model_copy(update={"seats": seats})
            for participant in live.participants:
                participant.send_control(notice)
            reloaded += 1
    log.info("avatar %s reloaded in %d live room(s)", avatar_id, reloaded)
    return reloaded


def _new_tracker(ctx: ServerContext, avatar_id: str, seats: list[int], participant):
    """A performer of a reloaded seat gets a tracker of the new avatar; others keep theirs."""
    if participant.role == "perform" and participant.seat_index in seats:
        return ctx.session_tracker(avatar_id)
    return None
