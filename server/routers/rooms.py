"""REST ``/v1/rooms``: live scenes of one or more seats, and their invitations.

Every route needs a bearer token with the ``stream`` scope; a room is its owner's (an admin
sees and manages all). ``GET /v1/rooms/{id}`` also answers an invitation token of that room,
so an invited page can show the room. Invitation tokens (``tsr_...``) are shown once, at
creation; they join ``/v1/stream?room=ID`` with their scope. Rooms and invitations are stored
(server/rooms/store.py): a restart keeps them, and clients reconnect into the same room.
"""

from __future__ import annotations

import math
import time
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, HTTPException, Request, Response, status
from pydantic import BaseModel, ConfigDict, Field, field_validator

from ..auth import Principal, bearer_token
from ..context import ServerContext
from ..dependencies import Context, StreamPrincipal, get_context
from ..registry import DEMO_ID, AvatarNotFound
from ..rooms.registry import Invitation, Placement, Room, RoomError, SeatSpec, is_invitation
from .avatars import ErrorOut

router = APIRouter(prefix="/v1/rooms", tags=["rooms"])

Vec3 = tuple[float, float, float]
ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"model": ErrorOut, "description": "Missing or invalid token"},
    403: {"model": ErrorOut, "description": "Wrong scope, or another owner's room"},
    404: {"model": ErrorOut, "description": "No such room"},
}


