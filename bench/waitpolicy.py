"""CPU hogs and the thread-wait comparison shared by bench/train.py and bench/render.py.

``--hog N`` starts N busy-loop processes (one per core stands for "a busy machine"), each
bounded: it exits when this process is gone or after ``HOG_MAX_S``, and is stopped when the
bench ends. ``--wait-compare`` measures the bench's one-case workload in child processes (the
OpenMP wait policy is read when torch loads, so each setting needs a fresh process) at 1 and
2 threads with ``OMP_WAIT_POLICY=ACTIVE`` (spin, the libgomp default's behaviour) and
``PASSIVE`` (what avatar_core/threads.py sets), all beside the same hogs, in interleaved
passes (the order alternates) so that the machine's noise hits every setting alike.
"""

from __future__ import annotations

import contextlib
import json
import os
import statistics
import subprocess
import sys
from collections.abc import Iterator

HOG_MAX_S = 3600.0
RESULT = "WAITCOMPARE "
_HOG = (
    "import os, time\n"
    "parent, end = os.getppid(), time.monotonic() + {max_s}\n"
    "while os.getppid() == parent and time.monotonic() < end:\n"
    "    for _ in range(200000):\n"
    "        pass\n"
)


@contextlib.contextmanager
def hogs(n: int, own_session: bool = False) -> Iterator[list[subprocess.Popen]]:
    """``n`` busy-loop processes for the duration of the block; ``own_session``: each in a
    session of its own (Linux's autogroup scheduling then shares the CPU with them as with
    other users' programs, and ``nice`` values here do not count against them)."""
    procs = [subprocess.Popen([sys.executable, "-c", _HOG.format(max_s=HOG_MAX_S)],
                              start_new_session=own_session) for _ in range(max(0, n))]
    try:
        yield procs
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def child_env(threads: int, policy: str) -> dict[str, str]:
    env = dict(os.environ)
    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        env[name] = str(threads)
    env["OMP_WAIT_POLICY"] = policy
    env.pop("KMP_BLOCKTIME", None)  # the policy alone decides (libgomp ignores it anyway)
    return env


def report(value: float, unit: str) -> None:
    """A child's result line, read by :func:`compare`."""
    print(RESULT + json.dumps({"value": value, "unit": unit}), flush=True)


def compare(argv: list[str], *, passes: int, hog: int, threads=(1, 2),
            policies=("ACTIVE", "PASSIVE"), timeout_s: float = 900.0) -> str:
    """Run ``python argv... --wait-child`` per (threads, policy), ``passes`` times
    interleaved, beside ``hog`` busy loops; a markdown table of medians."""
    settings = [(t, p) for t in threads for p in policies]
    values: dict[tuple[int, str], list[float]] = {s: [] for s in settings}
    unit = ""
    with hogs(hog):
        for i in range(passes):
            order = settings if i % 2 == 0 else settings[::-1]
            for t, p in order:
                out = subprocess.run([sys.executable, *argv, "--wait-child"],
                                     env=child_env(t, p), capture_output=True, text=True,
                                     timeout=timeout_s)
                line = next((ln for ln in out.stdout.splitlines() if ln.startswith(RESULT)),
                            None)
                if out.returncode != 0 or line is None:
                    raise RuntimeError(f"child ({t} threads, {p}) failed:\n{out.stderr[-3000:]}")
                got = json.loads(line[len(RESULT):])
                values[(t, p)].append(got["value"])
                unit = got["unit"]
                print(f"  pass {i + 1}: {t} thread(s), {p}: {got['value']:.2f} {unit}",
                      flush=True)
    rows = [f"| threads | OMP_WAIT_POLICY | {unit} (median of {passes}) | range | "
            "PASSIVE vs ACTIVE |", "|---:|---|---:|---:|---:|"]
    for t in threads:
        base = statistics.median(values[(t, policies[0])])
        for p in policies:
            v = values[(t, p)]
            med = statistics.median(v)
            rows.append(f"| {t} | {p} | **{med:.2f}** | {min(v):.2f}-{max(v):.2f} | "
                        f"{med / base:.2f}x |")
    return "\n".join(rows)
