"""REST over a real server: health, metrics, avatars (list, get, upload, download, delete),
auth refusals on HTTP and on the WebSocket, and the OpenAPI description."""

import asyncio
import io
import json
import zipfile

import httpx
import pytest
import websockets

from protocol import Hello, encode
from tests.server_fixtures import (
    is_type,
    recv_msg,
    recv_until,
    server_fixture,  # noqa: F401 (the `server` fixture)
    stream,
)


def _client(srv, token: str | None = None) -> httpx.Client:
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    return httpx.Client(base_url=srv.url, headers=headers, timeout=30)


@pytest.fixture(scope="module")
def demo_zip(server) -> bytes:
    with _client(server, server.token) as c:
        r = c.get("/v1/avatars/demo/package")
    assert r.status_code == 200 and r.headers["content-type"] == "application/zip"
    return r.content


def _rezip(src: bytes, rename: dict[str, str] | None = None,
           replace: dict[str, bytes] | None = None) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(src)) as zin, zipfile.ZipFile(out, "w") as zout:
        for info in zin.infolist():
            data = (replace or {}).get(info.filename, zin.read(info))
            zout.writestr((rename or {}).get(info.filename, info.filename), data)
    return out.getvalue()


def _stored(srv) -> tuple[set[str], list]:
    root = srv.settings.data_dir
    tmp = root / "tmp"
    return ({p.name for p in (root / "avatars").iterdir()},
            sorted(tmp.iterdir()) if tmp.exists() else [])


def test_health_metrics_and_openapi(server):
    with _client(server) as c:
        health = c.get("/v1/health").json()
        assert health["status"] == "ok" and health["max_sessions"] == 8
        metrics = c.get("/metrics")
        assert metrics.status_code == 200
        assert "telesplat_sessions" in metrics.text and "telesplat_stage_ms" in metrics.text
        spec = c.get("/openapi.json").json()
    for path in ("/v1/health", "/v1/avatars", "/v1/avatars/{avatar_id}",
                 "/v1/avatars/{avatar_id}/package"):
        assert path in spec["paths"]
    assert spec["paths"]["/v1/avatars"]["get"]["summary"] == "List avatars"
    for path in ("/v1/motions", "/v1/motions/{name}", "/v1/stream/tickets", "/v1/jobs",
                 "/v1/jobs/{job_id}/events"):
        assert path in spec["paths"]
    # dependencies (context, principal, job service) are never request parameters
    params = {p["name"] for ops in spec["paths"].values() for op in ops.values()
              for p in op.get("parameters", [])}
    assert not params & {"ctx", "conn", "request", "principal", "service"}, params


def test_the_app_carries_only_its_context(server):
    assert set(server.app.state._state) == {"ctx"}
    assert server.ctx.jobs is not None  # the job service, while the app runs


def test_rest_auth_refusals(server):
    stream_only = server.issue("alice", ("stream",))
    with _client(server) as c:
        assert c.get("/v1/avatars").status_code == 401
    with _client(server, "tsk_not-a-token") as c:
        r = c.get("/v1/avatars")
        assert r.status_code == 401 and "detail" in r.json()
    with _client(server, stream_only) as c:
        assert c.get("/v1/avatars").status_code == 200
        r = c.post("/v1/avatars", content=b"PK", headers={"content-type": "application/zip"})
        assert r.status_code == 403 and "train" in r.json()["detail"]


def test_upload_list_download_delete(server, demo_zip):
    bob = server.issue("bob", ("stream", "train"))
    carol = server.issue("carol", ("stream", "train"))
    with _client(server, bob) as c:
        r = c.post("/v1/avatars", files={"file": ("a.zip", demo_zip, "application/zip")},
                   data={"name": "bob's avatar"})
        assert r.status_code == 201, r.text
        rec = r.json()
        assert rec["owner"] == "bob" and rec["name"] == "bob's avatar"
        assert rec["num_gaussians"] > 0
        raw = c.post("/v1/avatars?name=raw", content=demo_zip,
                     headers={"content-type": "application/zip"})
        assert raw.status_code == 201 and raw.json()["name"] == "raw"
        ids = {a["id"] for a in c.get("/v1/avatars").json()}
        assert {rec["id"], raw.json()["id"], "demo"} <= ids
        back = c.get(f"/v1/avatars/{rec['id']}/package")
        assert back.status_code == 200
        with zipfile.ZipFile(io.BytesIO(back.content)) as z:
            assert sorted(z.namelist()) == ["avatar.json", "gaussians.npz"]
    with _client(server, carol) as c:
        ids = {a["id"] for a in c.get("/v1/avatars").json()}
        assert rec["id"] not in ids and "demo" in ids
        assert c.get(f"/v1/avatars/{rec['id']}").status_code == 403
        assert c.get(f"/v1/avatars/{rec['id']}/package").status_code == 403
        assert c.delete(f"/v1/avatars/{rec['id']}").status_code == 403
        assert c.delete("/v1/avatars/demo").status_code == 403  # public: admins only
        assert c.get("/v1/avatars/nope").status_code == 404
        assert c.delete("/v1/avatars/nope").status_code == 404
    with _client(server, server.token) as c:  # admin sees everything
        assert rec["id"] in {a["id"] for a in c.get("/v1/avatars").json()}
    with _client(server, bob) as c:
        assert c.delete(f"/v1/avatars/{rec['id']}").status_code == 204
        assert c.get(f"/v1/avatars/{rec['id']}").status_code == 404
        assert c.delete(f"/v1/avatars/{raw.json()['id']}").status_code == 204
    assert rec["id"] not in _stored(server)[0]


