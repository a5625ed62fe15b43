"""`make run`'s first start, timed: from nothing to the page, the first frame and the trained demo.

Starts ``python -m server serve --demo-avatar trained`` (what ``make run`` runs) as a
subprocess with an empty data dir and an empty demo cache (temporary folders; the user's
``~/.cache/telesplat/demo-avatar-*`` is never touched) and, unless ``--keep-caches``, empty
``XDG_CACHE_HOME`` and ``NUMBA_CACHE_DIR`` too (a fresh clone: the synthetic body models are
written and the render kernels compiled on the way). Seconds from the process start to:

    health      GET /v1/health answers 200
    page        GET / serves the page
    frame       the first frame of a /v1/stream session on ``demo``
    captured    GET /v1/demo reports the training stage (the capture is done)
    trained     GET /v1/demo reports ``ready`` (the trained demo swapped in)

While the build runs, one session streams for 20 s every 2 minutes (a new view every 1/30 s,
30 fps asked for: frames per second received per stage; idle in between, as a page nobody
touches, which costs no render time) and /v1/health is timed once a second (median and 95th
percentile per stage), so what the build costs live sessions shows. ``--hog N`` runs N
busy-loop processes beside it all, in a session of their own (other work on the machine;
``--hog-session same`` puts them in the server's session). ``--timeout`` bounds the whole
run: a build not done by then is reported with its progress and the time it would take at
the rate seen so far.

    .venv/bin/python bench/first_run.py [--hog 2] [--timeout 1800] [--recipe JSON] \\
        [--job-nice N] [--job-threads N] [--keep-caches] [--out results.json]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.waitpolicy import hogs  # noqa: E402
from client.stream import StreamClient  # noqa: E402
from server.jobs.demo_build import CAPTURE_SHARE  # noqa: E402

VIEW_HZ = 30.0
STREAM_WINDOW_S = 20.0  # a session turns the view for this long ...
STREAM_EVERY_S = 120.0  # ... once every this many seconds (live use now and then)
HEALTH_EVERY_S = 1.0
DEMO_EVERY_S = 1.0


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Timeline:
    """What happened when (seconds since the server process started), shared by threads."""

    def __init__(self, start: float) -> None:
        self.start = start
        self.marks: dict[str, float] = {}
        self.stage = "starting"  # the build's stage, from /v1/demo
        self.progress = 0.0
        self.health_ms: dict[str, list[float]] = {}
        self.frames: dict[str, int] = {}
        self.seconds: dict[str, float] = {}  # streamed seconds per stage
        self.error: str | None = None
        self.lock = threading.Lock()
        self.done = threading.Event()

    def now(self) -> float:
        return time.monotonic() - self.start

    def mark(self, name: str) -> None:
        with self.lock:
            self.marks.setdefault(name, self.now())


def _stage(status: dict) -> str:
    if status.get("state") == "building":
        return status.get("stage") or "building"
    return "trained" if status.get("state") == "ready" else status.get("state", "?")


def watch_http(base: str, line: Timeline, deadline: float) -> None:
    """Health and page first; then /v1/demo and /v1/health once a second."""
    with httpx.Client(base_url=base, timeout=10.0) as http:
        while time.monotonic() < deadline:
            with contextlib.suppress(httpx.HTTPError):
                if http.get("/v1/health").status_code == 200:
                    line.mark("health")
                    break
            time.sleep(0.05)
        while time.monotonic() < deadline and "page" not in line.marks:
            with contextlib.suppress(httpx.HTTPError):
                page = http.get("/")
                if page.status_code == 200 and "<html" in page.text.lower():
                    line.mark("page")
            time.sleep(0.05)
        next_health = 0.0
        while time.monotonic() < deadline and not line.done.is_set():
            with contextlib.suppress(httpx.HTTPError):
                status = http.get("/v1/demo").json()
                stage = _stage(status)
                with line.lock:
                    line.stage, line.progress = stage, float(status.get("progress", 0.0))
                if stage == "train":
                    line.mark("captured")
                if stage == "trained":
                    line.mark("captured")
                    line.mark("trained")
                if stage == "failed":
                    line.marks["failed"] = line.now()
                    line.error = status.get("error")
            if time.monotonic() >= next_health:
                next_health = time.monotonic() + HEALTH_EVERY_S
                t0 = time.perf_counter()
                with contextlib.suppress(httpx.HTTPError):
                    http.get("/v1/health")
                    ms = (time.perf_counter() - t0) * 1e3
                    with line.lock:
                        line.health_ms.setdefault(line.stage, []).append(ms)
            if "trained" in line.marks and time.monotonic() > line.start + line.marks[
                    "trained"] + 15:
                line.done.set()  # a few seconds of the trained demo streaming, then done
            time.sleep(DEMO_EVERY_S / 4)


async def stream_session(base: str, token: str, line: Timeline, deadline: float) -> None:
    """One session on ``demo`` from the moment the page is up: its first frame, then a new
    view every 1/VIEW_HZ s; frames counted per build stage."""
    while "page" not in line.marks and time.monotonic() < deadline:
        await asyncio.sleep(0.05)
    client = await StreamClient.connect(base, "demo", token, timeout=120)
    async with client:
        await client.request(max_fps=VIEW_HZ)
        await client.next_frame(timeout=300)
        line.mark("frame")
        stop = asyncio.Event()

        async def turn() -> None:
            yaw = 0.0
            while not stop.is_set():
                yaw = (yaw + 2.0) % 360.0
                await client.view({"yaw_deg": yaw - 180.0})
                await asyncio.sleep(1 / VIEW_HZ)

        while not line.done.is_set() and time.monotonic() < deadline:
            stop.clear()
            turner = asyncio.create_task(turn())
            last, end = time.monotonic(), time.monotonic() + STREAM_WINDOW_S
            try:
                while time.monotonic() < min(end, deadline) and not line.done.is_set():
                    with contextlib.suppress(TimeoutError, asyncio.TimeoutError):
                        await client.next_frame(timeout=1.0)
                        with line.lock:
                            line.frames[line.stage] = line.frames.get(line.stage, 0) + 1
                    now = time.monotonic()
                    with line.lock:
                        line.seconds[line.stage] = line.seconds.get(line.stage, 0.0) + now - last
                    last = now
            finally:
                stop.set()
                turner.cancel()
            # idle between windows (an idle page costs no render time): the build goes on
            await asyncio.sleep(max(0.0, min(STREAM_EVERY_S - STREAM_WINDOW_S,
                                             deadline - time.monotonic())))


def _token(data_dir: Path, deadline: float, server: subprocess.Popen, log: Path) -> str:
    path = data_dir / "local_token"
    while time.monotonic() < deadline and server.poll() is None:
        if path.is_file() and path.read_text().strip():
            return path.read_text().strip()
        time.sleep(0.1)
    raise RuntimeError("the server wrote no local token; its log ends:\n"
                       + log.read_text(errors="replace")[-3000:])


def run(args: argparse.Namespace) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench-first-run-") as tmp_name:
        tmp = Path(tmp_name)
        env = dict(os.environ)
        env.update(TELESPLAT_DATA_DIR=str(tmp / "data"),
                   TELESPLAT_DEMO_CACHE_DIR=str(tmp / "demo-cache"), PYTHONUNBUFFERED="1")
        if args.job_nice is not None:
            env["TELESPLAT_JOB_NICE"] = str(args.job_nice)
        if args.job_threads is not None:
            env["TELESPLAT_JOB_THREADS"] = str(args.job_threads)
        if args.recipe:
            env["TELESPLAT_DEMO_BUILD_RECIPE"] = args.recipe
        if not args.keep_caches:
            env.update(XDG_CACHE_HOME=str(tmp / "cache"), NUMBA_CACHE_DIR=str(tmp / "numba"))
        port = free_port()
        base = f"http://127.0.0.1:{port}"
        command = [sys.executable, "-m", "server", "--host", "127.0.0.1", "--port",  # = serve
                   str(port), "--demo-avatar", "trained"]
        with hogs(args.hog, args.hog_session == "own"), \
                open(tmp / "server.log", "wb") as log:
            start = time.monotonic()
            deadline = start + args.timeout
            server = subprocess.Popen(command, cwd=REPO, env=env, stdout=log,
                                      stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                      start_new_session=True)
            line = Timeline(start)
            watcher = threading.Thread(target=watch_http, args=(base, line, deadline),
                                       daemon=True)
            watcher.start()
            loads = []
            try:
                token = _token(tmp / "data", deadline, server, tmp / "server.log")
                streamer = threading.Thread(target=lambda: asyncio.run(
                    stream_session(base, token, line, deadline)), daemon=True)
                streamer.start()
                try:
                    while time.monotonic() < deadline and not line.done.is_set() \
                            and "failed" not in line.marks and server.poll() is None:
                        loads.append(os.getloadavg()[0])
                        time.sleep(5.0)
                except KeyboardInterrupt:  # stopped early: what was seen so far is reported
                    line.marks.setdefault("stopped", line.now())
                line.done.set()
                streamer.join(timeout=15)
                watcher.join(timeout=15)
            finally:
                line.done.set()
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(server.pid, signal.SIGTERM)
                try:
                    server.wait(timeout=60)
                except subprocess.TimeoutExpired:
                    os.killpg(server.pid, signal.SIGKILL)
                    server.wait()
            elapsed = line.now()
        log_tail = (tmp / "server.log").read_text(errors="replace")[-3000:]
    result = {"hog": args.hog, "hog_session": args.hog_session, "job_nice": args.job_nice,
              "job_threads": args.job_threads, "recipe": args.recipe, "timeout": args.timeout,
              "fresh_caches": not args.keep_caches, "elapsed_s": elapsed,
              "marks_s": line.marks, "stage_at_end": line.stage, "progress_at_end": line.progress,
              "error": line.error,
              "load_avg": {"median": statistics.median(loads) if loads else None,
                           "max": max(loads) if loads else None},
              "stream_fps": {s: line.frames.get(s, 0) / t for s, t in line.seconds.items()
                             if t > 0},
              "health_ms": {s: {"median": statistics.median(v),
                                "p95": sorted(v)[int(0.95 * (len(v) - 1))], "n": len(v)}
                            for s, v in line.health_ms.items() if v}}
    marks = line.marks
    if "trained" not in marks and "captured" in marks and line.progress > CAPTURE_SHARE:
        # the training's rate so far (its share of the progress since the capture ended)
        part = (line.progress - CAPTURE_SHARE) / (1 - CAPTURE_SHARE)
        result["trained_estimate_s"] = marks["captured"] + (elapsed - marks["captured"]) / part
    elif "trained" not in marks and "page" in marks and line.progress > 0:
        # still filming: the capture's rate so far, over its share
        result["captured_estimate_s"] = (marks["page"] + (elapsed - marks["page"])
                                         * CAPTURE_SHARE / line.progress)
    if "page" not in line.marks:
        result["server_log_tail"] = log_tail
    return result


def main() -> None:
    signal.signal(signal.SIGTERM, _interrupt)  # unwinds: the server and busy loops stop
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hog", type=int, default=0, help="busy-loop processes beside it")
    ap.add_argument("--hog-session", choices=["own", "same"], default="own")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds for the whole run")
    ap.add_argument("--recipe", default=None, help="demo_build_recipe as JSON (default: the "
                                                  "server's default recipe)")
    ap.add_argument("--job-nice", type=int, default=None, help="job_nice (default: the server's)")
    ap.add_argument("--job-threads", type=int, default=None,
                    help="job_threads (default: the server's)")
    ap.add_argument("--keep-caches", action="store_true",
                    help="use this user's body-model and numba caches (not a fresh clone)")
    ap.add_argument("--out", type=Path, default=None, help="also write the result as JSON")
    args = ap.parse_args()
    if args.recipe:
        json.loads(args.recipe)  # a bad one fails here, not in the server
    result = run(args)
    text = json.dumps(result, indent=1)
    print(text)
    if args.out:
        args.out.write_text(text)
    marks = result["marks_s"]
    print("| hogs | health | page | first frame | captured | trained | load avg |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    cells = [f"{marks[k]:.0f} s" if k in marks else "-" for k in
             ("health", "page", "frame", "captured", "trained")]
    if "trained" not in marks:
        cells[-1] = f"not by {result['elapsed_s']:.0f} s ({100 * result['progress_at_end']:.0f}%)"
        if "trained_estimate_s" in result:
            cells[-1] += f", ~{result['trained_estimate_s'] / 60:.0f} min at the training's rate"
        if "captured_estimate_s" in result:
            cells[-2] = f"~{result['captured_estimate_s'] / 60:.0f} min at its rate"
    load = result["load_avg"]["median"]
    load_cell = "-" if load is None else f"{load:.1f}"
    print(f"| {args.hog} | " + " | ".join(cells) + f" | {load_cell} |")


if __name__ == "__main__":
    main()
