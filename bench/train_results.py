"""The synthetic benchmark: the full model against its ablations, and what accuracy costs in time.

For each model (full; no FLAME/MANO fusion; no parameter fine-tuning) it trains on the
dataset's `train` split, and at evenly spaced points of training exports the avatar and scores
it on a subset of the held-out `novel_view` views (PSNR / SSIM against training wall-clock,
against the Gaussian count, next to the render time). At the end every model is evaluated on
`novel_view` and `self_reenactment`, and the ablation table, the curves (PNG) and the raw
numbers (JSON) are written to --out. LPIPS is off here (no backbone weights can be fetched),
so there is no "without LPIPS" ablation.

    telesplat synth capture --out DATA --max-frames 60 --resolution 512 --holdout-cameras cam07 \
        --motions \
        "smile+grin+mouth_open+thumbs_up,peace+talk_calm+heart,sad+angry+clapping"
    .venv/bin/python bench/train_results.py DATA --out docs/results --preset quick \\
        [--iterations N] [--points 5] [--models full,no_fusion,no_finetune]

Accuracy against the number of Gaussians rendered (and render time) for a trained avatar:

    .venv/bin/python bench/train_results.py DATA --budget-curve AVATAR --out docs/results

Render times of the curve snapshots, re-measured side by side after training:

    .venv/bin/python bench/train_results.py DATA --render-times out/results_work --out docs/results

Models can also be trained by separate runs (one --models each, own --out) and merged:

    .venv/bin/python bench/train_results.py --merge OUT_FULL OUT_NO_FUSION ... --out docs/results
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from avatar_core.dataset.loader import load_dataset  # noqa: E402
from avatar_core.metrics.evaluate import evaluate  # noqa: E402
from avatar_core.metrics.report import (  # noqa: E402
    ablation_json,
    ablation_table,
    ablation_table_from_json,
)
from avatar_core.train.config import TrainConfig, preset  # noqa: E402
from avatar_core.train.trainer import Trainer  # noqa: E402


def variants(base: TrainConfig) -> dict[str, tuple[TrainConfig, bool]]:
    """name -> (config, fusion at evaluation)."""
    return {
        "full": (base, True),
        "no_fusion": (replace(base, data=replace(base.data, fusion=False)), False),
        "no_finetune": (replace(base, finetune=replace(base.finetune, enabled=False)), True),
        # the paper's fixed fine-tuning rates, against the rates scaled to the run
        "finetune_fixed": (replace(base, finetune=replace(base.finetune, schedule="fixed")),
                           True),
    }


def train_with_curve(name: str, config: TrainConfig, fusion: bool, data, out: Path,
                     points: int, curve_views: int) -> tuple[Path, list[dict]]:
    trainer = Trainer(data, config, out / name)
    curve = []
    stops = [round(config.iterations * (i + 1) / points) for i in range(points)]
    # A snapshot right after a scheduled opacity reset scores a near-transparent avatar
    # (~10 dB): take that point one iteration earlier, before the reset.
    d = config.densify
    stops = [s - 1 if d.enabled and s < d.until_iter and s % d.opacity_reset_interval == 0
             else s for s in stops]
    for stop in stops:
        t0 = time.perf_counter()
        trainer.train(stop_at=stop)
        print(f"[{name}] {stop} its, {time.perf_counter() - t0:.0f} s", flush=True)
        snap = trainer.export(out / name / f"snapshot_{stop:06d}")
        res = evaluate(snap, data, "novel-view", fusion=fusion, max_views=curve_views,
                       frame_stride=10)
        curve.append({"iteration": stop, "train_s": round(trainer.train_time_s, 1),
                      "num_gaussians": trainer.num_gaussians,
                      "psnr": res.metrics["psnr"], "ssim": res.metrics["ssim"],
                      "render_ms": res.timing.get("render_ms_median")})
        print(f"[{name}] {curve[-1]}", flush=True)
    final = trainer.export(out / name / "avatar_final")
    return final, curve


def plot(curves: dict[str, list[dict]], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for name, rows in curves.items():
        axes[0].plot([r["train_s"] / 60 for r in rows], [r["psnr"] for r in rows], "o-",
                     label=name)
        axes[1].plot([r["num_gaussians"] for r in rows], [r["psnr"] for r in rows], "o-",
                     label=name)
        axes[2].plot([r["num_gaussians"] for r in rows], [r["render_ms"] for r in rows], "o-",
                     label=name)
    axes[0].set(xlabel="training wall-clock (min, 1 thread)", ylabel="novel-view PSNR (dB)")
    axes[1].set(xlabel="Gaussians after training", ylabel="novel-view PSNR (dB)")
    axes[2].set(xlabel="Gaussians", ylabel="render ms / view (512x512, cpu)")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(out / "accuracy_vs_time.png", dpi=110)


def render_times(work: Path, data, out: Path, rounds: int = 7) -> None:
    """Render ms of every curve snapshot, re-measured side by side on a quiet machine: the
    snapshots of all models posed once, then rendered in interleaved rounds (the training
    runs' own timings were taken while three trainings shared the cores)."""
    import numpy as np
    import torch

    from avatar_core.gaussians.loading import load_avatar
    from avatar_core.render.rasterize import rasterize
    from avatar_core.render.types import RenderRequest

    key = data.views("novel_view")[0]
    camera = data.view(*key).camera
    posed = {}
    for snap in sorted(work.glob("*/snapshot_*")):
        loaded = load_avatar(str(snap))
        posed[(snap.parent.name, int(snap.name.split("_")[1]))] = loaded.animator.pose({})
    times: dict = {k: [] for k in posed}
    with torch.no_grad():
        for p in posed.values():  # warm-up (numba compiles once)
            rasterize(p.gaussians, camera, RenderRequest())
        for _ in range(rounds):
            for k, p in posed.items():
                t0 = time.perf_counter()
                rasterize(p.gaussians, camera, RenderRequest())
                times[k].append((time.perf_counter() - t0) * 1e3)
    js = json.loads((out / "results.json").read_text())
    for name, rows in js["curves"].items():
        for row in rows:
            ms = times.get((name, row["iteration"]))
            if ms:
                row["render_ms"] = round(float(np.median(ms)), 2)
    js["render_ms_note"] = (f"median of {rounds} interleaved renders per snapshot, 512x512, "
                            "cpu backend, one process, after training")
    (out / "results.json").write_text(json.dumps(js, indent=2))
    plot(js["curves"], out)
    for k, ms in times.items():
        print(k, round(float(np.median(ms)), 2), "ms")


BUDGETS = (0.05, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0)


def budget_curve(avatar: Path, data, out: Path, views: int, stride: int) -> list[dict]:
    """Novel-view PSNR/SSIM and render ms of one trained avatar when only a fraction of its
    visible Gaussians (the most important: opacity x footprint) is rendered."""
    rows = []
    for budget in BUDGETS:
        res = evaluate(avatar, data, "novel-view", max_views=views, frame_stride=stride,
                       budget=None if budget == 1.0 else budget)
        rows.append({"budget": budget, "psnr": res.metrics["psnr"], "ssim": res.metrics["ssim"],
                     "render_ms": res.timing.get("render_ms_median")})
        print(rows[-1], flush=True)
    out.mkdir(parents=True, exist_ok=True)
    (out / "budget_curve.json").write_text(json.dumps(rows, indent=2))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ax[0].plot([r["render_ms"] for r in rows], [r["psnr"] for r in rows], "o-")
    ax[0].set(xlabel="render ms / view (512x512, cpu)", ylabel="novel-view PSNR (dB)")
    ax[1].plot([100 * r["budget"] for r in rows], [r["ssim"] for r in rows], "o-")
    ax[1].set(xlabel="% of visible Gaussians rendered", ylabel="novel-view SSIM")
    for a in ax:
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "budget_curve.png", dpi=110)
    return rows


