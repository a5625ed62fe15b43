"""Soak: well-behaved sessions beside hostile clients, against a real server on loopback.

Starts ``python -m server`` on a free port (fresh data dir, the demo avatar of ``--avatar``),
issues a second token for a hostile user, then runs two phases side by side in one run:

1. **undisturbed**: ``--good`` well-behaved sessions drive at 30 Hz for ``--baseline`` seconds;
2. **soak**: the same sessions for ``--seconds`` beside ``--hostile`` hostile clients, each
   cycling through one class of the review's attacks:

   - ``preauth``: connections that never authenticate (silent, or a 7.6 MiB first message
     without a token), many at a time;
   - ``garbage``: an authenticated session sending absurd drives (1e300 betas, 1e38 eye
     poses, NaN), malformed msgpack, oversize arrays and a 0.001 fps request, fast;
   - ``expensive``: an authenticated session asking the largest frames allowed (PNG with
     alpha and depth) as fast as it can;
   - ``uploads``: REST abuse: npz decompression bombs, absurd avatars (log-scales 80),
     truncated zips, job archives with zip bombs, and a slow reader that never reads frames;

   and, from the second review (issue 25), with ``--hostile`` up to 9:

   - ``roomburst``: garbage-credential bursts on the room path (16 at a time, each a garbage
     ``Authorization`` header and a 7.9 MiB hello);
   - ``bomb``: in-range render bombs (the demo avatar with every log-scale 6, 400 m splats)
     uploaded, and, where one gets in, streamed at the largest size;
   - ``whep``: WHEP offers that never complete (answered, then never connected);
   - ``dcflood``: a WHEP peer flooding its data channel (tests/webrtc_flooder.py in its own
     process: 20k pings, then one 16 MiB message);
   - ``fuzz``: a performer in a room of its own sending fuzzed messages (valid drives with
     bytes flipped, random msgpack, truncations), fast.

It reports the server's memory (RSS from /proc, sampled every second) at the start of the
soak, after its warm-up minute and at the end (target: growth after the warm-up <= 5%), the
well-behaved sessions' fps in the soak against the undisturbed phase (target >= 80%), errors
the well-behaved sessions saw (target: none), server 5xx answers (target: none) and the
hostile clients' refusals by code (expected).

    .venv/bin/python bench/soak.py [--seconds 300] [--baseline 30] [--good 4] [--hostile 4]
                                   [--size 256] [--fps 10] [--avatar synthetic] [--warmup 60]

It also samples ``GET /v1/health`` every second during the soak (target p95 <= 100 ms).
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import io
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import msgpack
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

sys.path.insert(0, str(ROOT / "bench"))

from stream import start_server, stop_server  # noqa: E402

from client import StreamClient  # noqa: E402
from client.stream import StreamError, stream_url  # noqa: E402
from protocol import PROTOCOL_VERSION  # noqa: E402

MAX_WIRE = 64 * 1024 * 1024


# -- the server ----------------------------------------------------------------------------


def issue_token(data_dir: Path, spec: str) -> str:
    out = subprocess.run([sys.executable, "-m", "server", "--data-dir", str(data_dir),
                          "--issue-token", spec], cwd=ROOT, capture_output=True, text=True,
                         check=True, timeout=120)
    return out.stdout.strip().splitlines()[-1]


def _sample_rss(pid: int, into: list, stop: threading.Event, every_s: float = 1.0) -> None:
    while not stop.wait(every_s):
        with _suppress():
            into.append((time.monotonic(), rss_bytes(pid)))


def rss_bytes(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    return 0


# -- well-behaved sessions -----------------------------------------------------------------


@dataclass
class GoodResult:
    frames: int = 0
    seconds: float = 0.0
    errors: list[str] = field(default_factory=list)

    @property
    def fps(self) -> float:
        return self.frames / self.seconds if self.seconds else 0.0


def talking(t: float, phase: float) -> dict[str, np.ndarray]:
    body = np.zeros((21, 3), np.float32)
    body[14] = (0.15 * math.sin(1.1 * t), 0.2 * math.sin(0.9 * t + phase), 0.0)
    return {"body_pose": body,
            "jaw_pose": np.array([0.12 + 0.12 * math.sin(9 * t + phase), 0, 0], np.float32)}


async def good_session(url: str, token: str, index: int, size: int, fps: float,
                       seconds: float) -> GoodResult:
    result = GoodResult()
    try:
        async with await StreamClient.connect(url, "demo", token, timeout=60,
                                              client_name=f"good-{index}") as client:
            await client.request(width=size, height=size, max_fps=fps, codec="jpeg")
            await client.view({"yaw_deg": 20.0 * index, "distance": 2.4})
            t0 = time.monotonic()
            end = t0 + seconds
            next_drive = t0
            while (now := time.monotonic()) < end:  # bounded by the deadline
                if now >= next_drive:
                    await client.drive(talking(now - t0, index))
                    next_drive += 1 / 30
                try:
                    await client.next_frame(timeout=max(0.001, min(next_drive, end) - now))
                    result.frames += 1
                except TimeoutError:
                    pass
            result.seconds = seconds
            result.errors = [f"{e.code}: {e.message}" for e in client.errors]
    except (StreamError, OSError) as exc:
        result.errors.append(f"session ended: {exc}")
    return result


# -- hostile clients -----------------------------------------------------------------------


@dataclass
class HostileTally:
    refusals: collections.Counter = field(default_factory=collections.Counter)
    server_errors: list[str] = field(default_factory=list)  # 5xx answers: none expected
    accepted_bad: list[str] = field(default_factory=list)   # absurd input accepted


def ws_url(url: str) -> str:
    return stream_url(url, "demo")


async def _close_code(ws, timeout: float = 15.0) -> str:
    """Read until the server closes; the error code it sent (or the close code)."""
    from websockets.exceptions import ConnectionClosed

    code = None
    try:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            data = await asyncio.wait_for(ws.recv(), max(0.01, end - time.monotonic()))
            if isinstance(data, bytes):
                with _suppress():
                    msg = msgpack.unpackb(data)
                    if isinstance(msg, dict) and msg.get("type") == "error":
                        code = msg.get("code")
    except ConnectionClosed as exc:
        return code or f"close {exc.rcvd.code if exc.rcvd else '?'}"
    except TimeoutError:
        return code or "no answer"
    return code or "open"


class _suppress:
    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc: object) -> bool:
        return True


async def hostile_preauth(url: str, end: float, tally: HostileTally) -> None:
    from websockets.asyncio.client import connect

    big = msgpack.packb({"type": "hello", "version": PROTOCOL_VERSION,
                         "pad": b"\0" * int(7.6 * 2**20)})
    while time.monotonic() < end:
        silent = []
        try:
            for _ in range(6):  # a handful of silent connections, kept open
                with _suppress():
                    silent.append(await connect(ws_url(url), max_size=MAX_WIRE, proxy=None,
                                                open_timeout=5))
            ws = await connect(ws_url(url), max_size=MAX_WIRE, proxy=None, open_timeout=5)
            with _suppress():
                await ws.send(big)
            tally.refusals["preauth big: " + await _close_code(ws)] += 1
            for ws in silent:
                tally.refusals["preauth silent: " + await _close_code(ws, 20)] += 1
        except OSError as exc:
            tally.refusals[f"preauth connect: {type(exc).__name__}"] += 1
            await asyncio.sleep(0.2)


def _drive(seq: int, **smplx) -> bytes:
    return msgpack.packb({"type": "drive", "seq": seq, "smplx": smplx})


async def hostile_garbage(url: str, token: str, end: float, tally: HostileTally) -> None:
    from websockets.asyncio.client import connect
    from websockets.exceptions import ConnectionClosed

    bad = [
        _drive(1, betas=[1e300] * 10),
        _drive(2, leye_pose=[1e38, 0.0, 0.0]),
        _drive(3, jaw_pose=[float("nan"), 0.0, 0.0]),
        _drive(4, transl=[float("inf"), 0.0, 0.0]),
        _drive(5, body_pose=[[0.0, 0.0, 0.0]] * 5000),
        msgpack.packb({"type": "request", "max_fps": 0.001}),
        msgpack.packb({"type": "request", "width": 10**9, "height": 10**9}),
        msgpack.packb({"type": "view", "orbit": {"distance": 1e308}}),
        b"\xc1\xc1\xc1 not msgpack",
        msgpack.packb([1, 2, 3]),
        msgpack.packb({"type": ["drive"]}),
    ]
    while time.monotonic() < end:
        try:
            ws = await connect(ws_url(url), max_size=MAX_WIRE, proxy=None, open_timeout=10)
            await ws.send(msgpack.packb({"type": "hello", "version": PROTOCOL_VERSION,
                                         "token": token, "client": "garbage"}))
            n = 0
            while time.monotonic() < end and n < 2000:  # one connection: a bounded burst
                await ws.send(bad[n % len(bad)])
                n += 1
                with _suppress():
                    data = await asyncio.wait_for(ws.recv(), 0.02)
                    msg = msgpack.unpackb(data)
                    if isinstance(msg, dict) and msg.get("type") == "error":
                        tally.refusals["garbage: " + str(msg.get("code"))] += 1
                    elif isinstance(msg, dict) and msg.get("type") == "welcome":
                        tally.refusals["garbage: welcome"] += 1
            await ws.close()
        except (OSError, ConnectionClosed) as exc:
            tally.refusals[f"garbage closed: {type(exc).__name__}"] += 1
            await asyncio.sleep(0.2)


async def hostile_expensive(url: str, token: str, end: float, tally: HostileTally) -> None:
    try:
        async with await StreamClient.connect(url, "demo", token, timeout=60,
                                              client_name="expensive") as client:
            lim = client.limits
            await client.request(width=lim.max_width, height=lim.max_height,
                                 outputs=["rgb", "alpha", "depth"], codec="png",
                                 max_fps=lim.max_fps)
            i = 0
            while time.monotonic() < end:  # bounded by the deadline
                await client.drive(talking(i / 30, 0.0))
                i += 1
                with _suppress():
                    await client.next_frame(timeout=0.05)
            for e in client.errors:
                tally.refusals["expensive: " + e.code] += 1
    except (StreamError, OSError) as exc:
        tally.refusals[f"expensive refused: {exc}"[:80]] += 1


def _npz_bomb() -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        header = io.BytesIO()
        np.lib.format.write_array_header_1_0(
            header, {"descr": "<f4", "fortran_order": False, "shape": (10**13,)})
        z.writestr("means.npy", header.getvalue() + b"\0" * 4096)
        with z.open("log_scales.npy", "w") as member:  # 400 MB of zeros: ~400 KB deflated
            np.lib.format.write_array_header_1_0(
                member, {"descr": "<f4", "fortran_order": False, "shape": (10**8,)})
            zeros = b"\0" * 2**20
            for _ in range(400):
                member.write(zeros)
    return buf.getvalue()


def _zip(members: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in members.items():
            z.writestr(name, data)
    return buf.getvalue()


def absurd_avatar(package_zip: bytes) -> bytes:
    """The demo package with every log-scale set to 80 (finite, absurd)."""
    src = zipfile.ZipFile(io.BytesIO(package_zip))
    out = {}
    for name in src.namelist():
        data = src.read(name)
        if name.endswith(".npz"):
            with np.load(io.BytesIO(data), allow_pickle=False) as npz:
                arrays = {k: npz[k] for k in npz.files}
            for key in arrays:
                if "scale" in key:
                    arrays[key] = np.full_like(arrays[key], 80.0)
            b = io.BytesIO()
            np.savez_compressed(b, **arrays)
            data = b.getvalue()
        out[name] = data
    return _zip(out)


async def hostile_uploads(url: str, token: str, end: float, tally: HostileTally) -> None:
    from websockets.asyncio.client import connect

    headers = {"Authorization": f"Bearer {token}"}
    async with httpx.AsyncClient(base_url=url, headers=headers, timeout=60) as http:
        demo = await http.get("/v1/avatars/demo/package")
        package = demo.content if demo.status_code == 200 else b""
        bombs = {
            "npz bomb avatar": _zip({"avatar.json": json.dumps({"schema": 1}).encode(),
                                     "gaussians.npz": _npz_bomb()}),
            "absurd avatar": absurd_avatar(package) if package else b"",
            "truncated zip": package[: len(package) // 2] if package else b"PK\x03\x04",
            "not a zip": b"definitely not a zip" * 100,
        }
        archive_bomb = io.BytesIO()
        with zipfile.ZipFile(archive_bomb, "w", zipfile.ZIP_DEFLATED) as z:
            with z.open("dataset/frames.bin", "w") as member:
                for _ in range(1024):  # 1 GiB of zeros, ~1 MB deflated
                    member.write(b"\0" * 2**20)
        # A slow reader: a session that never reads its frames.
        slow = await connect(ws_url(url), max_size=MAX_WIRE, proxy=None, open_timeout=10)
        await slow.send(msgpack.packb({"type": "hello", "version": PROTOCOL_VERSION,
                                       "token": token, "client": "slow-reader"}))
        try:
            while time.monotonic() < end:
                for name, body in bombs.items():
                    if not body:
                        continue
                    r = await http.post("/v1/avatars", content=body,
                                        headers={"Content-Type": "application/zip"})
                    if r.status_code >= 500:
                        tally.server_errors.append(f"{name}: {r.status_code}")
                    elif r.status_code < 300:
                        tally.accepted_bad.append(f"{name}: {r.status_code}")
                        with _suppress():
                            await http.delete(f"/v1/avatars/{r.json()['id']}")
                    tally.refusals[f"upload {name}: {r.status_code}"] += 1
                r = await http.post("/v1/jobs", files={
                    "archive": ("bomb.zip", archive_bomb.getvalue(), "application/zip")})
                if r.status_code >= 500:
                    tally.server_errors.append(f"job archive bomb: {r.status_code}")
                elif r.status_code < 300:
                    tally.accepted_bad.append(f"job archive bomb: {r.status_code}")
                tally.refusals[f"job archive bomb: {r.status_code}"] += 1
                await asyncio.sleep(0.5)
        finally:
            with _suppress():
                await asyncio.wait_for(slow.close(), 5)


# -- the second review's attacks (issue 25) ------------------------------------------------


async def _own_room(http: httpx.AsyncClient) -> str | None:
    r = await http.post("/v1/rooms", json={})
    return r.json()["id"] if r.status_code == 201 else None


async def hostile_roomburst(url: str, token: str, end: float, tally: HostileTally) -> None:
    from websockets.asyncio.client import connect

    big = msgpack.packb({"type": "hello", "version": PROTOCOL_VERSION,
                         "pad": b"\0" * int(7.9 * 2**20)})
    garbage = {"Authorization": "Bearer tsk_garbage"}
    async with httpx.AsyncClient(base_url=url, timeout=30,
                                 headers={"Authorization": f"Bearer {token}"}) as http:
        room = await _own_room(http)
    target = f"{ws_url(url).split('?')[0]}?room={room}"

    async def one() -> None:
        try:
            ws = await connect(target, additional_headers=garbage, max_size=MAX_WIRE,
                               proxy=None, open_timeout=5)
            with _suppress():
                await ws.send(big)
            tally.refusals["roomburst: " + await _close_code(ws, 10)] += 1
        except OSError as exc:
            tally.refusals[f"roomburst connect: {type(exc).__name__}"] += 1

    while time.monotonic() < end:
        await asyncio.gather(*(one() for _ in range(16)))
        await asyncio.sleep(0.5)


def bomb_avatar(package_zip: bytes) -> bytes:
    """The demo package with every log-scale at 6 (in range: 400 m splats)."""
    out = {}
    with zipfile.ZipFile(io.BytesIO(package_zip)) as z:
        for name in z.namelist():
            data = z.read(name)
            if name.endswith("gaussians.npz"):
                arrays = dict(np.load(io.BytesIO(data)))
                for key in arrays:
                    if "scale" in key:
                        arrays[key] = np.full_like(arrays[key], 6.0)
                b = io.BytesIO()
                np.savez_compressed(b, **arrays)
                data = b.getvalue()
            out[name] = data
    return _zip(out)


async def hostile_bomb(url: str, token: str, end: float, tally: HostileTally) -> None:
    headers = {"Authorization": f"Bearer {token}"}
    async with httpx.AsyncClient(base_url=url, headers=headers, timeout=120) as http:
        demo = await http.get("/v1/avatars/demo/package")
        bomb = bomb_avatar(demo.content) if demo.status_code == 200 else b""
        while time.monotonic() < end and bomb:
            r = await http.post("/v1/avatars", content=bomb,
                                headers={"Content-Type": "application/zip"})
            tally.refusals[f"bomb upload: {r.status_code}"] += 1
            if r.status_code >= 500:
                tally.server_errors.append(f"bomb upload: {r.status_code}")
            elif r.status_code < 300:  # got in: stream it at the largest size for a while
                tally.accepted_bad.append(f"bomb upload: {r.status_code}")
                avatar = r.json()["id"]
                with _suppress():
                    async with await StreamClient.connect(url, avatar, token,
                                                          timeout=60) as c:
                        lim = c.limits
                        await c.request(width=lim.max_width, height=lim.max_height,
                                        codec="png", max_fps=lim.max_fps)
                        stop = min(end, time.monotonic() + 20)
                        while time.monotonic() < stop:
                            with _suppress():
                                await c.next_frame(timeout=1)
                with _suppress():
                    await http.delete(f"/v1/avatars/{avatar}")
            await asyncio.sleep(2.0)


async def hostile_whep(url: str, token: str, end: float, tally: HostileTally) -> None:
    from aiortc import RTCPeerConnection

    headers = {"Authorization": f"Bearer {token}"}
    async with httpx.AsyncClient(base_url=url, headers=headers, timeout=30) as http:
        room = await _own_room(http)
        while time.monotonic() < end:
            pcs = []
            for _ in range(3):
                pc = RTCPeerConnection()
                pc.addTransceiver("video", direction="recvonly")
                pc.createDataChannel("telesplat")
                await pc.setLocalDescription(await pc.createOffer())
                r = await http.post(f"/v1/rooms/{room}/whep", content=pc.localDescription.sdp,
                                    headers={"Content-Type": "application/sdp"})
                tally.refusals[f"whep never completed: {r.status_code}"] += 1
                if r.status_code >= 500 and r.status_code != 503:
                    tally.server_errors.append(f"whep: {r.status_code}")
                pcs.append(pc)  # never given the answer: ICE never completes
            await asyncio.sleep(5.0)
            for pc in pcs:
                await pc.close()


async def hostile_dcflood(url: str, token: str, end: float, tally: HostileTally) -> None:
    async with httpx.AsyncClient(base_url=url, timeout=30,
                                 headers={"Authorization": f"Bearer {token}"}) as http:
        room = await _own_room(http)
    while time.monotonic() < end:
        for mode in (["--pings", "20000"], ["--big", str(16 * 2**20)]):
            proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "tests.webrtc_flooder", url, room, token, *mode,
                "--hold", "5", cwd=ROOT, stdin=asyncio.subprocess.PIPE,
                stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL)
            try:
                ready = await asyncio.wait_for(proc.stdout.readline(), 60)
                if not ready.startswith(b"ready"):
                    tally.refusals[f"dcflood {mode[0]}: not admitted"] += 1
                    continue
                proc.stdin.write(b"go\n")
                await proc.stdin.drain()
                done = await asyncio.wait_for(proc.stdout.readline(), 90)
                info = json.loads(done.split(b" ", 1)[1]) if done.startswith(b"done") else {}
                closed = info.get("closed_after_s")
                tally.refusals[f"dcflood {mode[0]}: "
                               f"{'closed' if closed is not None else 'kept open'}"] += 1
            except (TimeoutError, ValueError):
                tally.refusals[f"dcflood {mode[0]}: no answer"] += 1
            finally:
                with _suppress():
                    proc.kill()
                await proc.wait()
            if time.monotonic() >= end:
                break


def _fuzzed(rng: np.random.Generator, seq: int) -> bytes:
    base = _drive(seq, jaw_pose=[0.1, 0.0, 0.0], body_pose=[[0.0, 0.1, 0.0]] * 21)
    kind = seq % 4
    if kind == 0:  # bytes flipped
        data = bytearray(base)
        for i in rng.integers(0, len(data), size=4):
            data[i] = int(rng.integers(0, 256))
        return bytes(data)
    if kind == 1:  # truncated
        return base[: int(rng.integers(1, len(base)))]
    if kind == 2:  # random msgpack
        return msgpack.packb({"type": "drive", "seq": seq,
                              "smplx": {str(rng.integers(0, 9)): rng.normal(size=3).tolist()}})
    return bytes(rng.integers(0, 256, size=int(rng.integers(1, 512)), dtype=np.uint8))


async def hostile_fuzz(url: str, token: str, end: float, tally: HostileTally) -> None:
    from websockets.asyncio.client import connect
    from websockets.exceptions import ConnectionClosed

    rng = np.random.default_rng(0)
    async with httpx.AsyncClient(base_url=url, timeout=30,
                                 headers={"Authorization": f"Bearer {token}"}) as http:
        room = await _own_room(http)
    target = f"{ws_url(url).split('?')[0]}?room={room}"
    seq = 0
    while time.monotonic() < end:
        try:
            ws = await connect(target, max_size=MAX_WIRE, proxy=None, open_timeout=10)
            await ws.send(msgpack.packb({"type": "hello", "version": PROTOCOL_VERSION,
                                         "token": token, "role": "perform"}))
            n = 0
            while time.monotonic() < end and n < 3000:  # one connection: a bounded burst
                seq += 1
                n += 1
                await ws.send(_fuzzed(rng, seq))
                with _suppress():
                    msg = msgpack.unpackb(await asyncio.wait_for(ws.recv(), 0.01))
                    if isinstance(msg, dict) and msg.get("type") == "error":
                        tally.refusals["fuzz: " + str(msg.get("code"))] += 1
            await ws.close()
        except (OSError, ConnectionClosed) as exc:
            tally.refusals[f"fuzz closed: {type(exc).__name__}"] += 1
            await asyncio.sleep(0.2)


async def health_probe(url: str, end: float, into: list[float]) -> None:
    """``GET /v1/health`` once a second; each answer's time in ms (a failure counts 10 s)."""
    async with httpx.AsyncClient(base_url=url, timeout=10) as http:
        while time.monotonic() < end:
            t0 = time.monotonic()
            try:
                ok = (await http.get("/v1/health")).status_code == 200
            except httpx.HTTPError:
                ok = False
            into.append((time.monotonic() - t0) * 1e3 if ok else 10_000.0)
            await asyncio.sleep(max(0.0, 1.0 - (time.monotonic() - t0)))


