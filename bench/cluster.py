"""The Ray backends against the local ones, side by side in one run (issue 17).

Starts a real local Ray head (tests/ray_cluster.py: ``ray start --head`` on 127.0.0.1) and,
one after the other, servers (``python -m server`` subprocesses, the demo avatar of
``--avatar``) configured as

* ``local``: render_threads 1 (and ``--threads`` torch threads), job_backend local;
* ``ray x1`` / ``ray x2``: render_backend ray with one / two render actors of ``--threads``
  CPUs each, job_backend ray;

and measures on each:

* gateway overhead per frame: one session in lockstep (drive, wait for its frame, drive ...);
  per frame, the round trip minus the frame's own pose + render + encode time (which the
  renderer, local or remote, reports). What is left is the WebSocket, the session's loop and,
  with Ray, the actor call and the frame's trip back through the object store;
* throughput: ``--sessions`` sessions in lockstep at once, frames per second in total;
* job start latency (local and ray x1 only): POST /v1/jobs of a tiny synthetic capture, then
  the time to the job's first ``progress`` event (its first iteration; progress_interval 1).

    nice -n 10 .venv/bin/python bench/cluster.py [--seconds 8] [--size 256] [--sessions 4]
                                                 [--threads 1] [--avatar trained] [--repeat 1]

Prints Markdown tables. On a shared machine compare the rows of one run with each other only.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.stream import motion_frame, percentile, start_server, stop_server  # noqa: E402
from client import StreamClient  # noqa: E402
from tests.ray_cluster import ray_cluster  # noqa: E402

WARMUP_S = 2.0
JOB_TIMEOUT_S = 300.0
START_WORKERS_S = 300.0
TINY_JOB = {"preset": "test", "iterations": 5, "checkpoint_interval": 5, "progress_interval": 1}


@dataclass
class Run:
    name: str
    latency_ms: list[float] = field(default_factory=list)
    stage_ms: list[float] = field(default_factory=list)   # pose + render + encode
    overhead_ms: list[float] = field(default_factory=list)
    fps: list[float] = field(default_factory=list)  # one per round
    job_start_s: float = float("nan")
    job_running_s: float = float("nan")


# -- streaming ---------------------------------------------------------------------------------


async def lockstep(url: str, token: str, index: int, size: int, seconds: float,
                   start: asyncio.Event, run: Run | None) -> int:
    """Drive, wait for that frame, repeat; frames counted after the warm-up."""
    async with await StreamClient.connect(url, "demo", token, timeout=120,
                                          client_name=f"bench-{index}") as client:
        await client.request(width=size, height=size, max_fps=client.limits.max_fps,
                             codec="jpeg")
        await client.view({"yaw_deg": 15.0 * index, "distance": 2.4})
        await start.wait()
        t0 = time.monotonic()
        measure_from, end = t0 + WARMUP_S, t0 + WARMUP_S + seconds
        frames = 0
        while time.monotonic() < end:  # bounded by the deadline
            sent = time.monotonic()
            seq = await client.drive(motion_frame(sent - t0, 0.7 * index))
            frame = await client.wait_frame(seq, timeout=60)
            got = time.monotonic()
            if got < measure_from:
                continue
            frames += 1
            if run is not None:
                t = frame.timings
                stages = t.pose + t.render + t.encode
                run.latency_ms.append(1000 * (got - sent))
                run.stage_ms.append(stages)
                run.overhead_ms.append(1000 * (got - sent) - stages)
        return frames


async def sessions_at_once(url: str, token: str, sessions: int, size: int, seconds: float,
                           run: Run | None) -> int:
    start = asyncio.Event()
    tasks = [asyncio.create_task(lockstep(url, token, i, size, seconds, start,
                                          run if i == 0 else None))
             for i in range(sessions)]
    await asyncio.sleep(1.0)  # every session connected (and placed) before the clock starts
    start.set()
    return sum(await asyncio.gather(*tasks))


# -- jobs --------------------------------------------------------------------------------------


def tiny_capture(root: Path) -> bytes:
    """A 32 px, 3-camera, 2-frame synthetic capture as an upload zip."""
    from avatar_core.synth.capture import CaptureSpec, capture
    from avatar_core.synth.model_writer import write_synthetic_models
    from tests.test_jobs_support import zip_dataset

    files = write_synthetic_models(root / "models", seed=0)
    spec = CaptureSpec(sequences=(("smile",),), num_cameras=3, resolution=32, max_frames=2,
                       supersample=1, cross_identity=None, workers=1)
    return zip_dataset(capture(root / "capture", spec, model_dir=files.root))


def job_start(url: str, token: str, archive: bytes) -> tuple[float, float]:
    """Seconds from POST /v1/jobs to the job's 'running' state and to its first progress."""
    headers = {"Authorization": f"Bearer {token}"}
    with httpx.Client(base_url=url, headers=headers, timeout=120) as c:
        t0 = time.monotonic()
        r = c.post("/v1/jobs", data={"config": json.dumps(TINY_JOB), "name": "bench"},
                   files={"archive": ("take.zip", archive, "application/zip")})
        r.raise_for_status()
        running = progress = float("nan")
        with c.stream("GET", f"/v1/jobs/{r.json()['id']}/events",
                      timeout=httpx.Timeout(30.0, read=JOB_TIMEOUT_S)) as events:
            kind = None
            # Read to the end (the job's end ends the stream): no job outlives its server.
            for line in events.iter_lines():
                if line.startswith("event: "):
                    kind = line[7:]
                elif line.startswith("data: ") and kind == "state" and \
                        json.loads(line[6:]).get("state") == "running":
                    running = time.monotonic() - t0
                elif line.startswith("data: ") and kind == "progress" and progress != progress:
                    progress = time.monotonic() - t0
    if progress != progress:
        raise RuntimeError("the job ended without a progress event")
    return running, progress


