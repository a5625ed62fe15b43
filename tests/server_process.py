"""A real Telesplat server as a subprocess (``python -m server``), for tests that restart it:
SIGTERM (graceful: participants are told ``restarting``) or SIGKILL (nothing told), then the
same port and data dir again.

    with ServerProcess(tmp_path) as srv:     # started; srv.url, srv.token, srv.links
        ...
        srv.stop(signal.SIGKILL)             # or SIGTERM (the default)
        srv.start()                          # same port, same data dir, same admin token

Every wait is bounded; what the server prints is kept (``srv.output``) for failure messages.
"""

from __future__ import annotations

import collections
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
START_TIMEOUT_S = 180.0  # a cold start compiles numba kernels (cached afterwards)
STOP_TIMEOUT_S = 30.0
SERVING = re.compile(r"serving at (http://[^/\s]+)/[?#]token=(\S+)")
LINK = re.compile(r"^\s+(watch|perform) link: (\S+)")


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class ServerProcess:
    def __init__(self, data_dir: Path, port: int | None = None, **settings: Any) -> None:
        """``settings``: server settings as TELESPLAT_* variables (e.g. default_width=128)."""
        self.data_dir = data_dir
        self.port = port or free_port()
        self.env = {**os.environ, "PYTHONUNBUFFERED": "1", "TELESPLAT_TORCH_THREADS": "1",
                    **{f"TELESPLAT_{k.upper()}": str(v) for k, v in settings.items()}}
        self.proc: subprocess.Popen | None = None
        self.url = f"http://127.0.0.1:{self.port}"
        self.token: str | None = None
        self.links: dict[str, str] = {}
        self.output: collections.deque[str] = collections.deque(maxlen=200)
        self.started_at: float | None = None  # monotonic: when it printed its URL

    def start(self) -> ServerProcess:
        self.links, self.token = {}, None
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "server", "--port", str(self.port), "--data-dir",
             str(self.data_dir), "--demo-avatar", "synthetic", "--log-level", "warning"],
            cwd=ROOT, env=self.env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            text=True)
        ready = threading.Event()
        threading.Thread(target=self._pump, args=(self.proc, ready), daemon=True,
                         name=f"server-{self.port}-output").start()
        if not ready.wait(START_TIMEOUT_S) or self.token is None:
            self.stop(signal.SIGKILL)
            raise RuntimeError("the server did not start:\n" + "".join(self.output))
        return self

    def _pump(self, proc: subprocess.Popen, ready: threading.Event) -> None:
        """Read what the server prints (so its pipe never fills) until it exits."""
        links = str(self.env.get("TELESPLAT_STARTUP_ROOM", "true")).lower() != "false"
        for line in proc.stdout:  # ends when the process does
            self.output.append(line)
            found = SERVING.search(line)
            if found:
                self.token = found.group(2)
                self.started_at = time.monotonic()
            link = LINK.search(line)
            if link:
                self.links[link.group(1)] = link.group(2)
            if self.token is not None and (not links or len(self.links) == 2):
                ready.set()
        ready.set()

    def stop(self, sig: int = signal.SIGTERM) -> int | None:
        """Signal it and wait for it to exit; its exit status."""
        if self.proc is None or self.proc.poll() is not None:
            return None if self.proc is None else self.proc.returncode
        self.proc.send_signal(sig)
        try:
            return self.proc.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(STOP_TIMEOUT_S)
            raise RuntimeError(f"the server ignored signal {sig}:\n" + "".join(self.output)) \
                from None

    def headers(self, token: str | None = None) -> dict[str, str]:
        return {"Authorization": f"Bearer {token or self.token}"}

    def __enter__(self) -> ServerProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop(signal.SIGKILL)