# -- the run -------------------------------------------------------------------------------


async def run_good(url: str, token: str, n: int, size: int, fps: float,
                   seconds: float) -> list[GoodResult]:
    return await asyncio.gather(*(good_session(url, token, i, size, fps, seconds)
                                  for i in range(n)))


async def run_soak(url: str, good_token: str, bad_tokens: list[str], args) -> tuple:
    end = time.monotonic() + args.seconds
    tally = HostileTally()
    makers = [lambda: hostile_preauth(url, end, tally),
              lambda: hostile_garbage(url, bad_tokens[1], end, tally),
              lambda: hostile_expensive(url, bad_tokens[2], end, tally),
              lambda: hostile_uploads(url, bad_tokens[3], end, tally),
              lambda: hostile_roomburst(url, bad_tokens[4], end, tally),
              lambda: hostile_bomb(url, bad_tokens[5], end, tally),
              lambda: hostile_whep(url, bad_tokens[6], end, tally),
              lambda: hostile_dcflood(url, bad_tokens[7], end, tally),
              lambda: hostile_fuzz(url, bad_tokens[8], end, tally)][: args.hostile]
    hostile = [asyncio.create_task(make()) for make in makers]
    health: list[float] = []
    probe = asyncio.create_task(health_probe(url, end, health))
    await asyncio.sleep(2.0)  # the hostile load is on before the measured sessions start
    good = await run_good(url, good_token, args.good, args.size, args.fps, args.seconds - 4)
    results = await asyncio.gather(*hostile, return_exceptions=True)
    await probe
    for r in results:
        if isinstance(r, BaseException):
            tally.refusals[f"hostile client raised {type(r).__name__}: {r}"[:100]] += 1
    return good, tally, health


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=300.0, help="the soak phase")
    parser.add_argument("--baseline", type=float, default=30.0, help="the undisturbed phase")
    parser.add_argument("--good", type=int, default=4, help="well-behaved sessions")
    parser.add_argument("--hostile", type=int, default=9, choices=range(0, 10),
                        help="how many of the attack classes run (in the order above)")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--fps", type=float, default=10.0, help="well-behaved max_fps")
    parser.add_argument("--avatar", default="synthetic")
    parser.add_argument("--warmup", type=float, default=60.0,
                        help="seconds of the soak before memory growth is measured (buffers, "
                             "caches and allocator arenas fill in the first minute)")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory(prefix="telesplat-soak-") as tmp:
        data_dir = Path(tmp)
        # one hostile user per attack class: each has its own per-user quotas to spend
        bad_tokens = [issue_token(data_dir, f"mallory{i}:stream,train") for i in range(9)]
        proc, url, good_token = start_server(data_dir, 1, args.good + args.hostile + 8,
                                             args.avatar)
        try:
            baseline = asyncio.run(run_good(url, good_token, args.good, args.size, args.fps,
                                            args.baseline))
            rss_start = rss_bytes(proc.pid)
            samples: list[tuple[float, int]] = []
            stop = threading.Event()
            sampler = threading.Thread(target=_sample_rss, args=(proc.pid, samples, stop),
                                       daemon=True)
            sampler.start()
            good, tally, health_ms = asyncio.run(run_soak(url, good_token, bad_tokens, args))
            time.sleep(2.0)  # let closed sessions release their buffers
            stop.set()
            sampler.join(5)
            rss_end = rss_bytes(proc.pid)
            alive = proc.poll() is None
            health = httpx.get(url + "/v1/health", timeout=10).status_code if alive else None
        finally:
            stop_server(proc)

    base_fps = float(np.mean([r.fps for r in baseline]))
    soak_fps = float(np.mean([r.fps for r in good]))
    warm_at = samples[0][0] + args.warmup if samples else 0.0
    rss_warm = next((b for t, b in samples if t >= warm_at), rss_start)
    growth = (rss_end - rss_warm) / rss_warm if rss_warm else float("nan")
    good_errors = [e for r in good for e in r.errors]
    load = os.getloadavg()
    print(f"\nSoak on loopback: {args.good} well-behaved sessions ({args.size}x{args.size} JPEG, "
          f"max_fps {args.fps:g}, driving at 30 Hz) beside {args.hostile} hostile clients for "
          f"{args.seconds:g} s; undisturbed phase {args.baseline:g} s; {args.avatar} avatar; "
          f"{os.cpu_count()} CPUs ({platform.processor() or platform.machine()}), load "
          f"average {load[0]:.1f} at the end.\n")
    print("| measure | value | target |")
    print("|---|---:|---|")
    print(f"| well-behaved fps, undisturbed | {base_fps:.1f} | |")
    print(f"| well-behaved fps, under attack | {soak_fps:.1f} "
          f"({soak_fps / base_fps:.0%} of undisturbed) | >= 80% |")
    print(f"| min fps of a well-behaved session under attack | "
          f"{min(r.fps for r in good):.1f} | |")
    print(f"| server RSS: soak start, after {args.warmup:g} s, end | {rss_start / 2**20:.0f}, "
          f"{rss_warm / 2**20:.0f}, {rss_end / 2**20:.0f} MiB "
          f"(growth after warm-up {growth:+.1%}) | <= +5% |")
    print(f"| errors seen by well-behaved sessions | {len(good_errors)} | 0 |")
    print(f"| server 5xx answers | {len(tally.server_errors)} | 0 |")
    print(f"| absurd uploads accepted | {len(tally.accepted_bad)} | 0 |")
    health_p95 = float(np.percentile(health_ms, 95)) if health_ms else float("nan")
    print(f"| /v1/health during the soak, p95 (max) | {health_p95:.0f} ms "
          f"({max(health_ms, default=float('nan')):.0f} ms) | <= 100 ms |")
    print(f"| server alive, /v1/health after the soak | {alive}, {health} | True, 200 |")
    if samples:
        t0 = samples[0][0]
        print("\nServer RSS (MiB) every 30 s of the soak: " + ", ".join(
            f"{b / 2**20:.0f}" for t, b in samples if round(t - t0) % 30 == 0))
    print("\nHostile clients' refusals (expected):\n")
    print("| what | count |")
    print("|---|---:|")
    for what, count in sorted(tally.refusals.items()):
        print(f"| {what} | {count} |")
    for line in good_errors[:10] + tally.server_errors[:10] + tally.accepted_bad[:10]:
        print("  !", line)
    ok = (soak_fps >= 0.8 * base_fps and growth <= 0.05 and not good_errors
          and not tally.server_errors and not tally.accepted_bad and alive
          and health_p95 <= 100.0)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
