"""`make run`'s first start: the server is up at once with the untrained demo standing in, the
trained demo is built behind it (capture process, then a job of the server's own job service),
its progress is visible over the API and on the page, and `demo` becomes the trained one.

A real uvicorn (tests/server_fixtures.py) with the build configured to a tiny recipe (one
motion, 48 px, 2 frames, the test preset for 12 iterations) in the test's own demo cache; the
page in headless Chromium when it is installed. The capture is held at a gate (bounded) until
the page has shown the banner, so that a fast machine cannot finish the build unseen."""

from __future__ import annotations

import asyncio
import contextlib
import json
import threading
import time
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest

import server.jobs.demo_build as demo_build
from protocol import Frame, Hello, Orbit, View, encode
from server.registry import AvatarRegistry
from tests.server_fixtures import is_type, recv_until, run_server, stream, ws_connect
from tests.test_client_units import chromium_missing, make_chromium, node, run_node

TINY = {"motions": "smile", "resolution": 48, "frames": 2, "preset": "test", "iterations": 12}
BUILD_TIMEOUT_S = 600.0  # capture + a training process on a busy 2-core machine
GATE_TIMEOUT_S = 120.0


def _poll(predicate, timeout: float, what: str, interval: float = 0.2):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


def _page_probe(driver) -> dict:
    return driver.execute_script("""
        const b = document.getElementById("demo-build");
        const w = window.telesplat.session?.welcome?.avatar;
        return {hidden: b.hidden, text: b.textContent, frames: window.telesplat.framesShown,
                build: window.telesplat.demoBuild?.state ?? null,
                trained: w ? w.metadata?.trained ?? null : null};""")


NUDGE = View(orbit=Orbit(yaw_deg=20.0))  # a new view: renders once more, from the new scene
QUIET_S = 1.5  # no frame for this long: the last one shows the newest state


async def _settled_frame(ws, timeout: float = 60.0) -> np.ndarray:
    """After sending NUDGE: the frames until none comes for QUIET_S (bounded), the last one
    decoded."""
    await ws.send(encode(NUDGE))
    last, deadline = None, time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            msg = await recv_until(ws, is_type("frame"), timeout=QUIET_S if last else 30.0)
        except TimeoutError:
            break
        last = msg
    assert last is not None, "no frame after the new view"
    return cv2.imdecode(np.frombuffer(last.data, np.uint8), cv2.IMREAD_COLOR).astype(np.float32)


class KeptConnections:
    """The start-up room's performer and viewer and a plain session, connected while the
    stand-in shows and kept open across the swap (an event loop of their own, in a thread)."""

    def __init__(self, srv) -> None:
        self.srv = srv
        self.connected = threading.Event()
        self.result: dict = {}
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, daemon=True, name="kept-sessions")

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # reported by the test
            self.error = exc
            self.connected.set()

    async def _main(self) -> None:
        links = self.srv.ctx.startup_links
        room_url = self.srv.url.replace("http://", "ws://") + f"/v1/stream?room={links['room']}"
        tokens = {scope: links[scope].split("#token=")[1] for scope in ("perform", "watch")}
        async with contextlib.AsyncExitStack() as stack:
            sockets = {}
            for scope in ("perform", "watch"):
                ws = await stack.enter_async_context(ws_connect(room_url, open_timeout=30))
                await ws.send(encode(Hello(token=tokens[scope], role=scope)))
                ws.welcome = await recv_until(ws, is_type("welcome"), timeout=60)
                sockets[scope] = ws
            sockets["plain"] = await stack.enter_async_context(stream(self.srv, avatar="demo"))
            before = {name: await _settled_frame(ws) for name, ws in sockets.items()}
            self.result["welcomes"] = {n: ws.welcome for n, ws in sockets.items()}
            self.connected.set()
            # read on meanwhile (stats): a client that stops reading loses control messages
            told = await asyncio.gather(*(recv_until(ws, is_type("avatar"),
                                                     timeout=BUILD_TIMEOUT_S)
                                          for ws in sockets.values()))
            replaced = dict(zip(sockets, told, strict=True))
            after = {name: await _settled_frame(ws) for name, ws in sockets.items()}
            async with stream(self.srv, avatar="demo") as newcomer:  # a new plain session
                assert newcomer.welcome.avatar.metadata["trained"] is True
                fresh = await _settled_frame(newcomer)
            self.result.update(before=before, replaced=replaced, after=after, fresh=fresh)


