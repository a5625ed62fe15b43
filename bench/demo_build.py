"""The trained demo's background build on a busy machine: capture and training throughput.

Each case runs one stage the way the server runs it, for ``--window`` seconds after its first
progress report, and reports its rate and the whole stage's time at that rate:

    capture  ``python -m avatar_core.demo capture`` with the command and environment the
             server gives it (server/jobs/demo_build.py ``capture_process``: ``job_nice``,
             ``job_threads``, passive pools), the default recipe, into a fresh folder;
    train    ``python -m server.jobs.run`` (the job worker's command and environment) on a
             small dataset of the default recipe's cameras and resolution (filmed once
             first), the demo preset: iterations per second.

Cases: every combination of ``--stages``, ``--hog`` (busy-loop processes beside it),
``--nice`` and ``--threads``. ``--hog-session`` puts the busy loops in a session of their
own (``own``: other work on the machine, e.g. another terminal) or in this process's session
(``same``: as if started beside the server); ``--build-session`` likewise for the stage's
process (``same``: the server's session, where the capture runs; ``own``: a session of its
own). Linux's autogroup scheduling (``/proc/sys/kernel/sched_autogroup_enabled``) shares the
CPU between sessions first and applies ``nice`` only within a session, so these matter.

    .venv/bin/python bench/demo_build.py [--window 45] [--stages capture,train] \\
        [--hog 0,2] [--nice 0,10] [--threads 1,2] [--hog-session own|same] \\
        [--build-session same|own]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from types import SimpleNamespace

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from avatar_core.demo import DemoRecipe  # noqa: E402
from avatar_core.studio_entry import demo_build_plan  # noqa: E402
from bench.waitpolicy import hogs  # noqa: E402
from server.auth import PUBLIC_OWNER  # noqa: E402
from server.jobs.demo_build import DEMO_DATASET, capture_process  # noqa: E402
from server.jobs.service import JobService  # noqa: E402
from server.jobs.worker import WorkerConfig  # noqa: E402

TRAIN_DATASET_FRAMES = 3  # per sequence: the iteration rate does not depend on the count


def _stop(process: subprocess.Popen) -> None:
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(timeout=15)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def _rate(points: list[tuple[float, int]]) -> float | None:
    """Units per second between the first and the last report."""
    if len(points) < 2 or points[-1][0] <= points[0][0]:
        return None
    return (points[-1][1] - points[0][1]) / (points[-1][0] - points[0][0])


def run_capture(settings, window: float, own_session: bool, tmp: Path) -> dict:
    root = Path(tempfile.mkdtemp(dir=tmp, prefix="capture-"))
    plan = demo_build_plan(root)
    command, env = capture_process(settings, plan.capture_command)
    points: list[tuple[float, int]] = []
    total = [0]
    start = time.monotonic()
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                               stdin=subprocess.DEVNULL, env=env, text=True,
                               start_new_session=own_session)

    def read() -> None:
        for line in process.stdout:
            with contextlib.suppress(ValueError):
                event = json.loads(line)
                if event.get("stage") == "capture":
                    points.append((time.monotonic(), int(event["done"])))
                    total[0] = int(event["total"])

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    deadline = start + window + 600  # its start-up (imports, kernels) is not in the window
    try:
        while time.monotonic() < deadline and process.poll() is None:
            if points and points[-1][0] - points[0][0] >= window:
                break
            time.sleep(0.2)
    finally:
        _stop(process)
    reader.join(timeout=5)
    rate = _rate(points)
    return {"unit": "views/s", "rate": rate, "total": total[0],
            "first_s": points[0][0] - start if points else None,
            "stage_s": total[0] / rate if rate else None,
            "pct_per_min": 100 * 60 * rate / total[0] if rate and total[0] else None}


def small_dataset(tmp: Path) -> Path:
    """The default recipe's cameras and resolution, TRAIN_DATASET_FRAMES frames each."""
    root = tmp / "train-data"
    recipe = {"frames": TRAIN_DATASET_FRAMES}
    plan = demo_build_plan(root, recipe)
    if not (plan.dataset / "dataset.json").is_file():
        subprocess.run(plan.capture_command, check=True, stdout=subprocess.DEVNULL)
    return plan.dataset


