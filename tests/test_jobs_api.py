"""The /v1/jobs REST API on a real server (uvicorn on 127.0.0.1): an uploaded dataset trains,
its events stream as SSE, the avatar is registered for its owner and streams over the
WebSocket; bad uploads and configs are refused and write nothing; tokens and owners are
enforced."""

import asyncio
import dataclasses
import io
import json
import shutil
import stat
import zipfile

import httpx
import pytest

from protocol import Frame
from server.jobs.archive import UploadLimits

from . import test_jobs_support as support
from .dataset_fixtures import write_tiny_dataset
from .server_fixtures import is_type, recv_until, run_server, stream
from .test_jobs_support import (
    FAST,
    LONG,
    wait_for,
    zip_dataset,
)

capture_dir = support.capture_dir  # the shared session fixture


TIMEOUT = httpx.Timeout(30.0)


@pytest.fixture(scope="module")
def srv(tmp_path_factory, capture_dir):
    with run_server(tmp_path_factory.mktemp("jobs-api")) as server:
        jobs = server.app.state.ctx.jobs
        # full speed in tests (the default lowers the training process's priority)
        jobs.worker.config = dataclasses.replace(jobs.worker.config, nice=0, poll_s=0.05)
        shutil.copytree(capture_dir, jobs.datasets_dir / "take")
        server.alice = server.issue("alice", ("train", "stream"))
        server.bob = server.issue("bob", ("train",))
        server.viewer = server.issue("carol", ("stream",))
        yield server


def _client(srv, token=None) -> httpx.Client:
    headers = {} if token is None else {"Authorization": f"Bearer {token}"}
    return httpx.Client(base_url=srv.url, headers=headers, timeout=TIMEOUT)


def _upload(client, data: bytes, config=None, name=None) -> httpx.Response:
    form = {k: v for k, v in (("config", None if config is None else json.dumps(config)),
                              ("name", name)) if v is not None}
    return client.post("/v1/jobs", data=form,
                       files={"archive": ("take.zip", data, "application/zip")})


def _sse(client, job_id, **kw) -> list[dict]:
    """Every SSE event of a job until the stream ends: [{id, event, data}]."""
    events, current = [], {}
    with client.stream("GET", f"/v1/jobs/{job_id}/events", timeout=httpx.Timeout(
            30.0, read=120.0), **kw) as r:
        assert r.status_code == 200 and r.headers["content-type"].startswith(
            "text/event-stream")
        for line in r.iter_lines():
            if not line:
                if current:
                    events.append(current)
                current = {}
            elif not line.startswith(":"):
                key, _, value = line.partition(": ")
                current[key] = json.loads(value) if key == "data" else value
    return events


def _job_area(srv) -> set[str]:
    return {p.name for p in srv.app.state.ctx.jobs.jobs_dir.iterdir()}


def test_an_uploaded_dataset_trains_and_its_avatar_streams(srv, capture_dir):
    alice = _client(srv, srv.alice)
    r = _upload(alice, zip_dataset(capture_dir), FAST, name="Alice")
    assert r.status_code == 201, r.text
    job = r.json()
    assert r.headers["location"] == f"/v1/jobs/{job['id']}"
    assert (job["owner"], job["state"], job["dataset"], job["total"]) == (
        "alice", "queued", "upload", 20)

    # a second job waits in the queue: cancelling it is immediate
    queued = alice.post("/v1/jobs", json={"dataset": "take", "config": FAST}).json()
    r = alice.post(f"/v1/jobs/{queued['id']}/cancel")
    assert r.status_code == 202 and r.json()["state"] == "cancelled"
    assert alice.post(f"/v1/jobs/{queued['id']}/cancel").status_code == 409
    assert alice.get(f"/v1/jobs/{queued['id']}/result").status_code == 409

    events = _sse(alice, job["id"])
    end = events[-1]
    assert end["event"] == "end" and "id" not in end
    assert end["data"]["state"] == "succeeded", alice.get(f"/v1/jobs/{job['id']}/logs").text
    ids = [int(e["id"]) for e in events[:-1]]
    assert ids == list(range(1, len(ids) + 1))
    kinds = [e["event"] for e in events]
    assert kinds.count("progress") == 4 and "checkpoint" in kinds and "done" in kinds
    states = [e["data"]["state"] for e in events if e["event"] == "state"]
    assert states == ["queued", "running", "succeeded"]
    assert all("path" not in e["data"] for e in events)  # no server paths leak

    status = alice.get(f"/v1/jobs/{job['id']}").json()
    assert status["state"] == "succeeded" and status["progress"] == 1.0
    assert status["iteration"] == 20 and status["loss"] is not None
    result = alice.get(f"/v1/jobs/{job['id']}/result").json()
    avatar_id = result["avatar_id"]
    assert avatar_id == status["avatar_id"] == end["data"]["avatar_id"]
    record = srv.app.state.ctx.registry.get(avatar_id)
    assert (record.owner, record.name, record.source) == ("alice", "Alice", f"job:{job['id']}")
    folder = srv.app.state.ctx.jobs.worker.job_dir(job["id"])  # the upload and checkpoints freed
    assert not (folder / "dataset").exists() and not (folder / "out" / "checkpoints").exists()

    # replay: after a seq, or from Last-Event-ID
    later = _sse(alice, job["id"], params={"after": ids[-3]})
    assert [e.get("id") for e in later] == [str(i) for i in ids[-2:]] + [None]
    again = _sse(alice, job["id"], headers={"Last-Event-ID": str(ids[-2])})
    assert [e.get("id") for e in again] == [str(ids[-1]), None]

    log = alice.get(f"/v1/jobs/{job['id']}/logs", params={"tail": 3})
    assert log.status_code == 200 and len(log.text.splitlines()) == 3
    full = alice.get(f"/v1/jobs/{job['id']}/logs").text
    assert "attempt 1" in full and "trained" in full

    async def one_frame():
        async with stream(srv, avatar=avatar_id, token=srv.alice) as ws:
            assert ws.welcome.avatar.id == avatar_id
            return await recv_until(ws, is_type("frame"), timeout=60)

    frame = asyncio.run(one_frame())
    assert isinstance(frame, Frame)


