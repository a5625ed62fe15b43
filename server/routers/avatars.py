"""REST ``/v1/avatars``: list, get, upload (zip), download (zip), delete.

Reading needs the ``stream`` scope, uploading and deleting the ``train`` scope. A caller sees
its own avatars and the public ones (an admin sees all). Unknown ids are 404; an avatar that
exists but is another owner's is 403. Uploads are checked against the owner's quotas
(server/quotas.py: 429 past the avatar count, 413 past the stored bytes; admins exempt).
"""

from __future__ import annotations

import asyncio
import tempfile
from pathlib import Path
from typing import Any

from fastapi import APIRouter, HTTPException, Request, status
from fastapi.responses import FileResponse
from pydantic import BaseModel, Field
from starlette.background import BackgroundTask

from ..auth import Principal
from ..context import ServerContext
from ..dependencies import Context, StreamPrincipal, TrainPrincipal
from ..private import private_dir
from ..quotas import check_avatar_quota, storage_left
from ..registry import AvatarNotFound, AvatarRecord, PackageError, StorageQuotaExceeded
from ..uploads import receive_upload

router = APIRouter(prefix="/v1/avatars", tags=["avatars"])


class AvatarOut(BaseModel):
    id: str
    name: str
    owner: str
    num_gaussians: int
    sh_degree: int
    created: float = Field(description="Unix time it was added")
    size_bytes: int
    source: str = ""
    metadata: dict[str, Any] = Field(default_factory=dict)

    @classmethod
    def of(cls, rec: AvatarRecord) -> AvatarOut:
        return cls(**rec.to_dict())


class ErrorOut(BaseModel):
    detail: str


ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"model": ErrorOut, "description": "Missing or invalid token"},
    403: {"model": ErrorOut, "description": "Wrong scope, or another owner's avatar"},
}


def visible_avatar(ctx: ServerContext, principal: Principal, avatar_id: str) -> AvatarRecord:
    """The avatar if the caller may see it: 404 when unknown, 403 when another owner's."""
    try:
        rec = ctx.registry.get(avatar_id)
    except AvatarNotFound:
        raise HTTPException(404, f"no avatar {avatar_id!r}") from None
    if not principal.can_see(rec.owner):
        raise HTTPException(403, f"avatar {avatar_id!r} belongs to another owner")
    return rec


@router.get("", summary="List avatars", response_model=list[AvatarOut], responses=ERRORS)
def list_avatars(ctx: Context, principal: StreamPrincipal) -> list[AvatarOut]:
    """The caller's avatars and the public ones (every avatar for an admin)."""
    registry = ctx.registry
    recs = registry.list() if principal.is_admin else \
        registry.list(principal.subject, include_public=True)
    return [AvatarOut.of(r) for r in recs]


@router.get("/{avatar_id}", summary="Get one avatar", response_model=AvatarOut,
            responses={**ERRORS, 404: {"model": ErrorOut, "description": "No such avatar"}})
def get_avatar(avatar_id: str, ctx: Context, principal: StreamPrincipal) -> AvatarOut:
    return AvatarOut.of(visible_avatar(ctx, principal, avatar_id))


@router.post(
    "", summary="Upload an avatar package (zip)", status_code=status.HTTP_201_CREATED,
    response_model=AvatarOut,
    responses={**ERRORS, 400: {"model": ErrorOut, "description": "Malformed body"},
               413: {"model": ErrorOut, "description": "Larger than max_upload_bytes, past "
                                                        "an unpack limit or the storage quota"},
               422: {"model": ErrorOut, "description": "Not a valid avatar package (also a "
                                                        "damaged or truncated zip)"},
               429: {"model": ErrorOut, "description": "The owner has max_avatars_per_user"}},
    openapi_extra={"requestBody": {"required": True, "content": {
        "multipart/form-data": {"schema": {
            "type": "object", "required": ["file"],
            "properties": {"file": {"type": "string", "format": "binary"},
                           "name": {"type": "string", "maxLength": 200}}}},
        "application/zip": {"schema": {"type": "string", "format": "binary"}}}}})
async def upload_avatar(request: Request, ctx: Context, principal: TrainPrincipal,
                        name: str | None = None) -> AvatarOut:
    """A package zip (``avatar.json`` + ``gaussians.npz``), validated before anything is
    unpacked; the caller owns the new avatar. ``name`` (query or form field) overrides the
    package's name."""
    jobs = ctx.jobs
    exempt = principal.is_admin
    if not exempt:  # before the body is read
        await asyncio.to_thread(check_avatar_quota, principal.subject, 0, ctx.settings,
                                ctx.registry, jobs)
    upload = await receive_upload(request, ctx.settings.data_dir / "tmp",
                                  ctx.settings.max_upload_bytes)
    try:
        left = None if exempt else await asyncio.to_thread(
            storage_left, principal.subject, ctx.settings, ctx.registry, jobs)
        rec = await asyncio.to_thread(
            ctx.registry.add_package, upload.path, principal.subject,
            name or upload.name, source="upload", max_size_bytes=left)
    except StorageQuotaExceeded as exc:
        raise HTTPException(413, str(exc)) from None
    except PackageError as exc:
        raise HTTPException(422, f"not a valid avatar package: {exc}".replace(
            str(upload.path), "upload")) from None
    finally:
        upload.path.unlink(missing_ok=True)
    ctx.metrics.avatars.set(len(ctx.registry.list()))
    return AvatarOut.of(rec)


@router.get("/{avatar_id}/package", summary="Download an avatar package (zip)",
            response_class=FileResponse,
            responses={**ERRORS, 200: {"content": {"application/zip": {}}},
                       404: {"model": ErrorOut, "description": "No such avatar"}})
async def download_avatar(avatar_id: str, ctx: Context,
                          principal: StreamPrincipal) -> FileResponse:
    rec = visible_avatar(ctx, principal, avatar_id)
    tmp_dir = private_dir(ctx.settings.data_dir / "tmp")
    with tempfile.NamedTemporaryFile(dir=tmp_dir, suffix=".zip", delete=False) as fh:
        path = Path(fh.name)
    try:
        await asyncio.to_thread(ctx.registry.write_zip, rec.id, path)
    except (AvatarNotFound, OSError):
        path.unlink(missing_ok=True)
        raise HTTPException(404, f"no avatar {avatar_id!r}") from None
    return FileResponse(path, media_type="application/zip", filename=f"{rec.id}.zip",
                        background=BackgroundTask(path.unlink, missing_ok=True))


@router.delete("/{avatar_id}", summary="Delete an avatar", status_code=204,
               responses={**ERRORS, 404: {"model": ErrorOut, "description": "No such avatar"}})
def delete_avatar(avatar_id: str, ctx: Context, principal: TrainPrincipal) -> None:
    """Only its owner or an admin may delete an avatar (public ones: admins only)."""
    rec = visible_avatar(ctx, principal, avatar_id)
    if not principal.can_modify(rec.owner):
        raise HTTPException(403, f"only the owner or an admin may delete avatar {avatar_id!r}")
    try:
        ctx.registry.delete(avatar_id)
    except AvatarNotFound:
        raise HTTPException(404, f"no avatar {avatar_id!r}") from None
    ctx.metrics.avatars.set(len(ctx.registry.list()))
