"""A real local Ray cluster for tests: one ``ray start --head`` per test module, on 127.0.0.1.

    from tests.ray_cluster import ray_cluster_fixture, requires_ray

    pytestmark = requires_ray
    ray_head = ray_cluster_fixture(num_cpus=4)     # module-scoped fixture -> RayHead

    def test_x(ray_head):
        ray_head.address        # "127.0.0.1:PORT", for Settings(cluster_address=...)
        ray_head.env            # environment for a server subprocess that connects to it

The head runs in a session of its own and is torn down by killing THAT session's processes
(never ``ray stop``, which would stop every cluster on the machine, another test module's).
Ray workers run the worktree's code: the head is started with PYTHONPATH = the repository.
Ray 2.60 turns token auth on by default: the head gets ``RAY_AUTH_MODE=token`` and the token
Ray keeps in ``~/.ray/auth_token`` (made by Ray's own CLI if missing), which a client in this
process or in a subprocess with ``env`` reads the same way.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from server import cluster
from server.cluster import available

REPO = Path(__file__).resolve().parents[1]
START_TIMEOUT_S = 90.0  # a busy 2-core machine: the GCS + raylet take a few seconds
STOP_TIMEOUT_S = 15.0
OBJECT_STORE_BYTES = 96 * 2**20

requires_ray = pytest.mark.skipif(not available(),
                                  reason="ray is not installed (pip install 'telesplat[cluster]')")


@dataclass
class RayHead:
    address: str
    process: subprocess.Popen
    temp_dir: Path
    env: dict[str, str] = field(default_factory=dict)


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _ray_cli() -> str:
    beside = Path(sys.executable).with_name("ray")
    return str(beside) if beside.exists() else (shutil.which("ray") or "ray")


def cluster_env() -> dict[str, str]:
    """Environment for the head and for subprocesses that connect to it."""
    env = dict(os.environ)
    paths = [str(REPO), *filter(None, env.get("PYTHONPATH", "").split(os.pathsep))]
    env["PYTHONPATH"] = os.pathsep.join(dict.fromkeys(paths))
    env["RAY_AUTH_MODE"] = "token"
    env["RAY_USAGE_STATS_ENABLED"] = "0"
    # Ray's workers would otherwise start with every core's worth of threads each.
    env.setdefault("OMP_NUM_THREADS", "1")
    env.setdefault("NUMBA_NUM_THREADS", "1")
    return env


def _ensure_token(env: dict[str, str]) -> None:
    # Ray's CLI makes ~/.ray/auth_token only when there is none; the token is never printed here.
    subprocess.run([_ray_cli(), "get-auth-token", "--generate"], env=env, check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=60)


def _accepting(port: int) -> bool:
    with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 0.5):
        return True
    return False


def session_pids(sid: int) -> list[int]:
    """Live processes of session ``sid``: the head and everything it started. Ray's workers put
    themselves in process groups of their own, but stay in the session."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        with contextlib.suppress(OSError, ValueError, IndexError):
            # Fields after the ")" closing the command name: state, ppid, pgrp, session.
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            if int(fields[3]) == sid and fields[0] != "Z":  # zombies hold nothing
                pids.append(int(entry.name))
    return pids


def _stop(proc: subprocess.Popen) -> None:
    # `ray start --block` does not exit on SIGTERM in bounded time (measured: > 30 s), and a
    # SIGKILL of its group leaves the workers: kill the whole session, which is this head's.
    for pid in session_pids(proc.pid):
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, signal.SIGKILL)
    with contextlib.suppress(subprocess.TimeoutExpired):
        proc.wait(STOP_TIMEOUT_S)


@contextlib.contextmanager
def ray_cluster(num_cpus: int = 4, num_gpus: int = 0,
                object_store_bytes: int = OBJECT_STORE_BYTES) -> Iterator[RayHead]:
    """Start a head on a free port (``num_cpus`` logical CPUs, oversubscribing the machine is
    fine for tests), wait until it accepts connections and a client can attach, yield it,
    then kill its process group."""
    env = cluster_env()
    _ensure_token(env)
    port = _free_port()
    # Ray's socket paths must stay short (AF_UNIX, 107 bytes): /tmp, not pytest's tmp_path.
    temp_dir = Path(tempfile.mkdtemp(prefix="tsray", dir="/tmp"))
    cmd = [_ray_cli(), "start", "--head", "--block", "--node-ip-address=127.0.0.1",
           f"--port={port}", f"--num-cpus={num_cpus}", f"--num-gpus={num_gpus}",
           "--include-dashboard=false", f"--object-store-memory={object_store_bytes}",
           f"--temp-dir={temp_dir}", "--disable-usage-stats"]
    log = open(temp_dir / "head.log", "wb")  # noqa: SIM115 (closed below)
    proc = subprocess.Popen(cmd, env=env, cwd=REPO, start_new_session=True,
                            stdout=log, stderr=subprocess.STDOUT)
    head = RayHead(address=f"127.0.0.1:{port}", process=proc, temp_dir=temp_dir, env=env)
    try:
        deadline = time.monotonic() + START_TIMEOUT_S
        while not _ready(head):
            if proc.poll() is not None:
                raise RuntimeError(f"ray start exited {proc.returncode}: "
                                   f"{(temp_dir / 'head.log').read_text()[-2000:]}")
            if time.monotonic() > deadline:
                raise TimeoutError(f"Ray head not ready after {START_TIMEOUT_S} s")
            time.sleep(0.25)
        yield head
    finally:
        cluster.shutdown()  # this process's connection to it, if a test made one
        _stop(proc)
        log.close()
        shutil.rmtree(temp_dir, ignore_errors=True)


def _ready(head: RayHead) -> bool:
    """The GCS port accepts, and the raylet has registered the node (``ray status`` sees it)."""
    port = int(head.address.rsplit(":", 1)[1])
    if not _accepting(port):
        return False
    probe = subprocess.run(
        [sys.executable, "-c",
         "import ray, sys; ray.init(address=sys.argv[1], log_to_driver=False); "
         "sys.exit(0 if ray.cluster_resources().get('CPU', 0) > 0 else 1)", head.address],
        env=head.env, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        timeout=START_TIMEOUT_S)
    return probe.returncode == 0


def ray_cluster_fixture(num_cpus: int = 4, num_gpus: int = 0, **kwargs):
    """A module-scoped pytest fixture yielding a :class:`RayHead`."""

    @pytest.fixture(scope="module")
    def ray_head() -> Iterator[RayHead]:
        with ray_cluster(num_cpus=num_cpus, num_gpus=num_gpus, **kwargs) as head:
            yield head

    return ray_head
