"""Files only the server's user may read: folders 0700, files 0600.

The data dir holds tokens, uploaded datasets, avatars and logs; making it 0700 is what keeps
other local users out of everything below it, and what the server creates below it is made
private too (a copied or moved data dir keeps that).
"""

from __future__ import annotations

import logging
import os
import stat
from pathlib import Path

__all__ = ["make_private", "private_dir"]

log = logging.getLogger("telesplat.server")


def private_dir(path: str | Path) -> Path:
    """``path`` created if missing (parents too) and set to 0700 (a folder of another user's
    that we may use but not chmod is kept as it is, with a warning)."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True, mode=0o700)
    try:
        os.chmod(path, 0o700)
    except PermissionError:
        mode = stat.S_IMODE(path.stat().st_mode)
        log.warning("%s is not ours to make private (mode %o): other users may read it",
                    path, mode)
    return path


def make_private(path: str | Path) -> None:
    """Folders 0700 and files 0600 from ``path`` down (symlinks left alone)."""
    os.chmod(path, 0o700)
    for folder, dirs, files in os.walk(path):
        for name in dirs:
            os.chmod(os.path.join(folder, name), 0o700)
        for name in files:
            full = os.path.join(folder, name)
            if not os.path.islink(full):
                os.chmod(full, 0o600)