def merge(runs: list[Path], out: Path) -> None:
    """One table, one plot and one results.json from runs that each trained some models."""
    curves, rows, protocols, columns, meta = {}, {}, [], None, {}
    for run in runs:
        js = json.loads((run / "results.json").read_text())
        curves.update(js["curves"])
        rows.update(js["ablation"]["rows"])
        protocols += [p for p in js["ablation"]["protocols"] if p not in protocols]
        columns = js["ablation"]["columns"]
        meta = {k: js[k] for k in ("preset", "iterations")}
    table = {"protocols": protocols, "columns": columns, "rows": rows}
    out.mkdir(parents=True, exist_ok=True)
    (out / "ablation.md").write_text(ablation_table_from_json(table) + "\n")
    (out / "results.json").write_text(json.dumps({"ablation": table, "curves": curves, **meta},
                                                 indent=2))
    plot(curves, out)
    print(ablation_table_from_json(table))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", type=Path, nargs="?")
    ap.add_argument("--merge", type=Path, nargs="+", default=None,
                    help="--out folders of earlier runs to merge into --out")
    ap.add_argument("--budget-curve", type=Path, default=None, metavar="AVATAR",
                    help="only the render-budget curve of this trained avatar")
    ap.add_argument("--render-times", type=Path, default=None, metavar="WORK",
                    help="re-time the curve snapshots under WORK into --out/results.json")
    ap.add_argument("--out", type=Path, default=Path("docs/results"))
    ap.add_argument("--work", type=Path, default=Path("out/results_work"))
    ap.add_argument("--preset", default="quick")
    ap.add_argument("--iterations", type=int, default=None)
    ap.add_argument("--points", type=int, default=5)
    ap.add_argument("--curve-views", type=int, default=8)
    ap.add_argument("--eval-stride", type=int, default=5)
    ap.add_argument("--models", default="full,no_fusion,no_finetune")
    ap.add_argument("--seed", type=int, default=None, help="training seed (view order)")
    ap.add_argument("--target-size", type=int, default=None,
                    help="train at this longest image side (px)")
    ap.add_argument("--finetune-schedule", choices=["fixed", "budget"], default=None,
                    help="fine-tuning rates: fixed (MVFGA's) or scaled to the iterations")
    ap.add_argument("--finetune-reach", default=None, metavar="DEG,EXPR,M",
                    help="budget schedule reach: body pose deg, expression, translation m")
    ap.add_argument("--train-only", action="store_true",
                    help="export the avatars (and fine-tuned parameters) under --work; "
                         "evaluate later (bench/noisy_results.py)")
    args = ap.parse_args()
    if args.merge:
        merge(args.merge, args.out)
        return
    if args.dataset is None:
        ap.error("give a dataset (or --merge)")
    data = load_dataset(args.dataset)
    if args.render_times:
        render_times(args.render_times, data, args.out)
        return
    if args.budget_curve:
        budget_curve(args.budget_curve, data, args.out, args.curve_views * 2, args.eval_stride)
        return
    base = preset(args.preset)
    if args.iterations:
        base = replace(base, iterations=args.iterations,
                       lr=replace(base.lr, position_max_steps=args.iterations))
    if args.seed is not None:
        base = replace(base, seed=args.seed)
    if args.target_size:
        base = replace(base, data=replace(base.data, target_size=args.target_size))
    if args.finetune_schedule:
        base = replace(base, finetune=replace(base.finetune, schedule=args.finetune_schedule))
    if args.finetune_reach:
        deg, expr, metres = (float(v) for v in args.finetune_reach.split(","))
        base = replace(base, finetune=replace(base.finetune, reach_body_pose_deg=deg,
                                              reach_expression=expr, reach_transl=metres))
    args.out.mkdir(parents=True, exist_ok=True)
    curves, results = {}, {}
    chosen = variants(base)
    for name in args.models.split(","):
        config, fusion = chosen[name]
        final, curves[name] = train_with_curve(name, config, fusion, data, args.work,
                                               args.points, args.curve_views)
        if args.train_only:
            (args.out / f"{name}_curve.json").write_text(json.dumps(curves[name], indent=2))
            continue
        results[name] = {}
        for protocol in ("novel-view", "self-reenactment"):
            results[name][protocol] = evaluate(
                final, data, protocol, fusion=fusion, frame_stride=args.eval_stride,
                out_dir=args.out / name / protocol, max_images=4)
    if args.train_only:
        return
    (args.out / "ablation.md").write_text(ablation_table(results) + "\n")
    (args.out / "results.json").write_text(json.dumps(
        {"ablation": ablation_json(results), "curves": curves, "preset": args.preset,
         "iterations": base.iterations}, indent=2))
    plot(curves, args.out)
    print(ablation_table(results))


if __name__ == "__main__":
    main()