class _In(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class PlacementIn(_In):
    translation: Vec3 = Field((0.0, 0.0, 0.0), description="metres, in the scene")
    rotation: Vec3 = Field((0.0, 0.0, 0.0), description="axis-angle, radians")

    @field_validator("translation")
    @classmethod
    def _near(cls, value: Vec3) -> Vec3:
        if math.hypot(*value) > 100.0:
            raise ValueError("a seat is placed within 100 m of the origin")
        return value

    @field_validator("rotation")
    @classmethod
    def _turn(cls, value: Vec3) -> Vec3:
        if math.hypot(*value) > 2 * math.pi:
            raise ValueError("a rotation is at most one turn (2 pi)")
        return value


class SeatIn(_In):
    avatar: str = Field(max_length=200)
    placement: PlacementIn = Field(default_factory=PlacementIn)


class RoomIn(_In):
    name: str | None = Field(None, max_length=200)
    seats: list[SeatIn] = Field(default_factory=lambda: [SeatIn(avatar=DEMO_ID)], min_length=1,
                                max_length=16)


class PlacementOut(BaseModel):
    translation: Vec3
    rotation: Vec3


class SeatOut(BaseModel):
    index: int
    avatar: str
    placement: PlacementOut
    performer: str | None = Field(None, description="client name of its performer")
    holding: bool = Field(False, description="performer gone: last pose held / easing to rest")


class RoomOut(BaseModel):
    id: str
    name: str
    owner: str
    seats: list[SeatOut]
    viewers: int
    created: float = Field(description="Unix time")
    idle_timeout_s: float | None = Field(description="None: never closed for idleness")

    @classmethod
    def of(cls, room: Room, ctx: ServerContext) -> RoomOut:
        live = room.live
        seats = []
        for i, spec in enumerate(room.seats):
            seat = None if live is None else live.seats[i]
            seats.append(SeatOut(
                index=spec.index, avatar=spec.avatar,
                placement=PlacementOut(translation=spec.placement.translation,
                                       rotation=spec.placement.rotation),
                performer=None if seat is None or seat.performer is None else seat.performer.name,
                holding=False if seat is None else seat.holding))
        viewers = 0 if live is None else sum(p.role == "watch" for p in live.participants)
        return cls(id=room.id, name=room.name, owner=room.owner, seats=seats, viewers=viewers,
                   created=room.created,
                   idle_timeout_s=None if room.pinned else ctx.settings.room_idle_timeout_s)


class RoomsOut(BaseModel):
    rooms: list[RoomOut]


class InvitationIn(_In):
    scope: Literal["perform", "watch"]
    seat: int | None = Field(None, ge=0, lt=16, description="perform only; default the lowest")
    ttl_s: float | None = Field(None, gt=0, description="default room_invitation_ttl_s, at most "
                                                        "room_invitation_max_ttl_s")


class InvitationOut(BaseModel):
    id: str
    token: str | None = Field(None, description="only in the answer that created it")
    scope: Literal["perform", "watch"]
    seat: int | None
    expires_at: float = Field(description="Unix time")
    revoked: bool = False
    link: str | None = Field(None, description="the page's link (relative), with the token")

    @classmethod
    def of(cls, inv: Invitation, token: str | None = None) -> InvitationOut:
        return cls(id=inv.id, token=token, scope=inv.scope, seat=inv.seat,
                   expires_at=inv.expires_at, revoked=inv.revoked,
                   link=None if token is None else f"/?room={inv.room_id}#token={token}")


class InvitationsOut(BaseModel):
    invitations: list[InvitationOut]


def _http(exc: RoomError) -> HTTPException:
    return HTTPException(exc.status, str(exc))


def _owned_room(ctx: ServerContext, principal: Principal, room_id: str) -> Room:
    try:
        room = ctx.rooms.get(room_id)
    except RoomError as exc:
        raise _http(exc) from None
    if not room.visible_to(principal):
        raise HTTPException(403, f"room {room_id!r} belongs to another owner")
    return room


def close_room(ctx: ServerContext, room: Room, why: str) -> None:
    """Out of the registry already: everyone in it is told and closed, and its scene goes
    once they have left (on the event loop)."""
    if room.live is not None:
        room.live.close(why)


def sweep_idle_rooms(ctx: ServerContext) -> int:
    """Close the rooms empty for room_idle_timeout_s; how many."""
    idle = ctx.rooms.idle_rooms(time.monotonic())
    for room in idle:
        close_room(ctx, room, "closed after being empty for room_idle_timeout_s")
    return len(idle)


@router.post("", status_code=201, summary="Create a room", responses={
    **ERRORS, 422: {"model": ErrorOut, "description": "Too many seats, an unknown avatar"},
    429: {"model": ErrorOut, "description": "max_rooms_per_user reached"}})
async def create_room(body: RoomIn, response: Response, ctx: Context,
                      principal: StreamPrincipal) -> RoomOut:
    """A room with one seat per entry of ``seats`` (default: the demo avatar at the origin);
    each seat's avatar must be visible to the caller."""
    sweep_idle_rooms(ctx)
    for seat in body.seats:
        try:
            record = ctx.registry.get(seat.avatar)
        except AvatarNotFound:
            raise HTTPException(422, f"no avatar {seat.avatar!r}") from None
        if not principal.can_see(record.owner):
            raise HTTPException(403, f"avatar {seat.avatar!r} belongs to another owner")
    seats = [SeatSpec(i, seat.avatar, Placement(tuple(seat.placement.translation),
                                                 tuple(seat.placement.rotation)))
             for i, seat in enumerate(body.seats)]
    try:
        room = ctx.rooms.create(principal, body.name, seats)
    except RoomError as exc:
        raise _http(exc) from None
    response.headers["Location"] = f"/v1/rooms/{room.id}"
    return RoomOut.of(room, ctx)


@router.get("", summary="List rooms", responses=ERRORS)
async def list_rooms(ctx: Context, principal: StreamPrincipal) -> RoomsOut:
    """The caller's rooms (an admin: all)."""
    sweep_idle_rooms(ctx)
    return RoomsOut(rooms=[RoomOut.of(r, ctx) for r in ctx.rooms.list(principal)])


def _reader(request: Request, room_id: str) -> Room:
    """The room, for its owner, an admin, or an invitation token of this room."""
    ctx = get_context(request)
    token = bearer_token(request.headers.get("authorization"))
    if is_invitation(token):
        inv = ctx.rooms.resolve(token)
        if inv is None:
            raise HTTPException(401, "invalid, expired or revoked invitation",
                                headers={"WWW-Authenticate": "Bearer"})
        if inv.room_id != room_id:
            raise HTTPException(403, "this invitation is for another room")
        try:
            return ctx.rooms.get(room_id)
        except RoomError as exc:
            raise _http(exc) from None
    principal = ctx.tokens.principal(token)
    if principal is None:
        raise HTTPException(401, "missing or invalid bearer token",
                            headers={"WWW-Authenticate": "Bearer"})
    if not principal.has("stream"):
        raise HTTPException(403, "this token lacks the 'stream' scope")
    return _owned_room(ctx, principal, room_id)


@router.get("/{room_id}", summary="Get a room", responses=ERRORS)
async def get_room(room: Annotated[Room, Depends(_reader)], ctx: Context) -> RoomOut:
    """A room with its seats' performers and its viewer count (owner, admin, or an invitation
    of this room)."""
    return RoomOut.of(room, ctx)


@router.delete("/{room_id}", status_code=204, summary="Delete a room", responses=ERRORS)
async def delete_room(room_id: str, ctx: Context, principal: StreamPrincipal) -> Response:
    """Closes the room: everyone in it gets error ``gone`` and close code 4410."""
    room = _owned_room(ctx, principal, room_id)
    ctx.rooms.remove(room.id)
    close_room(ctx, room, f"room {room.id!r} was deleted")
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.post("/{room_id}/invitations", status_code=201, summary="Invite to a room",
             responses={**ERRORS, 422: {"model": ErrorOut, "description": "Bad seat or ttl"},
                        429: {"model": ErrorOut,
                              "description": "max_invitations_per_room reached"}})
async def invite(room_id: str, body: InvitationIn, ctx: Context,
                 principal: StreamPrincipal) -> InvitationOut:
    """An invitation token with scope ``perform`` (one seat) or ``watch``; the token is in
    this answer only."""
    room = _owned_room(ctx, principal, room_id)
    try:
        inv, token = ctx.rooms.invite(room, body.scope, body.seat, body.ttl_s)
    except RoomError as exc:
        raise _http(exc) from None
    return InvitationOut.of(inv, token)


@router.get("/{room_id}/invitations", summary="List a room's invitations", responses=ERRORS)
async def invitations(room_id: str, ctx: Context, principal: StreamPrincipal) -> InvitationsOut:
    room = _owned_room(ctx, principal, room_id)
    return InvitationsOut(invitations=[InvitationOut.of(i) for i in room.invitations.values()])


@router.delete("/{room_id}/invitations/{invitation_id}", status_code=204,
               summary="Revoke an invitation", responses=ERRORS)
async def revoke(room_id: str, invitation_id: str, ctx: Context,
                 principal: StreamPrincipal) -> Response:
    """It admits nobody from now on; participants already in stay."""
    room = _owned_room(ctx, principal, room_id)
    try:
        ctx.rooms.revoke(room, invitation_id)
    except RoomError as exc:
        raise _http(exc) from None
    return Response(status_code=status.HTTP_204_NO_CONTENT)
