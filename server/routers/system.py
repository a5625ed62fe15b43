"""``/v1/health`` (no auth) and ``/metrics`` (Prometheus text, no auth)."""

from __future__ import annotations

from fastapi import APIRouter, Response
from prometheus_client import CONTENT_TYPE_LATEST
from pydantic import BaseModel, Field

from protocol import PROTOCOL_VERSION

from ..dependencies import Context

router = APIRouter(tags=["system"])


class HealthOut(BaseModel):
    status: str
    protocol_version: int
    sessions: int
    max_sessions: int
    avatars: int
    render_queue: int
    webrtc: bool = Field(description="WHEP / WHIP endpoints open (webrtc_max_peers > 0)")
    webrtc_peers: int = Field(description="WebRTC peers now")


@router.get("/v1/health", summary="Liveness and load", response_model=HealthOut)
def health(ctx: Context) -> HealthOut:
    return HealthOut(status="ok", protocol_version=PROTOCOL_VERSION, sessions=ctx.slots.count,
                     max_sessions=ctx.slots.limit, avatars=len(ctx.registry.list()),
                     render_queue=ctx.scheduler.queued,
                     webrtc=ctx.settings.webrtc_max_peers > 0,
                     webrtc_peers=len(ctx.webrtc_peers))


@router.get("/metrics", summary="Prometheus metrics", response_class=Response,
            responses={200: {"content": {CONTENT_TYPE_LATEST: {}}}})
def metrics(ctx: Context) -> Response:
    ctx.metrics.sessions.set(ctx.slots.count)
    ctx.metrics.render_queue.set(ctx.scheduler.queued)
    ctx.render.observe(ctx.metrics)
    return Response(ctx.metrics.render_text(), media_type=CONTENT_TYPE_LATEST)