def _zip(members) -> bytes:
    """A zip of (ZipInfo or name, bytes) pairs."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for info, data in members:
            z.writestr(info, data)
    return buf.getvalue()


def _symlink() -> zipfile.ZipInfo:
    info = zipfile.ZipInfo("take/link")
    info.external_attr = (stat.S_IFLNK | 0o777) << 16
    return info


def _bad_schema(capture_dir) -> bytes:
    buf = io.BytesIO(zip_dataset(capture_dir))
    out = io.BytesIO()
    with zipfile.ZipFile(buf) as src, zipfile.ZipFile(out, "w") as dst:
        for info in src.infolist():
            data = src.read(info)
            if info.filename.endswith("dataset.json"):
                meta = json.loads(data)
                meta["format_version"] = 99
                del meta["fps"]
                data = json.dumps(meta).encode()
            dst.writestr(info, data)
    return out.getvalue()


@pytest.mark.parametrize("case, status, words", [
    ("too_large", 413, "larger than"),
    ("traversal", 400, "'..'"),
    ("absolute", 400, "absolute"),
    ("symlink", 400, "symlink"),
    ("not_a_zip", 400, "not a readable zip"),
    ("no_dataset", 400, "no dataset.json"),
    ("bad_schema", 400, "not valid"),
    ("unpacks_too_large", 413, "unpacks to more"),
    ("foreign_body_model", 400, "no body-model folder"),
])
def test_bad_uploads_are_refused_and_write_nothing(srv, capture_dir, tmp_path, case, status,
                                                   words):
    jobs = srv.app.state.ctx.jobs
    alice = _client(srv, srv.alice)
    data = {
        "too_large": lambda: zip_dataset(capture_dir),
        "traversal": lambda: _zip([("take/dataset.json", b"{}"), ("take/../../evil", b"x")]),
        "absolute": lambda: _zip([("/etc/evil", b"x")]),
        "symlink": lambda: _zip([("take/dataset.json", b"{}"), (_symlink(), b"/etc/passwd")]),
        "not_a_zip": lambda: b"PK\x03\x04 not really a zip" * 10,
        "no_dataset": lambda: _zip([("take/readme.txt", b"hello")]),
        "bad_schema": lambda: _bad_schema(capture_dir),
        "unpacks_too_large": lambda: _zip([("take/dataset.json", b"{}"),
                                           ("take/big", b"\0" * 200_000)]),
        # valid, but its parameters need a licensed body model the server does not have
        "foreign_body_model": lambda: zip_dataset(write_tiny_dataset(tmp_path / "t").root),
    }[case]()
    before_jobs, before_area = len(jobs.store.list(limit=1000)), _job_area(srv)
    limits = jobs.limits
    if case == "too_large":
        jobs.limits = UploadLimits(max_upload_bytes=len(data) // 2)
    if case == "unpacks_too_large":
        jobs.limits = UploadLimits(max_unpacked_bytes=100_000)
    try:
        r = _upload(alice, data, FAST)
    finally:
        jobs.limits = limits
    assert r.status_code == status, r.text
    assert words in r.json()["detail"]
    assert len(jobs.store.list(limit=1000)) == before_jobs
    assert _job_area(srv) == before_area  # no job folder, no scratch left


@pytest.mark.parametrize("config, key", [
    ({"preset": "test", "densify": {"intervall": 3}}, "densify.intervall"),
    ({"iterations": 0}, "iterations"),
    ("fastest", "unknown preset"),
    (["test"], "config"),
])
def test_bad_configs_are_422_naming_the_key(srv, capture_dir, config, key):
    alice = _client(srv, srv.alice)
    r = alice.post("/v1/jobs", json={"dataset": "take", "config": config})
    assert r.status_code == 422 and key in str(r.json()["detail"]), r.text
    if isinstance(config, dict):
        r = _upload(alice, zip_dataset(capture_dir), config)
        assert r.status_code == 422 and key in r.json()["detail"], r.text


def test_named_datasets_and_content_types(srv):
    alice = _client(srv, srv.alice)
    assert alice.post("/v1/jobs", json={"dataset": "../take"}).status_code == 400
    assert alice.post("/v1/jobs", json={"dataset": "nope"}).status_code == 404
    assert alice.post("/v1/jobs", json={"dataset": "take", "extra": 1}).status_code == 422
    assert alice.post("/v1/jobs", content=b"x", headers={
        "content-type": "text/plain"}).status_code == 415


def test_tokens_scopes_and_owners(srv):
    anonymous, viewer = _client(srv), _client(srv, srv.viewer)
    alice, bob, admin = _client(srv, srv.alice), _client(srv, srv.bob), _client(srv, srv.token)
    assert anonymous.get("/v1/jobs").status_code == 401
    assert anonymous.post("/v1/jobs", json={"dataset": "take"}).status_code == 401
    assert viewer.post("/v1/jobs", json={"dataset": "take"}).status_code == 403
    assert viewer.get("/v1/jobs").status_code == 403

    job = alice.post("/v1/jobs", json={"dataset": "take", "config": LONG}).json()
    try:
        for path in ("", "/events", "/logs", "/result"):
            assert bob.get(f"/v1/jobs/{job['id']}{path}").status_code == 404, path
        assert bob.post(f"/v1/jobs/{job['id']}/cancel").status_code == 404
        assert bob.post(f"/v1/jobs/{job['id']}/resume").status_code == 404
        assert bob.delete(f"/v1/jobs/{job['id']}").status_code == 404
        assert viewer.delete(f"/v1/jobs/{job['id']}").status_code == 403
        assert bob.get("/v1/jobs/does-not-exist").status_code == 404
        assert job["id"] not in [j["id"] for j in bob.get("/v1/jobs").json()["jobs"]]
        assert job["id"] in [j["id"] for j in alice.get("/v1/jobs").json()["jobs"]]
        everyone = admin.get("/v1/jobs", params={"limit": 1000}).json()["jobs"]
        assert job["id"] in [j["id"] for j in everyone]
        assert admin.get(f"/v1/jobs/{job['id']}").json()["owner"] == "alice"
    finally:
        assert admin.post(f"/v1/jobs/{job['id']}/cancel").status_code == 202
    wait_for(lambda: alice.get(f"/v1/jobs/{job['id']}").json()["state"] == "cancelled", 30,
             what="the cancel")


def test_openapi_documents_the_routes(srv):
    spec = httpx.get(f"{srv.url}/openapi.json", timeout=TIMEOUT).json()
    paths = spec["paths"]
    assert {"/v1/jobs", "/v1/jobs/{job_id}", "/v1/jobs/{job_id}/events",
            "/v1/jobs/{job_id}/logs", "/v1/jobs/{job_id}/cancel",
            "/v1/jobs/{job_id}/result", "/v1/jobs/{job_id}/resume"} <= set(paths)
    assert "delete" in paths["/v1/jobs/{job_id}"]
    submit = paths["/v1/jobs"]["post"]
    assert {"application/json", "multipart/form-data"} <= set(submit["requestBody"]["content"])
    assert submit["responses"]["201"]["content"]["application/json"]["schema"]["$ref"].endswith(
        "/JobOut")
    assert "404" in paths["/v1/jobs/{job_id}"]["get"]["responses"]
    assert "429" in submit["responses"]
    job = spec["components"]["schemas"]["JobOut"]["properties"]
    assert {"attempts", "max_attempts", "attempt_log"} <= set(job)
