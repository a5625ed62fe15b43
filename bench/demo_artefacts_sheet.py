"""Before/after contact sheet from two ``bench/demo_artefacts.py`` runs' crops.

Each crop there is ``truth | render | error`` (same box in both runs: the boxes come from
the truth). A row here is ``truth | before | after | before error | after error``.

    python bench/demo_artefacts_sheet.py BEFORE_DIR AFTER_DIR --out SHEET.png \\
        --crops armpit_left_arms_raised_low_left hem_relaxed_cam08
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

GAP = 4  # px of white between tiles


def thirds(path: Path) -> list[np.ndarray]:
    image = cv2.imread(str(path))
    if image is None:
        raise FileNotFoundError(f"cannot read {path}")
    w = image.shape[1] // 3
    return [image[:, i * w:(i + 1) * w] for i in range(3)]


def row(before: Path, after: Path, height: int) -> np.ndarray:
    (truth, pred_b, err_b), (_, pred_a, err_a) = thirds(before), thirds(after)
    tiles = [truth, pred_b, pred_a, err_b, err_a]
    scale = height / truth.shape[0]
    size = (max(1, round(truth.shape[1] * scale)), height)
    gap = np.full((height, GAP, 3), 255, np.uint8)
    out = []
    for tile in tiles:
        out += [cv2.resize(tile, size, interpolation=cv2.INTER_NEAREST), gap]
    return np.concatenate(out[:-1], axis=1)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("before", type=Path)
    parser.add_argument("after", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--crops", nargs="+", required=True, help="crop names, no .png")
    parser.add_argument("--height", type=int, default=120, help="px per row")
    args = parser.parse_args(argv)
    rows = [row(args.before / "crops" / f"{c}.png", args.after / "crops" / f"{c}.png",
                args.height) for c in args.crops]
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, GAP), (0, width - r.shape[1]), (0, 0)), constant_values=255)
            for r in rows]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), np.concatenate(rows, axis=0))
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
