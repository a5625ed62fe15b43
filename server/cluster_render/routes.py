"""``GET /v1/cluster/render`` (admin): where frames are made. With render_backend ray: each
render worker (name, state, pid, host, frames, recent ms per frame, its scenes) and each scene
(a room or a plain session) with its worker; with local: the render threads."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter

from ..auth import Principal
from ..dependencies import Context, require_scope

router = APIRouter(tags=["cluster"])
AdminPrincipal = Annotated[Principal, require_scope("admin")]


@router.get("/v1/cluster/render", summary="Render placement (admin)")
def render_placement(ctx: Context, principal: AdminPrincipal) -> dict[str, Any]:
    return ctx.render.placement(ctx)
