"""The GPU check on a CUDA machine that reaches no package registry (docs/gpu.md).

    python3 bench/gpu_offline.py --out DIR [--wheels .whl] [--site DIR] [--deadline 540]
                                 [--gsplat-cache DIR] [--gsplat-archive FILE] [--dry-run]

``make gpu-check OFFLINE=1 GPU_OUT=DIR`` runs it with the machine's own Python (the one that
holds its CUDA build of torch). Stages, in order, each timed and logged; one that fails stops
only the stages that need it:

gpu           nvidia-smi's summary (``nvidia-smi -q`` kept whole), the GPU's arch
wheels        the carried wheels (``make gpu-wheels``) installed into a fresh site folder
imports       every module the check imports, from that site and the machine (versions);
              torch sees the GPU; ninja and nvcc are there
gsplat-build  gsplat's CUDA kernels compiled for this GPU's arch with every core, timed, and
              one render; the build is cached (``--gsplat-cache``) and returned packed; if it
              fails, ``import gsplat`` is made to fail in the later stages (the gpu tests that
              need it skip instead of each compiling again)
pytest-gpu    ``pytest -m gpu`` with a per-test timeout, a JUnit XML report
bench         ``bench/gpu_check.py``: docs/gpu.md's figures and ratios, its time budget what
              the deadline leaves

Everything lands in ``--out`` as at most 8 plain files (what the device tool returns):
summary.md, summary.json, stages.log, nvidia-smi.txt, junit.xml, gpu.md (docs/gpu.md with the
measured section), figures.json, gsplat-cache.tar.gz. The summary is rewritten after every
stage, so a run cut short still leaves one. Exit 0 only when every stage passed.

``--dry-run`` (no CUDA needed): the same install-from-wheels path with this interpreter's torch;
wheels built for another Python are left out and listed, the CUDA stages are skipped with
their reason, and pytest only collects. Standard library only: nothing carried is importable
before the wheels stage.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable
from pathlib import Path

import gpu_site
import gsplat_cache

ROOT = Path(__file__).resolve().parents[1]
BENCH = Path(__file__).resolve().parent
DEFAULT_DEADLINE_S = 540.0  # 9 minutes: the device tool allows 10 a command
PER_TEST_TIMEOUT_S = 150
LOG_TAIL_LINES = 15


@dataclasses.dataclass
class Outcome:
    status: str  # "passed", "failed" or "skipped"
    note: str = ""


@dataclasses.dataclass
class Stage:
    name: str
    run: Callable[[Check, float], Outcome]
    cap_s: float  # the most it may take
    min_s: float  # less than this left: skipped (and kept for it by the stages before)
    cuda: bool = False  # skipped in a dry run
    after: tuple[str, ...] = ()  # stages that must have passed first


@dataclasses.dataclass
class Result:
    name: str
    status: str
    note: str
    elapsed_s: float
    budget_s: float


class Check:
    """One run: its options, clock, environment for the stages' processes, and findings."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.out: Path = args.out.resolve()
        self.wheels: Path = args.wheels.resolve()
        self.site: Path = args.site.resolve()
        self.cache: Path = args.gsplat_cache.resolve()
        self.archive: Path | None = args.gsplat_archive
        self.dry: bool = args.dry_run
        self.deadline_s: float = args.deadline
        self.t0 = time.monotonic()
        self.log = self.out / "stages.log"
        self.results: list[Result] = []
        self.facts: dict = {"dry_run": self.dry, "python": sys.executable,
                            "started": datetime.datetime.now(datetime.UTC).isoformat()}
        self.arch: str | None = None
        self.pytest_timeout = False
        self.gsplat_blocker: Path | None = None  # set when gsplat's kernels did not build
        self.tests: list[str] | None = getattr(args, "tests", None)

    def elapsed(self) -> float:
        return time.monotonic() - self.t0

    def say(self, text: str) -> None:
        print(text, flush=True)
        with self.log.open("a") as f:
            f.write(text + "\n")

    def env(self) -> dict[str, str]:
        """The stages' processes: the carried site first (its programs too), the repository's
        packages, and the one gsplat build."""
        first = [str(self.gsplat_blocker)] if self.gsplat_blocker else []
        path = os.pathsep.join(p for p in (*first, str(self.site), str(ROOT),
                                           os.environ.get("PYTHONPATH", "")) if p)
        tools = os.pathsep.join((str(self.site / "bin"), os.environ.get("PATH", "")))  # ninja
        return {**os.environ, "PYTHONPATH": path, "PATH": tools, "PYTHONUNBUFFERED": "1",
                **gsplat_cache.build_env(self.cache, self.arch)}

    def block_gsplat(self, why: str) -> None:
        """Make ``import gsplat`` fail, saying ``why``, in the later stages: gsplat wipes and
        restarts an unfinished build on every import, so each gpu test would spend its time
        compiling again; this way they skip (``importorskip``) and the others still run."""
        blocker = self.site.parent / f"{self.site.name}-gsplat-blocked"
        (blocker / "gsplat").mkdir(parents=True, exist_ok=True)
        (blocker / "gsplat" / "__init__.py").write_text(
            f"raise ImportError({'gsplat blocked by the GPU check: ' + why!r})\n")
        self.gsplat_blocker = blocker

    def run_logged(self, cmd: list[str], timeout: float) -> tuple[int | None, str]:
        """Run ``cmd`` in the repository, its output appended to stages.log; (exit code, or
        None when it ran out of time and was stopped; the output's last lines)."""
        with self.log.open("a") as log:
            log.write(f"$ {' '.join(cmd)}\n")
            log.flush()
            start = log.tell()
            proc = subprocess.Popen(cmd, cwd=ROOT, env=self.env(), stdout=log,
                                    stderr=subprocess.STDOUT, start_new_session=True)
            try:
                rc: int | None = proc.wait(timeout=max(1.0, timeout))
            except subprocess.TimeoutExpired:
                stop(proc)
                rc = None
        with self.log.open() as log:
            log.seek(start)
            tail = log.read().splitlines()[-LOG_TAIL_LINES:]
        if rc != 0:  # what went wrong, where the device tool shows it (the output's end)
            print("\n".join(f"    | {line}" for line in tail), flush=True)
        return rc, "\n".join(tail)


