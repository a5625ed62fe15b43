"""REST ``/v1/motions``: the built-in motion library (expressions, gestures, conversation) as
per-frame SMPL-X parameters, so that the browser page and other clients can play the clips.

Clips become parameters only through an avatar's body-model rig (its expression names,
gesture hand shapes and hand means), so ``GET /v1/motions/{name}`` samples the clip for one
avatar. ``betas`` are left out: a drive with them would replace the avatar's identity.
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, HTTPException, Query
from pydantic import BaseModel, Field

from avatar_core.motion.library import ALIASES, MOTIONS, motion

from ..dependencies import Context, StreamPrincipal
from .avatars import visible_avatar

router = APIRouter(prefix="/v1/motions", tags=["motions"])
MAX_FPS = 60.0


class MotionOut(BaseModel):
    name: str
    category: str
    duration: float = Field(description="seconds")


class MotionList(BaseModel):
    motions: list[MotionOut]


class MotionFrames(MotionOut):
    fps: float
    frames: list[dict[str, dict[str, list[Any]]]] = Field(
        description="per frame a drive body: {'smplx': {field: nested list}}")


@router.get("", summary="List the built-in motion clips", response_model=MotionList)
def list_motions(principal: StreamPrincipal) -> MotionList:
    return MotionList(motions=[MotionOut(name=n, category=s.category,
                                         duration=round(motion(n).duration, 3))
                               for n, s in MOTIONS.items()])


@router.get("/{name}", summary="A clip sampled for one avatar", response_model=MotionFrames,
            responses={404: {"description": "Unknown motion or avatar"},
                       422: {"description": "The avatar's body model lacks a name the clip "
                                            "uses (official models name no expressions)"},
                       403: {"description": "Another owner's avatar"}})
def get_motion(name: str, ctx: Context, principal: StreamPrincipal,
               avatar: str = Query(description="avatar id whose rig samples the clip"),
               fps: float = Query(30.0, gt=0, le=MAX_FPS)) -> MotionFrames:
    canonical = ALIASES.get(name, name)
    if canonical not in MOTIONS:
        raise HTTPException(404, f"unknown motion {name!r}; known: {sorted(MOTIONS)}")
    clip = motion(canonical)
    record = visible_avatar(ctx, principal, avatar)
    rig = ctx.rig(record.id)
    count = max(1, int(round(clip.duration * fps)) + 1)
    frames = []
    for i in range(count):
        try:
            params = clip.sample(min(i / fps, clip.duration), rig)
        except KeyError as exc:  # official model files name no expressions or gestures
            raise HTTPException(422, f"motion {canonical!r} names what this avatar's body "
                                     f"model does not: {exc.args[0]}") from None
        params.pop("betas", None)
        frames.append({"smplx": {k: v.tolist() for k, v in params.items()}})
    return MotionFrames(name=canonical, category=MOTIONS[canonical].category,
                        duration=clip.duration, fps=fps, frames=frames)
