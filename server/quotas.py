"""Per-user storage quotas: how many avatars a user owns and how many bytes they store.

A user's stored bytes are their avatars' packages plus their jobs' folders (an uploaded
dataset, checkpoints, the log) while those exist. Uploads are checked before they are
accepted: an avatar past the count is 429 (like the job quotas), anything past the bytes 413.
Admins are exempt. Two uploads racing each other can overshoot by one upload.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from fastapi import HTTPException

__all__ = ["check_avatar_quota", "dir_size", "storage_left", "stored_bytes"]

MAX_JOBS_COUNTED = 10_000  # the job store caps jobs per user far below this


def dir_size(path: Path) -> int:
    """Bytes of the regular files under ``path`` (0 when it is gone); symlinks not followed."""
    total = 0
    for folder, _, files in os.walk(path):
        for name in files:
            try:
                st = os.lstat(os.path.join(folder, name))
            except OSError:  # removed while we walk
                continue
            total += st.st_size
    return total


def stored_bytes(owner: str, registry: Any, jobs: Any | None) -> int:
    """The owner's avatars plus their jobs' folders, in bytes."""
    total = sum(r.size_bytes for r in registry.list(owner))
    if jobs is not None:
        for job in jobs.store.list(owner=owner, limit=MAX_JOBS_COUNTED):
            total += dir_size(jobs.worker.job_dir(job.id))
    return total


def storage_left(owner: str, settings: Any, registry: Any, jobs: Any | None) -> int:
    """Bytes ``owner`` may still store (negative when already over)."""
    return settings.max_stored_bytes_per_user - stored_bytes(owner, registry, jobs)


def check_avatar_quota(owner: str, incoming_bytes: int, settings: Any, registry: Any,
                       jobs: Any | None) -> None:
    """HTTPException 429 when ``owner`` has all the avatars allowed, 413 when
    ``incoming_bytes`` more would pass their storage quota."""
    count = len(registry.list(owner))
    if count >= settings.max_avatars_per_user:
        raise HTTPException(429, f"avatar quota reached: you own {count} avatars, the limit "
                                 f"is {settings.max_avatars_per_user}; delete some first")
    left = storage_left(owner, settings, registry, jobs)
    if incoming_bytes > left:
        raise HTTPException(413, f"storage quota exceeded: this avatar takes {incoming_bytes} "
                                 f"bytes and {max(0, left)} of your "
                                 f"{settings.max_stored_bytes_per_user} are left")