def test_first_run_serves_at_once_and_swaps_in_the_trained_demo(tmp_path, monkeypatch):
    gate = threading.Event()
    real_capture = demo_build.DemoBuild._capture

    def gated_capture(self, command, root):
        gate.wait(GATE_TIMEOUT_S)  # bounded: a missing browser never holds the build long
        return real_capture(self, command, root)

    monkeypatch.setattr(demo_build.DemoBuild, "_capture", gated_capture)
    cache = tmp_path / "demo-cache"
    browser = chromium_missing() is None
    if not browser:
        gate.set()
    with run_server(tmp_path / "data", demo_avatar="trained", demo_cache_dir=cache,
                    demo_build_recipe=TINY, job_nice=0) as srv:  # (not starved by others)
        auth = {"Authorization": f"Bearer {srv.token}"}
        with httpx.Client(base_url=srv.url, timeout=30, headers=auth) as client:
            # up at once: health, the stand-in demo, and a frame of it
            assert client.get("/v1/health").json()["status"] == "ok"
            demo = client.get("/v1/avatars/demo").json()
            assert demo["metadata"]["trained"] is False and demo["metadata"]["stand_in"]
            status = httpx.get(f"{srv.url}/v1/demo", timeout=30).json()  # no auth needed
            assert status["state"] == "building" and status["trained"] is False

            async def one_frame():
                async with stream(srv, avatar="demo") as ws:
                    assert ws.welcome.avatar.metadata["trained"] is False
                    return await recv_until(ws, is_type("frame"), timeout=60)

            assert isinstance(asyncio.run(one_frame()), Frame)
            kept = KeptConnections(srv)
            kept.thread.start()
            assert kept.connected.wait(GATE_TIMEOUT_S) and kept.error is None, kept.error
            assert all(w.avatar.metadata["trained"] is False
                       for w in kept.result["welcomes"].values())

            driver = make_chromium() if browser else None
            try:
                if driver is not None:
                    driver.get(f"{srv.url}/?transport=ws#token={srv.token}")
                    shown = _poll(lambda: (p := _page_probe(driver))["text"] and not p["hidden"]
                                  and p["frames"] > 0 and p, 60,
                                  "the page to show the build banner and frames")
                    assert shown["text"].startswith("building the trained demo avatar: ")
                    assert "%" in shown["text"] and shown["trained"] is False
                    gate.set()

                # the build's progress over the API, until it is done
                seen: list[dict] = []

                def ready():
                    s = client.get("/v1/demo").json()
                    seen.append(s)
                    assert s["state"] in ("building", "ready"), s
                    return s["state"] == "ready"

                _poll(ready, BUILD_TIMEOUT_S, "the trained demo to be built", interval=0.5)
                stages = {s["stage"] for s in seen if s["state"] == "building"}
                assert "train" in stages
                progress = [s["progress"] for s in seen]
                assert progress == sorted(progress) and progress[-1] == 1.0
                job_id = seen[-1]["job_id"]
                job = client.get(f"/v1/jobs/{job_id}").json()
                assert job["state"] == "succeeded" and job["dataset"] == "demo:trained"
                assert job["avatar_id"] == "demo" and job["iteration"] == 12
                # its progress events (the job is done: the stream replays them and ends)
                events = client.get(f"/v1/jobs/{job_id}/events", timeout=httpx.Timeout(
                    30.0, read=120.0))
                data = [json.loads(line[6:]) for line in events.text.splitlines()
                        if line.startswith("data: ")]
                assert events.status_code == 200
                assert any(e.get("iteration") == 12 for e in data), data[-3:]

                # `demo` is the trained one now
                demo = client.get("/v1/avatars/demo").json()
                assert demo["metadata"]["trained"] is True
                assert demo["source"] == "demo:trained" and demo["metadata"]["job_id"] == job_id
                assert (cache / "avatar" / "avatar.json").is_file()  # cached for later starts

                async def trained_frame():
                    async with stream(srv, avatar="demo") as ws:
                        assert ws.welcome.avatar.metadata["trained"] is True
                        return await recv_until(ws, is_type("frame"), timeout=60)

                assert isinstance(asyncio.run(trained_frame()), Frame)

                # the room's performer and viewer and the plain session, still on their first
                # connections: told, then shown the trained avatar, as a newcomer sees it
                kept.thread.join(120)
                assert not kept.thread.is_alive() and kept.error is None, kept.error
                got = kept.result
                for name, msg in got["replaced"].items():
                    assert msg.avatar.id == "demo" and msg.avatar.metadata["trained"], name
                    assert msg.seats == [0]
                    shown = np.abs(got["after"][name] - got["fresh"]).mean()
                    changed = np.abs(got["after"][name] - got["before"][name]).mean()
                    assert shown < 1.0 and changed > 5 * max(shown, 0.2), (name, shown, changed)

                if driver is not None:  # the banner goes, the page switches to the trained one
                    _poll(lambda: (p := _page_probe(driver))["hidden"] and p["trained"] is True,
                          60, "the page to switch to the trained demo")
            finally:
                if driver is not None:
                    driver.quit()

    # a later start finds it in the cache: trained at once, nothing to build
    registry = AvatarRegistry(tmp_path / "again")
    record = registry.register_demo("trained", cache=cache, recipe=TINY)
    assert record.metadata["trained"] is True and record.source == "demo:trained"


