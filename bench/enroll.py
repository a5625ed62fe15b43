"""Enrollment against the multi-view recipe, on the software studio (issue 29's table).

The synthetic actor is filmed twice: by one fixed camera, turning through +-``--yaw`` deg and
gesturing (the enrollment video), and by the 17-camera studio doing the same gestures plus a
held-out take. The enrolled avatars (``telesplat enroll``'s pipeline: no true parameter is
read) and the avatar trained on the studio capture (16 cameras; the held-out camera is the
novel view) are both scored by ``avatar_core.metrics.evaluate`` on

- novel view: the studio's gesture take at its held-out camera (next to the front one: the
  seen side);
- held-out take: the studio's other take at every camera (the back too, which a +-90 deg
  turn never shows).

Both avatars are driven by the studio's (simulated-tracker) parameters; an enrolled avatar
keeps its own fitted betas. Tracking runs once; the variants (fine-tuning off, masks off,
a second seed) train from the same prepared take. Writes ``enroll.json`` and ``enroll.md``::

    .venv/bin/python bench/enroll.py --out out/enroll --iterations 300 --resolution 128
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


from avatar_core.dataset.loader import load_dataset  # noqa: E402
from avatar_core.enroll import EnrollConfig  # noqa: E402
from avatar_core.enroll.pipeline import prepare, train_prepared  # noqa: E402
from avatar_core.enroll.video import read_video  # noqa: E402
from avatar_core.metrics.evaluate import evaluate  # noqa: E402
from avatar_core.synth.capture import CaptureSpec, capture  # noqa: E402
from avatar_core.synth.enroll_video import (  # noqa: E402
    EnrollVideoSpec,
    film_enroll_video,
    true_alpha,
    write_true_params,
)
from avatar_core.synth.studio import StudioConfig  # noqa: E402
from avatar_core.train.config import preset  # noqa: E402
from avatar_core.train.trainer import Trainer  # noqa: E402

GESTURES = ("smile", "wave", "thumbs_up", "mouth_open")
HELD_OUT = ("peace", "grin")
VARIANTS = {  # name -> (fine_tune, masks, seed)
    "enrolled": (True, True, 0), "enrolled_s1": (True, True, 1),
    "no_finetune": (False, True, 0), "no_finetune_s1": (False, True, 1),
    "no_masks": (True, False, 0),
    # not enrollment: the take's true parameters, betas and focal swapped in for the fitted
    # ones (same frames and masks), to measure how much of the gap the tracking/fit makes
    "truth_params": (True, True, 0),
    # not enrollment: the actor's true coverage in place of the selfie masks (fitted params)
    "truth_masks": (True, True, 0)}
KEYS = ("psnr", "ssim", "l1")


def multiview_config(iterations: int, resolution: int, frames: int):
    """The quick recipe at this run's length (same density schedule rule as enrollment)."""
    base = preset("quick")
    it = iterations
    return replace(base, iterations=it, sh_degree=1, sh_interval=max(1, it // 6),
                   checkpoint_interval=it, progress_interval=max(1, it // 10),
                   lr=replace(base.lr, position_max_steps=it),
                   loss=replace(base.loss, lpips=False),
                   data=replace(base.data, target_size=resolution),
                   densify=replace(base.densify, from_iter=max(1, it // 10),
                                   until_iter=it * 8 // 10,
                                   interval=max(1, min(max(frames, it // 20), it // 4))))


def with_truth(prep, path: Path, spec: EnrollVideoSpec):
    """``prep`` with the take's true per-frame parameters, betas and focal length."""
    import math

    with np.load(path) as raw:
        truth = {k: np.asarray(raw[k]) for k in raw.files}
    params = [{k: truth[k][i] for k in prep.params[0]} for i in prep.indices]
    focal = 0.5 * spec.width / math.tan(math.radians(spec.fov_x_deg) / 2)
    return replace(prep, params=params, betas=truth["betas"][0], focal_px=focal)


def score(avatar: Path, data, protocol: str, drive_betas, stride: int) -> dict:
    drive = None
    if drive_betas is not None:
        drive = {}
        for seq in data.sequences:
            raw = {k: np.asarray(v) for k, v in data.params(seq).items()}
            raw["betas"] = np.asarray(drive_betas, dtype=np.float64)
            drive[seq] = raw
    res = evaluate(avatar, data, protocol, frame_stride=stride, drive=drive, max_images=0)
    return {k: res.metrics.get(k) for k in KEYS} | {"views": res.num_views}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--fps", type=float, default=8.0)
    ap.add_argument("--yaw", type=float, default=90.0)
    ap.add_argument("--studio-frames", type=int, default=12)
    ap.add_argument("--stride", type=int, default=3, help="evaluate every n-th frame")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    args = ap.parse_args()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    rows: dict[str, dict] = {}
    video = out / "take.mp4"
    take_spec = EnrollVideoSpec(seconds=args.seconds, fps=args.fps, width=2 * args.resolution,
                                height=3 * args.resolution // 2, yaw_deg=args.yaw,
                                gestures=GESTURES)
    if not video.exists():
        film_enroll_video(video, take_spec, params_out=out / "take_true.npz")
    if not (out / "take_true.npz").exists():
        write_true_params(out / "take_true.npz", take_spec)
    old = out / "enroll.json"
    if old.exists():  # rows of an earlier run (other variants) are kept
        rows.update(json.loads(old.read_text())["rows"])
    studio = out / "studio"
    if not (studio / "dataset.json").exists():
        capture(studio, CaptureSpec(sequences=(GESTURES, HELD_OUT), resolution=args.resolution,
                                    max_frames=args.studio_frames,
                                    studio=StudioConfig(fps=5.0)))
    data = load_dataset(studio)

    t0 = time.perf_counter()
    mv_dir = out / "multiview"
    frames = args.studio_frames
    if not (mv_dir / "avatar").exists():
        trainer = Trainer(studio, multiview_config(args.iterations, args.resolution, frames),
                          mv_dir)
        trainer.train()
    mv_time = json.loads((mv_dir / "avatar" / "avatar.json").read_text())["training"]["time_s"]
    rows["multiview"] = {"cameras": 16, "train_s": mv_time,
                         "novel_view": score(mv_dir / "avatar", data, "novel-view", None,
                                             args.stride),
                         "held_out": score(mv_dir / "avatar", data, "self-reenactment", None,
                                           args.stride)}
    print("multiview", rows["multiview"], f"{time.perf_counter() - t0:.0f}s", flush=True)

    decoded = read_video(video)
    rgb, fps = list(decoded.frames), decoded.fps
    base = EnrollConfig(iterations=args.iterations, resolution=args.resolution, min_frames=12)
    t0 = time.perf_counter()
    prep = prepare(rgb, fps, config=base)
    prep_s = time.perf_counter() - t0
    prep_nomask = None
    for name in args.variants.split(","):
        ft, masks, seed = VARIANTS[name]
        cfg = replace(base, fine_tune=ft, masks=masks, seed=seed)
        use = prep
        if not masks:  # the same tracked frames, without the masks
            prep_nomask = prep_nomask or replace(prep, masks=None)
            use = prep_nomask
        if name == "truth_params":
            use = with_truth(prep, out / "take_true.npz", take_spec)
        if name == "truth_masks":
            use = replace(prep, masks=true_alpha(take_spec, prep.indices))
        res = train_prepared(use, out / name, config=cfg)
        rows[name] = {"cameras": 1, "train_s": res.train["seconds"], "prepare_s": prep_s,
                      "frames": asdict(res.frames),
                      "yaw_range_deg": res.yaw_range_deg, "focal_px": res.focal_px,
                      "novel_view": score(res.package, data, "novel-view", res.betas,
                                          args.stride),
                      "held_out": score(res.package, data, "self-reenactment", res.betas,
                                        args.stride)}
        print(name, rows[name], flush=True)
    doc = {"args": {k: str(v) for k, v in vars(args).items()}, "rows": rows}
    (out / "enroll.json").write_text(json.dumps(doc, indent=1) + "\n")
    lines = ["| avatar | cameras | novel-view PSNR / SSIM / L1 | held-out take PSNR / SSIM / L1 "
             "| training time (s) |", "|---|---|---|---|---|"]
    for name, r in rows.items():
        def cell(m):
            return f"{m['psnr']:.2f} / {m['ssim']:.4f} / {m['l1']:.4f}"
        extra = f" + {r['prepare_s']:.0f} prepare" if "prepare_s" in r else ""
        lines.append(f"| {name} | {r['cameras']} | {cell(r['novel_view'])} | "
                     f"{cell(r['held_out'])} | {r['train_s']:.0f}{extra} |")
    (out / "enroll.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
