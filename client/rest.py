"""A synchronous REST client (httpx) for avatars, rooms, jobs, motions and health.

    with RestClient("http://127.0.0.1:8000", token) as api:
        for avatar in api.avatars():
            print(avatar["id"])
        job = api.submit_job(dataset="synthetic-small", config={"iterations": 500})
        for event in api.job_events(job["id"]):
            print(event.event, event.data)

Errors come back as :class:`ApiError` with the HTTP status and the server's ``detail``.
"""

from __future__ import annotations

import io
import json
import mimetypes
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx


class ApiError(RuntimeError):
    def __init__(self, status: int, detail: Any, url: str = "") -> None:
        if isinstance(detail, dict) and {"reason", "message", "what_to_do"} <= set(detail):
            # a refused enrollment video: what is wrong and what to do, in words
            text = f"{detail['message']} {detail['what_to_do']} ({detail['reason']})"
        else:
            text = str(detail)
        super().__init__(f"HTTP {status} from {url}: {text}")
        self.status = status
        self.detail = detail


@dataclass(frozen=True)
class SseEvent:
    """One server-sent event; ``data`` is parsed as JSON when it is JSON."""

    event: str
    data: Any
    id: str | None = None


def parse_sse(lines: Iterator[str]) -> Iterator[SseEvent]:
    """Server-sent events from a stream of lines (the text/event-stream format)."""
    event, data, last_id = "message", [], None
    for line in lines:
        if line == "":  # a blank line ends an event
            if data:
                text = "\n".join(data)
                try:
                    value: Any = json.loads(text)
                except ValueError:
                    value = text
                yield SseEvent(event, value, last_id)
            event, data = "message", []
            continue
        if line.startswith(":"):  # comment / keep-alive
            continue
        field, _, value = line.partition(":")
        value = value.removeprefix(" ")
        if field == "event":
            event = value
        elif field == "data":
            data.append(value)
        elif field == "id":
            last_id = value
    if data:  # a stream that ends without the final blank line
        yield SseEvent(event, "\n".join(data), last_id)


def _items(body: Any, key: str) -> list[dict[str, Any]]:
    """A list answer, whether it comes bare or wrapped as {key: [...]}."""
    if isinstance(body, dict) and isinstance(body.get(key), list):
        return body[key]
    if isinstance(body, list):
        return body
    raise ApiError(200, f"unexpected answer: {str(body)[:200]}")