def test_an_unknown_recipe_key_is_refused():
    from avatar_core.studio_entry import demo_build_plan

    with pytest.raises(ValueError, match="unknown demo recipe key"):
        demo_build_plan(None, {"iterationz": 3})


@pytest.mark.skipif(node() is None, reason="node is not installed")
def test_the_banner_and_its_bounded_poll_in_node():
    """client/web/demo_build.js: the banner's text per status, and the poll: it shows every
    status, calls onReady once after having seen the build run, stops when it ends, and gives
    up after maxPolls."""
    module = (Path(__file__).resolve().parent.parent / "client" / "web" / "demo_build.js")
    out = run_node(f"""
        import {{ demoBanner, watchDemoBuild }} from {json.dumps(module.as_uri())};
        const texts = [
          demoBanner({{state: "building", stage: "capture", progress: 0.05}}),
          demoBanner({{state: "building", stage: "train", progress: 0.372}}),
          demoBanner({{state: "failed", error: "boom"}}),
          demoBanner({{state: "ready"}}), demoBanner({{state: "off"}}), demoBanner(null)];
        const seq = [null, {{state: "building", progress: 0.1}}, {{state: "ready"}}];
        const shown = [], ready = [];
        const last = await watchDemoBuild({{
          fetchStatus: async () => {{
            const s = seq.shift();
            if (s === null) throw new Error("down");
            return s;
          }},
          show: (s) => shown.push(s?.state ?? null), onReady: (s) => ready.push(s.state),
          sleep: async () => {{}} }});
        let polls = 0;
        const capped = await watchDemoBuild({{
          fetchStatus: async () => {{ polls += 1; return {{state: "building", progress: 0}}; }},
          show: () => {{}}, maxPolls: 5, sleep: async () => {{}} }});
        const quiet = [];
        await watchDemoBuild({{ fetchStatus: async () => ({{state: "ready"}}), show: () => {{}},
          onReady: () => quiet.push(1), sleep: async () => {{}} }});
        console.log(JSON.stringify({{texts, shown, ready, last, polls, capped, quiet}}));
    """)
    got = json.loads(out)
    assert got["texts"] == [
        "building the trained demo avatar: 5% (filming); the untrained one stands in",
        "building the trained demo avatar: 37% (training); the untrained one stands in",
        "the trained demo avatar could not be built: boom", None, None, None]
    assert got["shown"] == [None, "building", "ready"] and got["ready"] == ["ready"]
    assert got["last"] == {"state": "ready"}
    assert got["polls"] == 5 and got["capped"]["state"] == "building"
    assert got["quiet"] == []  # ready from the start (cached): no switch