def run_train(settings, window: float, own_session: bool, tmp: Path, dataset: Path) -> dict:
    data = Path(tempfile.mkdtemp(dir=tmp, prefix="jobs-"))
    service = JobService(data, lambda job, package: "unused", worker=WorkerConfig(
        threads=settings.job_threads, nice=settings.job_nice))
    config = demo_build_plan(tmp / "unused", None).config
    job = service.submit_prepared(PUBLIC_OWNER, DEMO_DATASET, dataset, config)
    claimed = service.store.claim_next()
    assert claimed is not None and claimed.id == job.id
    worker = service.worker
    folder = worker.job_dir(job.id)
    folder.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()
    with open(folder / "bench-log.txt", "wb") as logf:
        process = subprocess.Popen(worker._command(claimed), stdout=logf,
                                   stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                   env=worker._env(), cwd=folder,
                                   start_new_session=own_session)
        points: list[tuple[float, int]] = []
        deadline = start + window + 600
        try:
            while time.monotonic() < deadline and process.poll() is None:
                it = service.store.get(job.id).iteration
                if it and (not points or it != points[-1][1]):
                    points.append((time.monotonic(), it))
                if points and points[-1][0] - points[0][0] >= window:
                    break
                time.sleep(0.25)
        finally:
            _stop(process)
            service.store.close()
    rate = _rate(points)
    total = config["iterations"]
    return {"unit": "it/s", "rate": rate, "total": total,
            "first_s": points[0][0] - start if points else None,
            "stage_s": total / rate if rate else None,
            "pct_per_min": 100 * 60 * rate / total if rate else None}


def _ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x.strip()]


def _exit_on_term() -> None:
    """SIGTERM unwinds like Ctrl-C: the busy loops and the stage's process are stopped."""
    def raise_interrupt(signum, frame):
        raise KeyboardInterrupt
    signal.signal(signal.SIGTERM, raise_interrupt)


def main() -> None:
    _exit_on_term()
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--window", type=float, default=45.0, help="seconds of each stage timed")
    ap.add_argument("--stages", default="capture,train")
    ap.add_argument("--hog", default="0,2", help="busy-loop counts, comma-separated")
    ap.add_argument("--nice", default="0,10", help="job_nice values, comma-separated")
    ap.add_argument("--threads", default="1,2", help="job_threads values, comma-separated")
    ap.add_argument("--hog-session", choices=["own", "same"], default="own")
    ap.add_argument("--build-session", choices=["same", "own"], default="same")
    ap.add_argument("--out", type=Path, default=None, help="also write the rows as JSON")
    args = ap.parse_args()
    stages = [s for s in args.stages.split(",") if s]
    unknown = set(stages) - {"capture", "train"}
    if unknown:
        ap.error(f"unknown stage(s) {sorted(unknown)}")
    rows = []
    print(f"default recipe: {DemoRecipe()}; autogroup "
          f"{Path('/proc/sys/kernel/sched_autogroup_enabled').read_text().strip()}; "
          f"hogs' session {args.hog_session}, build's session {args.build_session}")
    print("| stage | hogs | job_nice | job_threads | rate | whole stage at that rate | "
          "% per min | load avg |\n|---|---:|---:|---:|---:|---:|---:|---:|", flush=True)
    with tempfile.TemporaryDirectory(prefix="bench-demo-build-") as tmp_name:
        tmp = Path(tmp_name)
        dataset = small_dataset(tmp) if "train" in stages else None
        for stage in stages:
            for hog in _ints(args.hog):
                for nice in _ints(args.nice):
                    for threads in _ints(args.threads):
                        settings = SimpleNamespace(job_nice=nice, job_threads=threads)
                        own = args.build_session == "own"
                        with hogs(hog, args.hog_session == "own"):
                            if stage == "capture":
                                row = run_capture(settings, args.window, own, tmp)
                            else:
                                row = run_train(settings, args.window, own, tmp, dataset)
                        row.update(stage=stage, hogs=hog, nice=nice, threads=threads,
                                   load=os.getloadavg()[0], hog_session=args.hog_session,
                                   build_session=args.build_session)
                        rows.append(row)
                        rate = f"{row['rate']:.2f} {row['unit']}" if row["rate"] else "-"
                        whole = f"{row['stage_s'] / 60:.1f} min" if row["stage_s"] else "-"
                        pct = f"{row['pct_per_min']:.1f}" if row["pct_per_min"] else "-"
                        print(f"| {stage} | {hog} | {nice} | {threads} | {rate} | {whole} | "
                              f"{pct} | {row['load']:.1f} |", flush=True)
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
