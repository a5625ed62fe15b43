"""gsplat's JIT-compiled CUDA extension, kept between runs of the offline GPU check.

gsplat 1.5.3's wheel compiles its kernels on first use with torch's ``cpp_extension`` into
``$TORCH_EXTENSIONS_DIR/gsplat_cuda`` (ninja, ``MAX_JOBS`` jobs, for the archs in
``TORCH_CUDA_ARCH_LIST``). A later process with the same sources, flags and paths finds ninja
with nothing to do and loads the built module at once. So the check points
``TORCH_EXTENSIONS_DIR`` at a cache folder (kept on a warm machine), records what the build
depends on next to it (the key), wipes it when that changed, and returns it packed as one
archive that a later run can be given. Standard library only.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tarfile
from pathlib import Path

BUILD = "gsplat_cuda"  # gsplat's extension name, the build folder's name
KEY_FILE = "telesplat-cache-key.json"
ARCHIVE = "gsplat-cache.tar.gz"
# The device tool returns files of at most 16 MiB; a bigger archive stays on the machine.
RETURN_LIMIT_BYTES = 16 * 1024 * 1024


def gpu_arch() -> str | None:
    """The first GPU's compute capability ("9.0" on an H100), from nvidia-smi."""
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=compute_cap", "--format=csv,noheader"],
                             capture_output=True, text=True, timeout=30, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    first = out.strip().splitlines()[0].strip() if out.strip() else ""
    return first or None


def nvcc_version(nvcc: str | None) -> str | None:
    """nvcc's release line, or None where there is no nvcc (gsplat then cannot compile)."""
    if not nvcc:
        return None
    try:
        out = subprocess.run([nvcc, "--version"], capture_output=True, text=True,
                             timeout=30, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    lines = [line for line in out.splitlines() if "release" in line]
    return lines[-1].strip() if lines else out.strip() or None


def build_env(cache_dir: Path, arch: str | None, jobs: int | None = None) -> dict[str, str]:
    """The variables every process of the check gets, so all load the one build: the cache
    folder, this GPU's arch only (one arch compiles several times faster than torch's list),
    every core for ninja."""
    env = {"TORCH_EXTENSIONS_DIR": str(cache_dir), "MAX_JOBS": str(jobs or os.cpu_count() or 1)}
    if arch:
        env["TORCH_CUDA_ARCH_LIST"] = arch
    return env


def built(cache_dir: Path) -> bool:
    return (cache_dir / BUILD / f"{BUILD}.so").is_file()


def read_key(cache_dir: Path) -> dict | None:
    try:
        return json.loads((cache_dir / KEY_FILE).read_text())
    except (OSError, ValueError):
        return None


def prepare(cache_dir: Path, key: dict, archive: Path | None = None) -> str:
    """Make ``cache_dir`` hold a build for ``key`` or nothing, and say which: "hit" (a build
    for this key is there), "restored" (unpacked from ``archive``), else "miss" (compile)."""
    cache_dir.mkdir(parents=True, exist_ok=True)
    if read_key(cache_dir) == key and built(cache_dir):
        return "hit"
    clear(cache_dir)
    if archive is not None and archive.is_file():
        unpack(archive, cache_dir)
        if read_key(cache_dir) == key and built(cache_dir):
            return "restored"
        clear(cache_dir)
    return "miss"


def unpack(archive: Path, cache_dir: Path) -> None:
    """Extract a packed build with each file's time rounded down to its second. Ninja keeps
    nanosecond times of what it built (.ninja_log, .ninja_deps) and rebuilds an object whose
    time on disk is later than the one it recorded; the archive's times are floats, which can
    come back a fraction of a microsecond later. Earlier, never later, keeps the build valid:
    its sources are older still (they carry their wheel's timestamps)."""
    with tarfile.open(archive) as tar:
        members = tar.getmembers()
        tar.extractall(cache_dir, members=members, filter="data")
    for member in members:
        path = cache_dir / member.name
        if member.isfile() and path.is_file():
            second = int(member.mtime) * 1_000_000_000
            os.utime(path, ns=(second, second))


def clear(cache_dir: Path) -> None:
    shutil.rmtree(cache_dir / BUILD, ignore_errors=True)
    (cache_dir / KEY_FILE).unlink(missing_ok=True)


def remember(cache_dir: Path, key: dict) -> None:
    (cache_dir / KEY_FILE).write_text(json.dumps(key, indent=1, sort_keys=True) + "\n")


def pack(cache_dir: Path, out: Path) -> tuple[Path | None, str]:
    """The build and its key as one archive in ``out`` (what the device tool can return),
    or None and why not."""
    if not built(cache_dir):
        return None, "no build to pack"
    archive = out / ARCHIVE
    with tarfile.open(archive, "w:gz", compresslevel=6) as tar:
        tar.add(cache_dir / KEY_FILE, arcname=KEY_FILE)
        tar.add(cache_dir / BUILD, arcname=BUILD)
    size = archive.stat().st_size
    if size > RETURN_LIMIT_BYTES:
        archive.unlink()
        return None, (f"the packed build is {size / 2**20:.1f} MiB, over the 16 MiB a file the "
                      f"device tool returns; it stays in {cache_dir}")
    return archive, f"{size / 2**20:.1f} MiB"