def wait_for_render_workers(url: str, token: str, count: int) -> None:
    """Until ``count`` render workers are ready (they start beside the server, not before)."""
    deadline = time.monotonic() + START_WORKERS_S
    with httpx.Client(base_url=url, headers={"Authorization": f"Bearer {token}"},
                      timeout=30) as c:
        while time.monotonic() < deadline:
            workers = c.get("/v1/cluster/render").json().get("workers", [])
            if sum(w["state"] == "ready" for w in workers) >= count:
                return
            time.sleep(0.5)
    raise TimeoutError(f"{count} render workers not ready after {START_WORKERS_S} s")


# -- the servers -------------------------------------------------------------------------------


@contextlib.contextmanager
def environment(values: dict[str, str]):
    saved = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def measure(run: Run, env: dict[str, str], args, archive: bytes | None) -> None:
    with tempfile.TemporaryDirectory(prefix="bench-cluster-") as tmp:
        with environment({**env, "TELESPLAT_TORCH_THREADS": str(args.threads)}):
            proc, url, token = start_server(Path(tmp), 1, max(8, args.sessions + 2),
                                            args.avatar)
        try:
            if "TELESPLAT_RENDER_ACTORS" in env:
                wait_for_render_workers(url, token, int(env["TELESPLAT_RENDER_ACTORS"]))
            asyncio.run(sessions_at_once(url, token, 1, args.size, args.seconds, run))
            frames = asyncio.run(sessions_at_once(url, token, args.sessions, args.size,
                                                  args.seconds, None))
            run.fps.append(frames / args.seconds)
            if archive is not None:
                run.job_running_s, run.job_start_s = job_start(url, token, archive)
        finally:
            stop_server(proc)
    print(f"  {run.name}: done", file=sys.stderr)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--sessions", type=int, default=4)
    parser.add_argument("--threads", type=int, default=1,
                        help="torch threads of the local renderer / CPUs per render actor")
    parser.add_argument("--avatar", default="trained")
    parser.add_argument("--cpus", type=int, default=4, help="logical CPUs of the Ray head")
    parser.add_argument("--repeat", type=int, default=1,
                        help="rounds, the backends alternating (load drift shows as spread)")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory(prefix="bench-cluster-data-") as tmp:
        archive = tiny_capture(Path(tmp))
    runs = [Run("local"), Run("ray x1"), Run("ray x2")]
    with ray_cluster(num_cpus=args.cpus) as head:
        cluster = {**{k: v for k, v in head.env.items() if k.startswith(("RAY_", "PYTHON"))},
                   "TELESPLAT_CLUSTER_ADDRESS": head.address,
                   "TELESPLAT_RENDER_ACTOR_NUM_CPUS": str(args.threads)}
        envs = [{"TELESPLAT_RENDER_BACKEND": "local", "TELESPLAT_JOB_BACKEND": "local"}] + [
            {**cluster, "TELESPLAT_RENDER_BACKEND": "ray", "TELESPLAT_JOB_BACKEND": "ray",
             "TELESPLAT_RENDER_ACTORS": str(actors)} for actors in (1, 2)]
        for round_ in range(args.repeat):
            for run, env in zip(runs, envs, strict=True):
                jobs = round_ == 0 and run.name != "ray x2"  # a job backend each, once
                measure(run, env, args, archive if jobs else None)
    report(runs, args)
    return 0


def report(runs: list[Run], args) -> None:
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"\n{platform.node()}: {os.cpu_count()} cores, load {load:.1f}; {args.size} px JPEG, "
          f"avatar {args.avatar}, {args.threads} thread(s) per renderer, "
          f"{args.seconds:g} s per measurement, {args.repeat} round(s)\n")
    base = runs[0]
    print("| backend | frame ms (pose+render+encode, p50) | round trip p50 / p95 ms "
          "| gateway overhead p50 ms | % of frame | vs local |")
    print("|---|---|---|---|---|---|")
    for r in runs:
        stage, over = statistics.median(r.stage_ms), statistics.median(r.overhead_ms)
        extra = over - statistics.median(base.overhead_ms)
        print(f"| {r.name} | {stage:.1f} | {percentile(r.latency_ms, 50):.1f} / "
              f"{percentile(r.latency_ms, 95):.1f} | {over:.1f} | {100 * over / stage:.0f}% | "
              f"{'-' if r is base else f'{extra:+.1f} ms'} |")
    print(f"\n| backend | {args.sessions} sessions at once: frames/s in total, median "
          "(min-max over rounds) | vs local |")
    print("|---|---|---|")
    for r in runs:
        fps = statistics.median(r.fps)
        print(f"| {r.name} | {fps:.1f} ({min(r.fps):.1f}-{max(r.fps):.1f}) | "
              f"{fps / statistics.median(base.fps):.2f} |")
    print("\n| job backend | submit -> running s | submit -> first iteration s |")
    print("|---|---|---|")
    for r in runs:
        if r.job_start_s == r.job_start_s:  # measured
            print(f"| {r.name.split()[0]} | {r.job_running_s:.2f} | {r.job_start_s:.2f} |")


if __name__ == "__main__":
    raise SystemExit(main())
