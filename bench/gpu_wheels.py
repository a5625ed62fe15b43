"""The wheels that an offline CUDA machine needs for the GPU check (``make gpu-wheels``).

    python bench/gpu_wheels.py [--list requirements-gpu-offline.txt] [--dest .whl]
                               [--python-version 3.12] [--limit-mib 60]

Downloads each pinned line of the list alone (``pip download --no-deps``: nothing is pulled
implicitly) as a binary wheel for CPython on x86-64 Linux, into a fresh folder that then
replaces ``--dest``; then checks that the folder holds exactly one wheel per line at its pinned
version, and that it stays under ``--limit-mib`` and, with the repository's tree, under what
the device tool carries (64 MiB). Standard library only (and pip, run as a program).
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MIB = 1024 * 1024
CARRY_LIMIT_MIB = 64  # what the device tool carries: the working tree plus carried paths
# torch 2.11's own wheels need glibc 2.28, so a machine that runs it takes manylinux up to that.
PLATFORMS = ("manylinux1_x86_64", "manylinux2010_x86_64", "manylinux2014_x86_64",
             *(f"manylinux_2_{n}_x86_64" for n in range(5, 29)))


@dataclasses.dataclass(frozen=True)
class Pin:
    name: str  # normalised (PEP 503)
    version: str
    reason: str

    @property
    def spec(self) -> str:
        return f"{self.name}=={self.version}"


def normalise(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def read_pins(path: Path) -> list[Pin]:
    """``name==version  # reason`` per line; every line pinned and explained, no name twice."""
    pins: dict[str, Pin] = {}
    for number, raw in enumerate(path.read_text().splitlines(), 1):
        line, _, reason = raw.partition("#")
        line, reason = line.strip(), reason.strip()
        if not line:
            continue
        m = re.fullmatch(r"([A-Za-z0-9][A-Za-z0-9._-]*)==([A-Za-z0-9.+!-]+)", line)
        if m is None:
            raise ValueError(f"{path}:{number}: not 'name==version': {line!r}")
        if not reason:
            raise ValueError(f"{path}:{number}: {line} has no reason (a '# why' comment)")
        pin = Pin(normalise(m[1]), m[2], reason)
        if pin.name in pins:
            raise ValueError(f"{path}:{number}: {pin.name} is listed twice")
        pins[pin.name] = pin
    return list(pins.values())


def wheel_name_version(filename: str) -> tuple[str, str]:
    """(normalised project name, version) of a wheel file name."""
    parts = filename.removesuffix(".whl").split("-")
    if len(parts) not in (5, 6) or not filename.endswith(".whl"):
        raise ValueError(f"not a wheel file name: {filename}")
    return normalise(parts[0]), parts[1]


def check_folder(folder: Path, pins: list[Pin], limit_mib: float) -> list[tuple[str, int]]:
    """The folder's wheels as (file, bytes), after checking it holds one wheel per pin at its
    version, nothing else, and at most ``limit_mib``; raises ValueError saying what is off."""
    wheels = sorted(folder.glob("*.whl"))
    found: dict[str, list[str]] = {}
    for wheel in wheels:
        name, version = wheel_name_version(wheel.name)
        found.setdefault(name, []).append(version)
    problems = [f"{name}: {len(v)} versions ({', '.join(v)}); pip installs only one"
                for name, v in found.items() if len(v) > 1]
    wanted = {p.name: p for p in pins}
    problems += [f"{name} is not in the list (pulled implicitly?)"
                 for name in found if name not in wanted]
    problems += [f"{p.spec} is missing" for p in pins if p.name not in found]
    problems += [f"{p.name}: {found[p.name][0]} instead of {p.version}" for p in pins
                 if p.name in found and len(found[p.name]) == 1
                 and found[p.name][0] != p.version]
    sizes = [(w.name, w.stat().st_size) for w in wheels]
    total = sum(size for _, size in sizes)
    if total > limit_mib * MIB:
        problems.append(f"{total / MIB:.1f} MiB of wheels, over the {limit_mib:g} MiB limit")
    if problems:
        raise ValueError("; ".join(problems))
    return sizes


def tree_bytes(root: Path) -> int:
    """What the device tool carries of the repository: tracked files and untracked ones that
    git does not ignore."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others",
                             "--exclude-standard"], cwd=root, capture_output=True,
                            check=True).stdout
    paths = {p for p in listed.decode().split("\0") if p}
    return sum((root / p).stat().st_size for p in paths if (root / p).is_file())


def download(pins: list[Pin], dest: Path, python_version: str) -> None:
    """Fetch the pinned wheels into a fresh folder and put it in place of ``dest``."""
    abi = "cp" + python_version.replace(".", "")
    dest.parent.mkdir(parents=True, exist_ok=True)
    fresh = Path(tempfile.mkdtemp(prefix=".whl-new-", dir=dest.parent))
    cmd = [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps",
           "--only-binary=:all:", "--implementation", "cp", "--python-version", python_version,
           "--abi", abi, "--abi", "abi3", "--abi", "none",
           *(arg for p in PLATFORMS for arg in ("--platform", p)),
           "--dest", str(fresh), *(p.spec for p in pins)]
    try:
        subprocess.run(cmd, check=True)
    except BaseException:
        shutil.rmtree(fresh, ignore_errors=True)
        raise
    shutil.rmtree(dest, ignore_errors=True)  # stale wheels would be a second version
    fresh.rename(dest)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--list", type=Path, default=ROOT / "requirements-gpu-offline.txt")
    parser.add_argument("--dest", type=Path, default=ROOT / ".whl")
    parser.add_argument("--python-version", default="3.12", help="the CUDA machine's Python")
    parser.add_argument("--limit-mib", type=float, default=60.0)
    parser.add_argument("--check-only", action="store_true", help="check --dest, fetch nothing")
    args = parser.parse_args(argv)
    pins = read_pins(args.list)
    if not args.check_only:
        download(pins, args.dest, args.python_version)
    try:
        sizes = check_folder(args.dest, pins, args.limit_mib)
    except ValueError as exc:
        print(f"gpu-wheels: {args.dest}: {exc}", file=sys.stderr)
        return 1
    total = sum(size for _, size in sizes)
    for name, size in sizes:
        print(f"{size / MIB:8.2f} MiB  {name}")
    print(f"{total / MIB:8.2f} MiB  in {len(sizes)} wheels in {args.dest}")
    if args.dest.resolve().is_relative_to(ROOT):
        carried = tree_bytes(ROOT) + total
        print(f"{carried / MIB:8.2f} MiB  carried with the repository's tree "
              f"(the device tool's limit: {CARRY_LIMIT_MIB} MiB)")
        if carried > CARRY_LIMIT_MIB * MIB:
            print("gpu-wheels: the tree and the wheels are over what the device tool carries",
                  file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
