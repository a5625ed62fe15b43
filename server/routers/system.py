"""``/v1/health``, ``/v1/demo`` (the trained demo's build) and ``/metrics`` (Prometheus text),
none with auth."""

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


class DemoBuildOut(BaseModel):
    state: str = Field(description="off (no trained demo configured), building, ready or "
                                   "failed")
    stage: str | None = Field(description="capture or train while building")
    progress: float = Field(description="the whole build's progress, in [0, 1]")
    stage_progress: float = Field(description="the stage's progress, in [0, 1]")
    job_id: str | None = Field(description="the training job (visible to admins)")
    error: str | None = Field(description="why it failed")
    trained: bool = Field(description="whether the avatar 'demo' is the trained one now")


@router.get("/v1/demo", summary="The trained demo avatar's background build (no auth)",
            response_model=DemoBuildOut)
def demo_build(ctx: Context) -> DemoBuildOut:
    return DemoBuildOut(**ctx.demo_build.status())


@router.get("/metrics", summary="Prometheus metrics", response_class=Response,
            responses={200: {"content": {CONTENT_TYPE_LATEST: {}}}})
def metrics(ctx: Context) -> Response:
    ctx.metrics.sessions.set(ctx.slots.count)
    ctx.metrics.render_queue.set(ctx.scheduler.queued)
    ctx.render.observe(ctx.metrics)
    return Response(ctx.metrics.render_text(), media_type=CONTENT_TYPE_LATEST)
