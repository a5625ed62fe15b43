"""Carried wheels installed into a site folder (put on PYTHONPATH) without any registry.

``pip install --no-index --no-deps --target SITE`` of every wheel that fits this interpreter,
then each installed file gets the timestamp its wheel records: pip stamps them with the time of
the install, and a JIT-compiled extension's build (gsplat's, see gsplat_cache.py) would look
out of date against sources that are new on every run, and be compiled again. Standard library
and pip only: it runs before anything carried is importable.
"""

from __future__ import annotations

import calendar
import dataclasses
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

from gpu_wheels import wheel_name_version


@dataclasses.dataclass
class Installed:
    site: Path
    installed: list[str]  # "name version"
    left_out: list[str]  # "file: why"


def interpreter_tags() -> set[str]:
    """The wheel tags (py-abi-platform) this interpreter installs."""
    try:
        from packaging.tags import sys_tags
    except ImportError:  # pip vendors the same module
        from pip._vendor.packaging.tags import sys_tags
    return {str(tag) for tag in sys_tags()}


def wheel_tags(filename: str) -> set[str]:
    """Every py-abi-platform tag a wheel file name declares (dotted parts are alternatives)."""
    py, abi, plat = filename.removesuffix(".whl").split("-")[-3:]
    return {f"{p}-{a}-{pl}" for p in py.split(".") for a in abi.split(".")
            for pl in plat.split(".")}


def duplicates(wheels: list[Path]) -> list[str]:
    """Projects with more than one wheel: pip refuses the whole install then."""
    seen: dict[str, list[str]] = {}
    for wheel in wheels:
        seen.setdefault(wheel_name_version(wheel.name)[0], []).append(wheel.name)
    return [", ".join(names) for names in seen.values() if len(names) > 1]


def stamp_from_wheels(wheels: list[Path], site: Path) -> int:
    """Give each installed file the time its wheel records for it (UTC, as recorded: the same
    on every run). Returns how many files were stamped."""
    count = 0
    for wheel in wheels:
        with zipfile.ZipFile(wheel) as archive:
            for info in archive.infolist():
                path = site / info.filename
                if info.is_dir() or not path.is_file():
                    continue  # pip's own files (RECORD, INSTALLER), .data/ moved elsewhere
                when = calendar.timegm((*info.date_time, 0, 0, 0))
                os.utime(path, (when, when))
                count += 1
    return count


def install(wheel_dir: Path, site: Path, *, lenient: bool) -> Installed:
    """A fresh ``site`` holding every wheel of ``wheel_dir`` that fits this interpreter.

    ``lenient`` (the CPU dry run): a wheel built for another Python or platform is left out
    and said so; otherwise it is an error, as are two versions of one project and a folder
    with no wheel."""
    wheels = sorted(wheel_dir.glob("*.whl"))
    if not wheels:
        raise RuntimeError(f"no wheels in {wheel_dir}: run `make gpu-wheels` where the package "
                           "registry is reachable, and carry the folder")
    twice = duplicates(wheels)
    if twice:
        raise RuntimeError("two versions of one project (pip would refuse all): "
                           + "; ".join(twice))
    tags = interpreter_tags()
    fits = [w for w in wheels if wheel_tags(w.name) & tags]
    misfits = [w for w in wheels if w not in fits]
    tag = f"cp{sys.version_info.major}{sys.version_info.minor}"
    left_out = [f"{w.name}: built for another Python or platform (this is {tag})"
                for w in misfits]
    if misfits and not lenient:
        raise RuntimeError("; ".join(left_out))
    shutil.rmtree(site, ignore_errors=True)
    site.mkdir(parents=True)
    if fits:
        subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-index",
                        "--no-deps", "--no-compile", "--no-cache-dir",
                        "--disable-pip-version-check", "--target", str(site),
                        *map(str, fits)], check=True)
    stamp_from_wheels(fits, site)
    return Installed(site, [" ".join(wheel_name_version(w.name)) for w in fits], left_out)
