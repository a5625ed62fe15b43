"""The noisy-tracker benchmark: what fine-tuning buys, and what a webcam viewer sees.

Evaluates the avatars that ``bench/train_results.py --train-only`` trained (one ``--work``
folder per seed, one sub-folder per model) on a capture made with ``--tracker-noise``:

- novel view (the training takes at the held-out camera) driven three ways: by the tracked
  parameters (fused as the model was trained), by the model's fine-tuned parameters (when it
  fine-tuned), and by the true parameters (the capture's ``true_params.npz``);
- self-reenactment (the held-out take, every camera) by the tracked and the true parameters;
- the webcam protocol (``avatar_core.metrics.webcam``) for ``--webcam-model`` of the first
  seed: true parameters / simulated trackers + fusion / webcam tracking, one table.

AKD is against the true body throughout. Writes ``noisy.json``, ``ablation.md`` and
``webcam/`` to ``--out``::

    telesplat synth capture --out DATA --cameras 12 --resolution 384 --max-frames 40 \\
        --motions "smile+grin+mouth_open+thumbs_up,peace+talk_calm+heart,sad+angry+clapping" \\
        --cross-identity -1 --tracker-noise studio --holdout-cameras cam05
    for s in 0 1; do .venv/bin/python bench/train_results.py DATA --preset demo \\
        --iterations 1500 --target-size 128 --finetune-schedule budget --seed $s \\
        --models full,no_finetune,no_fusion --points 1 --train-only \\
        --work out/noisy/work_s$s --out out/noisy/res_s$s & done; wait
    .venv/bin/python bench/noisy_results.py DATA --work out/noisy/work_s0 out/noisy/work_s1 \\
        --out docs/results/noisy --size 128
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from avatar_core.dataset.loader import load_dataset  # noqa: E402
from avatar_core.metrics.evaluate import evaluate  # noqa: E402
from avatar_core.metrics.webcam import (  # noqa: E402
    evaluate_webcam,
    true_params_path,
    webcam_markdown,
)

FUSION = {"no_fusion": False}  # every other model was trained (and is driven) with fusion
KEYS = ("psnr", "ssim", "l1", "akd_face", "akd_hands", "akd_torso", "tje")


def true_params(data) -> dict[str, dict[str, np.ndarray]]:
    out = {}
    for seq in data.sequences:
        path = true_params_path(data.root, seq)
        if path.is_file():
            with np.load(path) as raw:
                out[seq] = {k: np.asarray(raw[k]) for k in raw.files}
    if not out:
        raise SystemExit(f"{data.root} has no true_params.npz: capture with --tracker-noise")
    return out


def fine_tuned(model_dir: Path) -> dict[str, dict[str, np.ndarray]] | None:
    folder = model_dir / "finetuned_params"
    if not folder.is_dir():
        return None
    return {p.stem: dict(np.load(p)) for p in sorted(folder.glob("*.npz"))}


def evaluate_model(model_dir: Path, data, truth, size: int | None, stride: int,
                   sr_stride: int) -> dict:
    avatar = model_dir / "avatar_final"
    fusion = FUSION.get(model_dir.name, True)
    drives = {"novel-view": {"tracked": None, "true": truth},
              "self-reenactment": {"tracked": None, "true": truth}}
    tuned = fine_tuned(model_dir)
    if tuned:
        drives["novel-view"]["fine-tuned"] = tuned
    row: dict = {}
    for protocol, by_drive in drives.items():
        for drive, params in by_drive.items():
            t0 = time.perf_counter()
            res = evaluate(avatar, data, protocol, fusion=fusion,
                           frame_stride=stride if protocol == "novel-view" else sr_stride,
                           size=size, drive=params, truth=truth)
            row[f"{protocol}/{drive}"] = {k: res.metrics.get(k) for k in KEYS}
            row[f"{protocol}/{drive}"]["views"] = res.num_views
            print(f"[{model_dir.parent.name}/{model_dir.name}] {protocol} {drive}: "
                  f"{row[f'{protocol}/{drive}']} ({time.perf_counter() - t0:.0f} s)", flush=True)
    return row


def _f(v, digits=2) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def table(results: dict) -> str:
    cols = [("novel-view/tracked", "psnr", "NV PSNR tracked"),
            ("novel-view/fine-tuned", "psnr", "NV PSNR fine-tuned params"),
            ("novel-view/true", "psnr", "NV PSNR true params"),
            ("novel-view/tracked", "ssim", "NV SSIM tracked"),
            ("self-reenactment/tracked", "psnr", "SR PSNR tracked"),
            ("self-reenactment/true", "psnr", "SR PSNR true params"),
            ("novel-view/tracked", "akd_hands", "NV AKD hands tracked (px)")]
    lines = ["| model | seed | " + " | ".join(c[2] for c in cols) + " |",
             "|---|---:|" + "---:|" * len(cols)]
    for key, row in sorted(results.items()):
        seed, model = key.split("/")
        cells = [_f(row.get(d, {}).get(k), 4 if k == "ssim" else 2) for d, k, _ in cols]
        lines.append(f"| {model} | {seed} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--work", type=Path, nargs="+", required=True,
                    help="bench/train_results.py --work folders, one per seed")
    ap.add_argument("--models", default="full,no_finetune,no_fusion,finetune_fixed")
    ap.add_argument("--out", type=Path, default=Path("docs/results/noisy"))
    ap.add_argument("--size", type=int, default=None, help="score width (default: dataset's)")
    ap.add_argument("--stride", type=int, default=2, help="novel view: every K-th frame")
    ap.add_argument("--sr-stride", type=int, default=5,
                    help="self-reenactment (all cameras): every K-th frame")
    ap.add_argument("--webcam-model", default="full")
    ap.add_argument("--webcam-only", action="store_true")
    ap.add_argument("--skip-webcam", action="store_true")
    args = ap.parse_args()
    data = load_dataset(args.dataset)
    truth = true_params(data)
    args.out.mkdir(parents=True, exist_ok=True)
    js_path = args.out / "noisy.json"
    doc = json.loads(js_path.read_text()) if js_path.is_file() else {}
    if not args.webcam_only:
        results = doc.setdefault("ablation", {})  # runs evaluated earlier are kept
        for work in args.work:
            for model in args.models.split(","):
                if (work / model / "avatar_final").is_dir():
                    results[f"{work.name}/{model}"] = evaluate_model(
                        work / model, data, truth, args.size, args.stride, args.sr_stride)
                    js_path.write_text(json.dumps(doc, indent=2) + "\n")
        (args.out / "ablation.md").write_text(table(results))
        print(table(results))
    if not args.skip_webcam:
        avatar = args.work[0] / args.webcam_model / "avatar_final"
        res = evaluate_webcam(avatar, data, size=args.size, out_dir=args.out / "webcam",
                              max_images=3)
        doc["webcam"] = res.to_dict()
        print(webcam_markdown(res))
    doc["settings"] = {"size": args.size, "stride": args.stride, "sr_stride": args.sr_stride,
                       "dataset": str(args.dataset)}
    js_path.write_text(json.dumps(doc, indent=2) + "\n")


if __name__ == "__main__":
    main()
