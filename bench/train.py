"""Training throughput: iterations per second at 512 x 512 per view, with a breakdown.

Films a small take in the synthetic studio (the ``telesplat synth capture`` code: 17 cameras
at 512 x 512, a few frames of one motion; cached between runs), then times the trainer's
``step()`` with ``crop_to_subject`` on and off, with and without SMPL-X fine-tuning, side by
side: every variant is a Trainer of its own, warmed up (the view cache filled, the numba
kernels compiled), then the variants run in interleaved rounds so machine noise hits them
alike; the it/s is the median over rounds. The breakdown is the mean wall time per
iteration of each phase (timed with a synchronisation between phases):

    data       next view (LRU cache; decode + prepare on a miss)
    pose       posed mesh -> triangle frames (cached when not fine-tuning)
    render     world Gaussians + rasterize (forward)
    loss       visibility, L1 + D-SSIM under the weight map, regularisers
    backward   autograd backward pass
    optimizer  finiteness check, density statistics, both Adam steps
    densify    densification / opacity reset when scheduled (never, in this window)

Measured at the initial one-Gaussian-per-triangle avatar and again after densifying to
``--gaussians`` (every Gaussian cloned/split until the count is reached: a stand-in for the
avatar partway through training). LPIPS is off (not available offline here anyway).

    .venv/bin/python bench/train.py [--gaussians 48000] [--rounds 5] [--iters 40]

Beside a busy machine: ``--hog N`` runs it next to N busy-loop processes; ``--wait-compare``
instead times the "crop, no fine-tune" variant at 1 and 2 threads with OpenMP's wait policy
ACTIVE and PASSIVE (a fresh process each, interleaved passes; bench/waitpolicy.py):

    .venv/bin/python bench/train.py --wait-compare --hog 2 [--passes 3]
"""

from __future__ import annotations

import argparse
import logging
import os
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numba
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from avatar_core.synth.capture import CaptureSpec, capture  # noqa: E402
from avatar_core.synth.model_writer import ensure_models  # noqa: E402
from avatar_core.train.config import preset  # noqa: E402
from avatar_core.train.density import DensityStats, densify_and_prune  # noqa: E402
from avatar_core.train.trainer import Trainer  # noqa: E402
from bench import waitpolicy  # noqa: E402

PHASES = ("data", "pose", "render", "loss", "backward", "optimizer", "densify")
VARIANTS = {  # name: (crop_to_subject, fine-tuning)
    "crop, no fine-tune": (True, False),
    "full frame, no fine-tune": (False, False),
    "crop, fine-tune": (True, True),
    "full frame, fine-tune": (False, True),
}


def bench_dataset(root: Path, frames: int) -> Path:
    """17 cameras x ``frames`` frames of 'peace' at 512 x 512 (filmed once, then reused)."""
    out = root / f"train-bench-512-f{frames}"
    if (out / "dataset.json").is_file():
        return out
    print(f"filming the benchmark take into {out} ...", flush=True)
    spec = CaptureSpec(sequences=(("peace",),), num_cameras=17, resolution=512,
                       max_frames=frames, cross_identity=None, supersample=2)
    capture(out, spec, model_dir=ensure_models().root)
    return out


def densify_to(trainer: Trainer, target: int) -> None:
    """Clone/split every Gaussian (largest first) until ``target`` are reached."""
    while trainer.num_gaussians < target:
        n = trainer.num_gaussians
        stats = DensityStats(grad_accum=torch.ones(n), count=torch.ones(n),
                             max_radii=torch.zeros(n))
        trainer.state = densify_and_prune(
            trainer.state, stats, trainer.optimizer, grad_threshold=1e-9,
            extent=trainer.extent, face_scales=trainer._posed_k, max_gaussians=target,
            generator=trainer.split_generator).state
        trainer.stats = DensityStats.zeros(trainer.num_gaussians)


def make_trainers(data: Path, out: Path, warmup: int) -> dict[str, Trainer]:
    base = preset("quick")
    # no densification inside the timed window; the rest as in training
    base = replace(base, loss=replace(base.loss, lpips=False),
                   densify=replace(base.densify, from_iter=10**9))
    trainers = {}
    for name, (crop, finetune) in VARIANTS.items():
        cfg = replace(base, data=replace(base.data, crop_to_subject=crop),
                      finetune=replace(base.finetune, enabled=finetune))
        t = Trainer(data, cfg, out / name.replace(", ", "_").replace(" ", "-"),
                    body_model=ensure_models().root, profile=True)
        for _ in range(warmup):
            t.step()
        trainers[name] = t
    return trainers