def zip_folder(folder: Path) -> bytes:
    """A folder's files as zip bytes (paths relative to the folder)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as zf:
        for path in sorted(folder.rglob("*")):
            if path.is_file():
                zf.write(path, path.relative_to(folder).as_posix())
    return buffer.getvalue()


class RestClient:
    def __init__(self, server: str, token: str | None = None, *, timeout: float = 60.0,
                 transport: httpx.BaseTransport | None = None) -> None:
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self._http = httpx.Client(base_url=server.rstrip("/"), headers=headers,
                                  timeout=timeout, transport=transport, trust_env=False)

    def __enter__(self) -> RestClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    # -- plumbing -------------------------------------------------------------------------

    def _check(self, response: httpx.Response) -> httpx.Response:
        if response.is_success:
            return response
        try:
            detail = response.json().get("detail", response.text)
        except ValueError:
            detail = response.text
        raise ApiError(response.status_code, detail, str(response.url))

    def _json(self, method: str, path: str, **kwargs: Any) -> Any:
        response = self._check(self._http.request(method, path, **kwargs))
        return response.json() if response.content else None

    def _download(self, path: str, out: Path) -> Path:
        """Stream a file to ``out`` (a folder: the server's file name is used)."""
        out = Path(out)
        with self._http.stream("GET", path) as response:
            self._check(response)
            if out.is_dir():
                name = _filename(response.headers.get("content-disposition", ""))
                out = out / (name or "download.zip")
            out.parent.mkdir(parents=True, exist_ok=True)
            with out.open("wb") as fh:
                for chunk in response.iter_bytes():
                    fh.write(chunk)
        return out

    # -- health ---------------------------------------------------------------------------

    def health(self) -> dict[str, Any]:
        return self._json("GET", "/v1/health")

    # -- avatars --------------------------------------------------------------------------

    def avatars(self) -> list[dict[str, Any]]:
        return _items(self._json("GET", "/v1/avatars"), "avatars")

    def avatar(self, avatar_id: str) -> dict[str, Any]:
        return self._json("GET", f"/v1/avatars/{avatar_id}")

    def upload_avatar(self, package: str | Path, *, name: str | None = None) -> dict[str, Any]:
        """Upload an avatar package (a .zip, or a folder zipped on the fly); the caller owns
        the new avatar, whose id the answer carries."""
        package = Path(package)
        data = zip_folder(package) if package.is_dir() else package.read_bytes()
        form = {"name": name} if name else {}
        files = {"file": (package.stem + ".zip", data, "application/zip")}
        return self._json("POST", "/v1/avatars", files=files, data=form)

    def download_avatar(self, avatar_id: str, out: str | Path) -> Path:
        return self._download(f"/v1/avatars/{avatar_id}/package", Path(out))

    def delete_avatar(self, avatar_id: str) -> None:
        self._json("DELETE", f"/v1/avatars/{avatar_id}")

    # -- motions --------------------------------------------------------------------------

    def motions(self) -> list[dict[str, Any]]:
        return _items(self._json("GET", "/v1/motions"), "motions")

    def motion(self, name: str, *, avatar: str | None = None,
               fps: float | None = None) -> dict[str, Any]:
        params = {k: v for k, v in (("avatar", avatar), ("fps", fps)) if v is not None}
        return self._json("GET", f"/v1/motions/{name}", params=params)

    # -- rooms --------------------------------------------------------------------------

    def create_room(self, seats: list[dict[str, Any]] | None = None, *,
                    name: str | None = None) -> dict[str, Any]:
        """A live room: ``seats`` is ``[{"avatar": ID, "placement"?: {"translation": [x, y, z],
        "rotation": [rx, ry, rz]}}]`` (default: one seat of the demo avatar)."""
        body = {k: v for k, v in (("name", name), ("seats", seats)) if v is not None}
        return self._json("POST", "/v1/rooms", json=body)

    def rooms(self) -> list[dict[str, Any]]:
        return _items(self._json("GET", "/v1/rooms"), "rooms")

    def room(self, room_id: str) -> dict[str, Any]:
        return self._json("GET", f"/v1/rooms/{room_id}")

    def delete_room(self, room_id: str) -> None:
        self._json("DELETE", f"/v1/rooms/{room_id}")

    def invite(self, room_id: str, scope: str, seat: int | None = None,
               ttl_s: float | None = None) -> dict[str, Any]:
        """An invitation token of ``scope`` "perform" (one seat) or "watch"; the answer is the
        only place its token is ever shown, with the page's relative ``link``."""
        body = {k: v for k, v in (("scope", scope), ("seat", seat), ("ttl_s", ttl_s))
                if v is not None}
        return self._json("POST", f"/v1/rooms/{room_id}/invitations", json=body)

    def invitations(self, room_id: str) -> list[dict[str, Any]]:
        return _items(self._json("GET", f"/v1/rooms/{room_id}/invitations"), "invitations")

    def revoke_invitation(self, room_id: str, invitation_id: str) -> None:
        self._json("DELETE", f"/v1/rooms/{room_id}/invitations/{invitation_id}")

    def link(self, relative: str) -> str:
        """An absolute page URL from a relative ``link`` the server answered."""
        return str(self._http.base_url.join(relative))

    # -- jobs -----------------------------------------------------------------------------

    def submit_job(self, *, dataset: str | None = None, archive: str | Path | None = None,
                   video: str | Path | None = None,
                   config: dict[str, Any] | str | None = None,
                   name: str | None = None) -> dict[str, Any]:
        """Submit a training job on a dataset the server has (by name) or an uploaded .zip,
        or an enrollment job on one uploaded ``video`` (preset "enroll").

        ``config`` is a training-config dict or a preset name ("quick", "default", "test");
        with a video, "enroll" or a dict of EnrollConfig fields.
        """
        if sum(x is not None for x in (dataset, archive, video)) != 1:
            raise ValueError("give exactly one of dataset, archive and video")
        if dataset is not None:
            body = {k: v for k, v in (("dataset", dataset), ("config", config), ("name", name))
                    if v is not None}
            return self._json("POST", "/v1/jobs", json=body)
        form = {k: v for k, v in (("config", json.dumps(config) if config is not None else None),
                                  ("name", name)) if v is not None}
        path = Path(archive if archive is not None else video)
        part, kind = ("archive", "application/zip") if archive is not None else \
            ("video", mimetypes.guess_type(path.name)[0] or "application/octet-stream")
        with path.open("rb") as fh:
            return self._json("POST", "/v1/jobs", data=form, files={part: (path.name, fh, kind)},
                              timeout=httpx.Timeout(60.0, write=None))

    def jobs(self) -> list[dict[str, Any]]:
        return _items(self._json("GET", "/v1/jobs"), "jobs")

    def job(self, job_id: str) -> dict[str, Any]:
        return self._json("GET", f"/v1/jobs/{job_id}")

    def job_events(self, job_id: str, *, after: int | None = None,
                   timeout: float | None = None) -> Iterator[SseEvent]:
        """The job's server-sent events (replayed after ``after``, then live) until the
        server ends the stream: an ``end`` event once the job has finished."""
        params = {"after": after} if after is not None else {}
        with self._http.stream("GET", f"/v1/jobs/{job_id}/events", params=params,
                               headers={"Accept": "text/event-stream"},
                               timeout=httpx.Timeout(60.0, read=timeout)) as response:
            self._check(response)
            yield from parse_sse(response.iter_lines())

    def job_logs(self, job_id: str, *, tail: int | None = None) -> str:
        params = {"tail": tail} if tail is not None else {}
        return self._check(self._http.get(f"/v1/jobs/{job_id}/logs", params=params)).text

    def cancel_job(self, job_id: str) -> dict[str, Any]:
        return self._json("POST", f"/v1/jobs/{job_id}/cancel")

    def job_result(self, job_id: str) -> dict[str, Any]:
        return self._json("GET", f"/v1/jobs/{job_id}/result")


def _filename(disposition: str) -> str | None:
    for part in disposition.split(";"):
        key, _, value = part.strip().partition("=")
        if key.lower() == "filename" and value:
            return Path(value.strip('"')).name or None
    return None
