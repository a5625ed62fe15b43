"""The offline GPU check (bench/gpu_offline.py, `make gpu-check OFFLINE=1`) without a GPU: its
dry run installs hand-made wheels into a site folder and skips the CUDA stages saying why; the
stage runner keeps time for later stages and runs those that do not need a failed one; the
carried sources keep their wheel's timestamps, so a cached JIT build (gsplat's) is loaded
without compiling again."""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

import gpu_offline  # noqa: E402
import gpu_site  # noqa: E402
import gsplat_cache  # noqa: E402

WHEEL_TIME = (2025, 7, 4, 16, 50, 0)


def make_wheel(folder: Path, name: str, version: str, files: dict[str, str],
               tag: str = "py3-none-any") -> Path:
    """A minimal wheel written by hand (no registry, no build backend)."""
    dist = f"{name}-{version}.dist-info"
    path = folder / f"{name}-{version}-{tag}.whl"
    with zipfile.ZipFile(path, "w") as z:
        for arcname, text in files.items():
            z.writestr(zipfile.ZipInfo(arcname, date_time=WHEEL_TIME), text)
        z.writestr(f"{dist}/METADATA",
                   f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n")
        z.writestr(f"{dist}/WHEEL", "Wheel-Version: 1.0\nGenerator: tests\n"
                                    f"Root-Is-Purelib: true\nTag: {tag}\n")
        z.writestr(f"{dist}/RECORD", "")
    return path


def test_the_dry_run_installs_the_wheels_and_skips_the_cuda_stages(tmp_path):
    wheels = tmp_path / "whl"
    wheels.mkdir()
    make_wheel(wheels, "telesplat_probe", "1.0",
               {"telesplat_probe/__init__.py": "ANSWER = 42\n"})
    make_wheel(wheels, "elsewhere", "2.0", {"elsewhere.py": ""},
               tag="cp399-cp399-manylinux_2_17_x86_64")  # built for another Python
    out, site = tmp_path / "out", tmp_path / "site"
    done = subprocess.run([sys.executable, str(ROOT / "bench" / "gpu_offline.py"), "--dry-run",
                           "--out", str(out), "--wheels", str(wheels), "--site", str(site),
                           "--gsplat-cache", str(tmp_path / "cache")],
                          capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stdout + done.stderr
    log = done.stdout
    for stage in ("wheels", "imports", "pytest-gpu"):
        assert re.search(rf"<== {stage}: passed in \d+\.\d s", log), stage
    for stage in ("gpu", "gsplat-build", "bench", "profile"):
        assert f"==> {stage}: skipped (CUDA only: a dry run has no GPU)" in log
    assert "left out elsewhere-2.0-cp399" in log
    probe = subprocess.run([sys.executable, "-c", "import telesplat_probe, sys; "
                            "sys.exit(telesplat_probe.ANSWER != 42 or "
                            f"not telesplat_probe.__file__.startswith({str(site)!r}))"],
                           env={"PYTHONPATH": str(site)}, timeout=60)
    assert probe.returncode == 0  # installed into the site folder, importable from there
    summary = json.loads((out / "summary.json").read_text())
    assert summary["passed"] and summary["installed"] == ["telesplat-probe 1.0"]
    status = {s["name"]: s["status"] for s in summary["stages"]}
    assert status == {"gpu": "skipped", "wheels": "passed", "imports": "passed",
                      "gsplat-build": "skipped", "pytest-gpu": "passed", "bench": "skipped",
                      "profile": "skipped"}
    assert "server.app" in summary["imports"]["found"]
    page = (out / "summary.md").read_text()
    assert "| gsplat-build | skipped |" in page and "| wheels | passed |" in page
    # what the device tool returns: at most 8 plain files, no folders
    assert all(p.is_file() for p in out.iterdir()) and len(list(out.iterdir())) <= 8


def test_two_versions_of_a_project_stop_the_install(tmp_path):
    for version in ("1.0", "1.1"):
        make_wheel(tmp_path, "twice", version, {"twice.py": ""})
    with pytest.raises(RuntimeError, match="two versions"):
        gpu_site.install(tmp_path, tmp_path / "site", lenient=True)
    with pytest.raises(RuntimeError, match="no wheels"):
        gpu_site.install(tmp_path / "site", tmp_path / "other", lenient=True)


def test_a_wheel_for_another_python_fails_a_real_run(tmp_path):
    make_wheel(tmp_path, "elsewhere", "2.0", {"elsewhere.py": ""},
               tag="cp399-cp399-manylinux_2_17_x86_64")
    with pytest.raises(RuntimeError, match="another Python"):
        gpu_site.install(tmp_path, tmp_path / "site", lenient=False)


def _check(tmp_path: Path, deadline: float = 100.0, dry: bool = False) -> gpu_offline.Check:
    out = tmp_path / "out"
    out.mkdir()
    args = argparse.Namespace(out=out, wheels=tmp_path, site=tmp_path / "site",
                              gsplat_cache=tmp_path / "cache", gsplat_archive=None,
                              dry_run=dry, deadline=deadline)
    return gpu_offline.Check(args)


def test_a_failed_stage_stops_only_the_stages_that_need_it(tmp_path):
    ran = []

    def step(name, status):
        def run(check, budget):
            ran.append((name, round(budget)))
            return gpu_offline.Outcome(status, f"{name} {status}")
        return run

    stages = (gpu_offline.Stage("a", step("a", "failed"), cap_s=30, min_s=1),
              gpu_offline.Stage("b", step("b", "passed"), cap_s=30, min_s=1),
              gpu_offline.Stage("c", step("c", "passed"), cap_s=30, min_s=1, after=("a",)),
              gpu_offline.Stage("d", step("d", "passed"), cap_s=90, min_s=20, after=("b",)))
    check = _check(tmp_path, deadline=40.0)
    assert gpu_offline.run_stages(check, stages) is False
    c = next(r for r in check.results if r.name == "c")
    assert (c.status, c.note) == ("skipped", "needs a, which failed")
    # each budget: its cap, less the minimums of the stages after it (1 + 1 + 20 for a), and
    # d, the last, what the deadline leaves
    assert ran == [("a", 18), ("b", 19), ("d", 40)]
    assert json.loads((check.out / "summary.json").read_text())["passed"] is False


def test_a_stage_the_deadline_cannot_fit_is_skipped(tmp_path):
    def run(check, budget):
        return gpu_offline.Outcome("passed")

    stages = (gpu_offline.Stage("first", run, cap_s=30, min_s=5),
              gpu_offline.Stage("long", run, cap_s=300, min_s=60))
    check = _check(tmp_path, deadline=40.0)
    assert gpu_offline.run_stages(check, stages) is False
    long = check.results[1]
    assert long.status == "skipped" and long.note.startswith("no time left")


def test_a_failed_gsplat_build_makes_gsplat_unimportable_later(tmp_path):
    check = _check(tmp_path)
    check.block_gsplat("not built within 300 s")
    done = subprocess.run([sys.executable, "-c", "import gsplat"], env=check.env(),
                          capture_output=True, text=True, timeout=60)
    assert done.returncode != 0
    assert "ImportError: gsplat blocked by the GPU check: not built within 300 s" in done.stderr


@pytest.mark.skipif(shutil.which("ninja") is None or shutil.which("c++") is None,
                    reason="needs ninja and a C++ compiler")
def test_stamped_sources_keep_a_cached_build_valid(tmp_path):
    """A torch JIT extension built from a carried wheel's source, as gsplat's is: installed
    afresh with its wheel's timestamps, ninja finds nothing to do, also when the build comes
    back from its archive; with install-time stamps it compiles again."""
    wheels = tmp_path / "whl"
    wheels.mkdir()
    make_wheel(wheels, "tinyext", "1.0",
               {"tinyext/add.cpp": 'extern "C" int tiny_add(int a, int b) { return a + b; }\n'})
    site, cache, out = tmp_path / "site", tmp_path / "cache", tmp_path / "out"
    out.mkdir()
    key = {"case": "tinyext"}

    def build() -> str:
        """Install the wheel afresh, load the extension; ninja's words."""
        gpu_site.install(wheels, site, lenient=False)
        code = ("import torch.utils.cpp_extension as ce; "
                f"ce.load('{gsplat_cache.BUILD}', ['{site}/tinyext/add.cpp'], "
                f"build_directory='{cache / gsplat_cache.BUILD}', is_python_module=False, "
                "verbose=True)")
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                              timeout=120)
        assert done.returncode == 0, done.stdout + done.stderr
        return done.stdout + done.stderr

    assert gsplat_cache.prepare(cache, key) == "miss"
    (cache / gsplat_cache.BUILD).mkdir()
    assert "c++" in build()  # compiled
    gsplat_cache.remember(cache, key)
    assert "no work to do" in build()
    archive, size = gsplat_cache.pack(cache, out)
    assert archive == out / gsplat_cache.ARCHIVE, size
    gsplat_cache.clear(cache)
    assert gsplat_cache.prepare(cache, key, archive) == "restored"
    assert "no work to do" in build()
    assert gsplat_cache.prepare(cache, {"case": "other"}, archive) == "miss"  # another key
    assert not gsplat_cache.built(cache)


@pytest.mark.skipif(shutil.which("make") is None, reason="no make here")
def test_make_runs_the_driver_offline():
    """`make gpu-check OFFLINE=1`: the machine's python3 runs the driver (no venv, no pip
    install); with DRY_RUN=1 this venv's Python does, with --dry-run."""
    def recipe(*args: str) -> str:
        return subprocess.run(["make", "-n", "gpu-check", "OFFLINE=1", *args], cwd=ROOT,
                              capture_output=True, text=True, timeout=60, check=True).stdout

    real = recipe("GPU_OUT=/results", "PYTHON=python3", "GSPLAT_ARCHIVE=old.tar.gz")
    assert "python3 bench/gpu_offline.py --out /results --wheels .whl" in real
    assert "--gsplat-archive old.tar.gz" in real and "--dry-run" not in real
    assert "pip install" not in real and "nvidia-smi -L" not in real
    dry = recipe("DRY_RUN=1", "VENV=/some/venv")
    assert "/some/venv/bin/python bench/gpu_offline.py" in dry and "--dry-run" in dry