def measure(trainers: dict[str, Trainer], rounds: int, iters: int) -> dict[str, dict]:
    rates: dict[str, list[float]] = {n: [] for n in trainers}
    for t in trainers.values():
        t.phases.totals.clear()
    for _ in range(rounds):
        for name, t in trainers.items():
            t0 = time.perf_counter()
            for _ in range(iters):
                t.step()
            rates[name].append(iters / (time.perf_counter() - t0))
    out = {}
    for name, t in trainers.items():
        n = rounds * iters
        out[name] = {"its": statistics.median(rates[name]), "min": min(rates[name]),
                     "max": max(rates[name]), "N": t.num_gaussians,
                     "pixels": statistics.mean(v.target.shape[0] * v.target.shape[1]
                                               for v in t.views._cache.values()),
                     **{p: 1e3 * t.phases.totals.get(p, 0.0) / n for p in PHASES}}
    return out


def table(results: dict[str, dict]) -> str:
    head = ("| variant | Gaussians | px / view | it/s (median) | range | "
            + " | ".join(f"{p} ms" for p in PHASES) + " |")
    rule = "|---|---:|---:|---:|---:|" + "---:|" * len(PHASES)
    rows = [f"| {name} | {r['N']:,} | {r['pixels']:,.0f} | **{r['its']:.1f}** | "
            f"{r['min']:.1f}-{r['max']:.1f} | "
            + " | ".join(f"{r[p]:.1f}" for p in PHASES) + " |" for name, r in results.items()]
    return "\n".join([head, rule, *rows])


def wait_child(data: Path, warmup: int, iters: int) -> None:
    """One trainer (crop, no fine-tune), warmed up; the median it/s of 3 windows."""
    base = preset("quick")
    cfg = replace(base, loss=replace(base.loss, lpips=False),
                  densify=replace(base.densify, from_iter=10**9))
    with tempfile.TemporaryDirectory() as tmp:
        t = Trainer(data, cfg, Path(tmp) / "t", body_model=ensure_models().root)
        for _ in range(warmup):
            t.step()
        rates = []
        for _ in range(3):
            t0 = time.perf_counter()
            for _ in range(iters):
                t.step()
            rates.append(iters / (time.perf_counter() - t0))
    waitpolicy.report(statistics.median(rates), "it/s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--data", type=Path, default=None, help="cache folder for the take")
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--gaussians", type=int, default=48_000, help="densified size (0: skip)")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--iters", type=int, default=40, help="iterations per variant per round")
    ap.add_argument("--warmup", type=int, default=80)
    ap.add_argument("--hog", type=int, default=0, help="busy-loop processes beside the bench")
    ap.add_argument("--wait-compare", action="store_true",
                    help="1 and 2 threads x OMP_WAIT_POLICY ACTIVE / PASSIVE, one case")
    ap.add_argument("--passes", type=int, default=3, help="--wait-compare: interleaved passes")
    ap.add_argument("--wait-child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    cache = args.data or Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) \
        / "telesplat" / "bench"
    data = bench_dataset(cache, args.frames)
    if args.wait_child:
        wait_child(data, min(args.warmup, 20), min(args.iters, 10))
        return
    if args.wait_compare:
        argv = [str(Path(__file__).resolve()), "--frames", str(args.frames),
                "--warmup", str(args.warmup), "--iters", str(args.iters)]
        if args.data:
            argv += ["--data", str(args.data)]
        print(f"training it/s, crop, no fine-tune, beside {args.hog} busy loop(s), "
              f"{os.cpu_count()} cores", flush=True)
        print(waitpolicy.compare(argv, passes=args.passes, hog=args.hog))
        return
    with waitpolicy.hogs(args.hog):
        run_bench(args, data)


def run_bench(args: argparse.Namespace, data: Path) -> None:
    print(f"torch {torch.__version__} ({torch.get_num_threads()} threads), numba "
          f"{numba.__version__} ({numba.get_num_threads()} threads), {os.cpu_count()} cores")
    with tempfile.TemporaryDirectory() as tmp:
        trainers = make_trainers(data, Path(tmp), args.warmup)
        print("\none Gaussian per triangle\n")
        print(table(measure(trainers, args.rounds, args.iters)), flush=True)
        if args.gaussians:
            for t in trainers.values():
                densify_to(t, args.gaussians)
                for _ in range(10):
                    t.step()
            print(f"\ndensified to {args.gaussians:,}\n")
            print(table(measure(trainers, args.rounds, args.iters)), flush=True)


if __name__ == "__main__":
    main()