def stop(proc: subprocess.Popen) -> None:
    """End the stage's process group (its server and workers too), gently first."""
    for sig, grace in ((signal.SIGTERM, 10), (signal.SIGKILL, 5)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(grace)
            return
        except subprocess.TimeoutExpired:
            continue


def last_json(text: str) -> dict:
    for line in reversed(text.splitlines()):
        if line.startswith("{"):
            try:
                return json.loads(line)
            except ValueError:
                break
    return {}


# -- the stages ------------------------------------------------------------------------------


def stage_gpu(check: Check, budget: float) -> Outcome:
    if shutil.which("nvidia-smi") is None:
        return Outcome("failed", "no nvidia-smi: this is no CUDA machine (DRY_RUN=1 checks the "
                                 "rest without one)")
    query = subprocess.run(["nvidia-smi", "-q"], capture_output=True, text=True,
                           timeout=budget)
    (check.out / "nvidia-smi.txt").write_text(query.stdout + query.stderr)
    summary = {}
    for line in query.stdout.splitlines():
        key, sep, value = line.partition(":")
        key = key.strip()
        if sep and key in ("Product Name", "Driver Version", "CUDA Version", "Total",
                           "Product Architecture") and key not in summary:
            summary[key] = value.strip()  # "Total" first appears under FB memory
    check.arch = gsplat_cache.gpu_arch()
    summary["compute capability"] = check.arch
    check.facts["gpu"] = summary
    check.say("gpu: " + ", ".join(f"{k} {v}" for k, v in summary.items()))
    if query.returncode != 0 or not check.arch:
        return Outcome("failed", f"nvidia-smi exited {query.returncode} and gave no compute "
                                 "capability")
    return Outcome("passed", f"{summary.get('Product Name', '?')}, sm {check.arch}")


def stage_wheels(check: Check, budget: float) -> Outcome:
    try:
        done = gpu_site.install(check.wheels, check.site, lenient=check.dry)
    except (RuntimeError, subprocess.CalledProcessError) as exc:
        return Outcome("failed", str(exc))
    check.facts["site"] = str(done.site)
    check.facts["installed"] = done.installed
    check.facts["left_out"] = done.left_out
    for line in done.installed:
        check.say(f"installed {line}")
    for line in done.left_out:
        check.say(f"left out {line}")
    note = f"{len(done.installed)} wheels into {done.site}"
    if done.left_out:
        note += f"; {len(done.left_out)} left out (built for another Python)"
    return Outcome("passed", note)


def stage_imports(check: Check, budget: float) -> Outcome:
    cmd = [sys.executable, str(BENCH / "gpu_probe.py"), "imports"]
    rc, tail = check.run_logged(cmd + ([] if check.dry else ["--cuda"]), budget)
    report = last_json(tail)
    check.facts["imports"] = report
    check.pytest_timeout = "pytest_timeout" in report.get("found", {})
    if rc is None:
        return Outcome("failed", f"timed out after {budget:.0f} s")
    if rc != 0 or not report:
        missing = ", ".join(report.get("missing", {}))
        if not missing:
            return Outcome("failed", f"the probe broke (exit {rc}): see stages.log")
        return Outcome("failed", f"missing here: {missing} (carry it: "
                                 "requirements-gpu-offline.txt)")
    torch_info = report.get("torch", {})
    return Outcome("passed", f"torch {torch_info.get('version')} (CUDA {torch_info.get('cuda')})"
                             f", gsplat {report['found'].get('gsplat', '?').split()[0]}")


def stage_gsplat_build(check: Check, budget: float) -> Outcome:
    imports = check.facts.get("imports", {})
    key = {"gsplat": imports.get("found", {}).get("gsplat", "").split(" ")[0],
           "torch": imports.get("torch", {}).get("version"), "python": imports.get("python"),
           "nvcc": gsplat_cache.nvcc_version(imports.get("tools", {}).get("nvcc")),
           "arch": check.arch, "site": str(check.site)}
    state = gsplat_cache.prepare(check.cache, key, check.archive)
    check.say(f"gsplat cache {check.cache}: {state}")
    rc, tail = check.run_logged([sys.executable, str(BENCH / "gpu_probe.py"), "gsplat"], budget)
    report = last_json(tail)
    report.update(cache=str(check.cache), cache_state=state)
    check.facts["gsplat_build"] = report
    if rc is None or rc != 0 or "load_s" not in report:
        why = (f"not built within {budget:.0f} s (MAX_JOBS={check.env()['MAX_JOBS']})"
               if rc is None else "its kernels did not build or render: see stages.log")
        check.block_gsplat(why)
        return Outcome("failed", f"{why}; the gpu tests that need gsplat skip")
    gsplat_cache.remember(check.cache, key)
    what = "compiled" if state == "miss" else f"loaded ({state})"
    note = f"{what} in {report['load_s']:.1f} s, cache {check.cache}"
    if state == "miss":
        archive, size = gsplat_cache.pack(check.cache, check.out)
        report["archive"] = str(archive) if archive else None
        note += f"; packed: {size}"
    check.say(f"gsplat: {note}")
    return Outcome("passed", note)


def stage_pytest(check: Check, budget: float) -> Outcome:
    tests = check.tests or sorted(str(p.relative_to(ROOT))
                                  for p in (ROOT / "tests").glob("test_gpu_*.py"))
    cmd = [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-p", "no:xdist",
           "-m", "gpu", "-rs", *tests]
    if check.dry:
        rc, tail = check.run_logged(cmd + ["--collect-only", "-q"], budget)
        check.facts["pytest"] = {"collected_only": True, "tail": tail.splitlines()[-1:]}
        if rc != 0:
            return Outcome("failed", f"collection failed (exit {rc}): see stages.log")
        return Outcome("passed", "dry run: collected only, not run: "
                                 + (tail.splitlines()[-1] if tail else ""))
    junit = check.out / "junit.xml"
    cmd += [f"--junitxml={junit}", "-o", "junit_family=xunit2"]
    if check.pytest_timeout:
        cmd += [f"--timeout={PER_TEST_TIMEOUT_S}"]
    rc, tail = check.run_logged(cmd, budget)
    counts = junit_counts(junit)
    check.facts["pytest"] = counts
    shown = ", ".join(f"{v} {k}" for k, v in counts.items()) or "no report"
    if not check.pytest_timeout:
        shown += f" (pytest-timeout missing: only the stage's {budget:.0f} s bound held)"
    if rc is None:
        return Outcome("failed", f"timed out after {budget:.0f} s; {shown}")
    return Outcome("passed" if rc == 0 else "failed", shown)


def junit_counts(path: Path) -> dict[str, int]:
    if not path.is_file():
        return {}
    root = ET.parse(path).getroot()
    suite = root if root.tag == "testsuite" else root.find("testsuite")
    if suite is None:
        return {}
    return {k: int(suite.get(k, 0)) for k in ("tests", "failures", "errors", "skipped")}


def stage_bench(check: Check, budget: float) -> Outcome:
    page = check.out / "gpu.md"
    shutil.copyfile(ROOT / "docs" / "gpu.md", page)
    # Its fixed costs (server start, capture, warm-ups) take about a minute; the rest is
    # spent in its eight timed measurements.
    seconds = max(1.0, min(6.0, (budget - 75.0) / 8.0))
    cmd = [sys.executable, str(BENCH / "gpu_check.py"), "--out", str(page),
           "--json", str(check.out / "figures.json"), "--seconds", f"{seconds:.1f}"]
    rc, tail = check.run_logged(cmd, budget)
    check.facts["bench"] = {"seconds": seconds}
    if rc is None:
        return Outcome("failed", f"timed out after {budget:.0f} s")
    if rc != 0:
        return Outcome("failed", f"exit {rc}: see stages.log")
    return Outcome("passed", f"{seconds:.1f} s a measurement; figures in gpu.md")


def stage_profile(check: Check, budget: float) -> Outcome:
    """Where a frame's time goes (bench/gpu_profile.py): its tables go to stages.log, its
    numbers (the output's last line) to summary.json (no file of its own: the device tool
    brings back 8)."""
    cmd = [sys.executable, str(BENCH / "gpu_profile.py"), *(["--dry-run"] if check.dry else [])]
    rc, tail = check.run_logged(cmd, budget)
    check.facts["profile"] = last_json(tail)
    if rc is None:
        return Outcome("failed", f"timed out after {budget:.0f} s")
    return Outcome("passed" if rc == 0 else "failed",
                   "tables in stages.log, numbers in summary.json" if rc == 0
                   else f"exit {rc}: see stages.log")


STAGES = (
    Stage("gpu", stage_gpu, cap_s=30, min_s=5, cuda=True),
    Stage("wheels", stage_wheels, cap_s=120, min_s=10),
    Stage("imports", stage_imports, cap_s=90, min_s=10, after=("wheels",)),
    Stage("gsplat-build", stage_gsplat_build, cap_s=360, min_s=60, cuda=True,
          after=("gpu", "imports")),
    Stage("pytest-gpu", stage_pytest, cap_s=240, min_s=60, after=("gpu", "imports")),
    Stage("bench", stage_bench, cap_s=200, min_s=90, cuda=True,
          after=("gpu", "imports", "gsplat-build")),
    Stage("profile", stage_profile, cap_s=240, min_s=60, cuda=True,
          after=("gpu", "imports", "gsplat-build")),
)


# -- running them ----------------------------------------------------------------------------


def skip_reason(check: Check, stage: Stage) -> str | None:
    if stage.cuda and check.dry:
        return "CUDA only: a dry run has no GPU"
    status = {r.name: r.status for r in check.results}
    cuda = {s.name for s in STAGES if s.cuda}
    for need in stage.after:
        if check.dry and need in cuda:
            continue  # skipped by design in a dry run
        if status.get(need) != "passed":
            return f"needs {need}, which {status.get(need, 'did not run')}"
    return None


def budget_for(check: Check, index: int, stages: tuple[Stage, ...]) -> float:
    """The stage's cap, less what the deadline must keep for the minimums of those after it."""
    later = sum(s.min_s for s in stages[index + 1:] if not (s.cuda and check.dry))
    return min(stages[index].cap_s, check.deadline_s - check.elapsed() - later)


def run_stages(check: Check, stages: tuple[Stage, ...] = STAGES) -> bool:
    for index, stage in enumerate(stages):
        start = check.elapsed()
        reason = skip_reason(check, stage)
        budget = budget_for(check, index, stages)
        if reason is None and budget < stage.min_s:
            reason = f"no time left: {budget:.0f} s of the {check.deadline_s:.0f} s deadline"
        if reason is not None:
            outcome, budget = Outcome("skipped", reason), 0.0
            check.say(f"==> {stage.name}: skipped ({reason})")
        else:
            check.say(f"==> {stage.name} (at {start:.1f} s, budget {budget:.0f} s)")
            try:
                outcome = stage.run(check, budget)
            except Exception as exc:  # noqa: BLE001 - a broken stage must not stop the rest
                outcome = Outcome("failed", f"{type(exc).__name__}: {exc}")
            check.say(f"<== {stage.name}: {outcome.status} in {check.elapsed() - start:.1f} s"
                      + (f" ({outcome.note})" if outcome.note else ""))
        check.results.append(Result(stage.name, outcome.status, outcome.note,
                                    round(check.elapsed() - start, 1), round(budget)))
        write_summary(check)
    return passed(check)


def passed(check: Check) -> bool:
    """Every stage passed (in a dry run the CUDA stages are skipped by design)."""
    cuda = {s.name for s in STAGES if s.cuda}
    return all(r.status == "passed" or (check.dry and r.name in cuda and r.status == "skipped")
               for r in check.results)


def write_summary(check: Check) -> None:
    facts = {**check.facts, "elapsed_s": round(check.elapsed(), 1),
             "deadline_s": check.deadline_s, "passed": passed(check),
             "stages": [dataclasses.asdict(r) for r in check.results]}
    (check.out / "summary.json").write_text(json.dumps(facts, indent=1, default=str) + "\n")
    lines = [f"# GPU check{' (dry run: no GPU)' if check.dry else ''}", "",
             f"Started {check.facts['started']}; {facts['elapsed_s']} s of a "
             f"{check.deadline_s:.0f} s deadline; python {check.facts['python']}.", "",
             "| stage | status | seconds | budget | note |", "|---|---|---|---|---|"]
    lines += [f"| {r.name} | {r.status} | {r.elapsed_s} | {r.budget_s} | "
              f"{r.note.replace('|', '/')} |" for r in check.results]
    if "gpu" in check.facts:
        lines += ["", "GPU: " + ", ".join(f"{k} {v}" for k, v in check.facts["gpu"].items())]
    imports = check.facts.get("imports", {})
    if imports:
        torch_info = imports.get("torch", {})
        lines += ["", f"torch {torch_info.get('version')} (CUDA {torch_info.get('cuda')}, "
                      f"available: {torch_info.get('cuda_available')}); onnxruntime providers: "
                      f"{imports.get('onnxruntime_providers')}", "",
                  "| module | version (from) |", "|---|---|"]
        lines += [f"| {name} | {where} |" for name, where in sorted(imports["found"].items())]
        lines += [f"| {name} | **missing**: {why} |"
                  for name, why in imports.get("missing", {}).items()]
        lines += [f"| {name} | not here (optional): {why} |"
                  for name, why in imports.get("optional_missing", {}).items()]
    build = check.facts.get("gsplat_build")
    if build and "load_s" in build:
        lines += ["", f"gsplat extension: {build['load_s']:.1f} s to "
                      f"{'compile' if build.get('cache_state') == 'miss' else 'load'} "
                      f"(cache {build['cache']}: {build.get('cache_state')})."]
    page = check.out / "gpu.md"
    if page.is_file():
        text = page.read_text()
        begin, end = "<!-- gpu-check:begin -->", "<!-- gpu-check:end -->"
        if begin in text and end in text:
            lines += ["", text.split(begin, 1)[1].split(end, 1)[0].strip()]
    (check.out / "summary.md").write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="where the results go")
    parser.add_argument("--wheels", type=Path, default=ROOT / ".whl")
    parser.add_argument("--site", type=Path, default=Path("/tmp/telesplat-gpu-site"),
                        help="the carried wheels' install folder (fixed: gsplat's cached "
                             "build names its sources by path)")
    parser.add_argument("--gsplat-cache", type=Path, default=ROOT / ".gsplat-cache")
    parser.add_argument("--gsplat-archive", type=Path, default=None,
                        help="a gsplat-cache.tar.gz from an earlier run")
    parser.add_argument("--deadline", type=float, default=DEFAULT_DEADLINE_S)
    parser.add_argument("--dry-run", action="store_true")
    parser.add_argument("--stages", default=",".join(s.name for s in STAGES),
                        help="comma-separated stages to run, in their fixed order (default: all)")
    parser.add_argument("--tests", nargs="*", default=None,
                        help="the pytest stage's test files (default: tests/test_gpu_*.py)")
    args = parser.parse_args(argv)
    chosen = set(args.stages.split(","))
    unknown = chosen - {s.name for s in STAGES}
    if unknown:
        parser.error(f"unknown stages: {', '.join(sorted(unknown))}")
    args.out.mkdir(parents=True, exist_ok=True)
    check = Check(args)
    check.log.write_text("")
    check.say(f"gpu check{' (dry run)' if check.dry else ''}: results in {check.out}, "
              f"deadline {check.deadline_s:.0f} s")
    ok = run_stages(check, tuple(s for s in STAGES if s.name in chosen))
    check.say(f"gpu check: {'every stage passed' if ok else 'NOT every stage passed'} in "
              f"{check.elapsed():.1f} s; summary in {check.out / 'summary.md'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