def test_bad_uploads_are_refused_and_leave_nothing(server, demo_zip, monkeypatch):
    manifest = json.loads(zipfile.ZipFile(io.BytesIO(demo_zip)).read("avatar.json"))
    bad = {
        "traversal": (_rezip(demo_zip, rename={"avatar.json": "../avatar.json"}), 422),
        "absolute": (_rezip(demo_zip, rename={"avatar.json": "/etc/avatar.json"}), 422),
        "schema": (_rezip(demo_zip, replace={"avatar.json": json.dumps(
            {**manifest, "schema_version": 99}).encode()}), 422),
        "no gaussians": (_rezip(demo_zip, rename={"gaussians.npz": "other.npz"}), 422),
        "not a zip": (b"this is not a zip file at all", 422),
        "empty": (b"", 400),
    }
    before = _stored(server)
    with _client(server, server.token) as c:
        for name, (body, code) in bad.items():
            r = c.post("/v1/avatars", content=body, headers={"content-type": "application/zip"})
            assert r.status_code == code, (name, r.text)
            assert "detail" in r.json()
        r = c.post("/v1/avatars", files={"other": ("a.zip", demo_zip)})
        assert r.status_code == 400
        monkeypatch.setattr(server.settings, "max_upload_bytes", 4096)
        r = c.post("/v1/avatars", files={"file": ("a.zip", demo_zip, "application/zip")})
        assert r.status_code == 413
        r = c.post("/v1/avatars", content=demo_zip, headers={
            "content-type": "application/zip"})
        assert r.status_code == 413

        def chunks():  # no Content-Length: the limit holds while the bytes arrive
            for i in range(0, len(demo_zip), 1000):
                yield demo_zip[i:i + 1000]
        r = c.post("/v1/avatars", content=chunks(), headers={"content-type": "application/zip"})
        assert r.status_code == 413
    assert _stored(server) == before


def test_websocket_auth_refusals(server, demo_zip):
    dave = server.issue("dave", ("stream", "train"))
    train_only = server.issue("erin", ("train",))
    with _client(server, dave) as c:
        private = c.post("/v1/avatars", content=demo_zip,
                         headers={"content-type": "application/zip"}).json()["id"]

    async def refused(token, avatar="demo", hello: bytes | None = None):
        async with stream(server, avatar=avatar, token=token, welcome=False) as ws:
            if hello is not None:
                await ws.send(hello)
            err = await recv_msg(ws)
            with pytest.raises(websockets.ConnectionClosed) as closed:
                await asyncio.wait_for(ws.recv(), 10)
            return err.code, closed.value.rcvd.code

    async def run():
        assert await refused("", hello=encode(Hello())) == ("unauthorized", 4401)
        assert await refused("tsk_bad") == ("unauthorized", 4401)
        assert await refused(train_only) == ("forbidden", 4403)
        assert await refused(server.issue("frank", ("stream",)), avatar=private) == \
            ("forbidden", 4403)
        assert await refused(server.token, avatar="missing") == ("not_found", 4404)
        assert await refused("", hello=encode(Hello(token=dave, version=99))) == \
            ("version", 4400)
        # The owner streams it; the token may also come in the hello message.
        async with stream(server, avatar=private, token="", welcome=False) as ws:
            await ws.send(encode(Hello(token=dave, client="test")))
            welcome = await recv_msg(ws)
            assert welcome.type == "welcome" and welcome.avatar.owner == "dave"
            await recv_until(ws, is_type("frame"))
        # ... or in an Authorization header.
        async with stream(server, token="", additional_headers={
                "Authorization": f"Bearer {dave}"}) as ws:
            await recv_until(ws, is_type("frame"))
    asyncio.run(run())
