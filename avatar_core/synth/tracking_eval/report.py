"""Reporting: markdown tables, the landmark offset table and the contact sheet."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .metrics import GROUPS, HAND_SIDES
from .run import ClipResult

FACE_COLOUR, POSE_COLOUR = (0, 230, 255), (255, 160, 0)
HAND_COLOUR = {"left_hand": (255, 0, 255), "right_hand": (0, 0, 255)}
POSE_DRAW_EDGES = [(11, 12), (11, 13), (13, 15), (12, 14), (14, 16), (11, 23), (12, 24),
                   (23, 24)]


def draw_fit(frame: np.ndarray, fitted_px: np.ndarray, seen: dict[str, bool],
             label: str) -> np.ndarray:
    from avatar_core.track.draw import HAND_EDGES
    from avatar_core.track.fit import correspondence as cor

    img = frame.copy()

    def pt(p):
        return int(round(float(p[0]))), int(round(float(p[1])))

    pose = fitted_px[cor.POSE_SLICE]
    for a, b in POSE_DRAW_EDGES:
        if np.isfinite(pose[[a, b]]).all():
            cv2.line(img, pt(pose[a]), pt(pose[b]), POSE_COLOUR, 2, cv2.LINE_AA)
    for g in ("left_hand", "right_hand"):
        if not seen.get(g):
            continue
        hand = fitted_px[cor.GROUP_SLICES[g]]
        for a, b in HAND_EDGES:
            cv2.line(img, pt(hand[a]), pt(hand[b]), HAND_COLOUR[g], 2, cv2.LINE_AA)
    if seen.get("face"):
        for q in fitted_px[cor.FACE_SLICE]:
            cv2.circle(img, pt(q), 2, FACE_COLOUR, -1, cv2.LINE_AA)
    cv2.putText(img, label, (10, 36), cv2.FONT_HERSHEY_SIMPLEX, 1.1, (255, 255, 255), 5,
                cv2.LINE_AA)
    cv2.putText(img, label, (10, 36), cv2.FONT_HERSHEY_SIMPLEX, 1.1, (0, 0, 0), 2, cv2.LINE_AA)
    return img


def contact_sheet(results: list[ClipResult], out: Path, cols: int = 3,
                  scale: float = 0.5) -> Path:
    tiles = []
    for r in results:
        if not r.frames_bgr:
            continue
        i = len(r.frames_bgr) // 2  # the clips hold their key pose in the middle
        seen = {g: bool(r.seen[g][i]) for g in GROUPS}
        hands = "+".join(s[0].upper() + (" (wrong side)" if r.swapped[f"{s}_hand"][i] else "")
                         for s in HAND_SIDES if seen[f"{s}_hand"]) or "none"
        img = draw_fit(r.frames_bgr[i], r.fitted_px[i], seen, f"{r.name}, hands: {hands}")
        tiles.append(cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA))
    while len(tiles) % cols:
        tiles.append(np.full_like(tiles[0], 255))
    rows = [np.concatenate(tiles[k:k + cols], 1) for k in range(0, len(tiles), cols)]
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), np.concatenate(rows, 0))
    return out


def _fmt(x: float, digits: int = 1) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"


def _pct(x: float) -> str:
    return "-" if not np.isfinite(x) else f"{100 * x:.0f}%"


def overall(results: list[ClipResult]) -> dict[str, float]:
    """Frame-weighted means over clips (each metric over the clips where it is defined,
    weighted by the frames it was computed on)."""
    out: dict[str, float] = {}
    keys = results[0].metrics.keys()
    for k in keys:
        vals, wts = [], []
        for r in results:
            v = r.metrics.get(k, float("nan"))
            if np.isfinite(v):
                if k.startswith("akd_") and not k.startswith("akd_n_"):
                    g = k[4:]
                    w = r.metrics.get(f"akd_n_{g}", 0)
                elif k.startswith("det_") and k.endswith("hand"):
                    w = int(r.in_view[k[4:]].sum())
                elif k == "wrong_side":
                    w = r.metrics["hand_reports"]
                else:
                    w = r.frames
                if w:
                    vals.append(v)
                    wts.append(w)
        out[k] = float(np.average(vals, weights=wts)) if vals else float("nan")
    out["frames"] = sum(r.frames for r in results)
    return out


def tables(results: list[ClipResult]) -> str:
    rows = [(r.name, r.frames, r.metrics) for r in results]
    rows.append(("**all**", sum(r.frames for r in results), overall(results)))
    lines = ["| clip | frames | face | left hand (in view) | right hand (in view) | "
             "hands on the wrong side | pose | AKD face | AKD L hand | AKD R hand | AKD torso |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, n, m in rows:
        lines.append(
            f"| {name} | {n} | {_pct(m['det_face'])} | {_pct(m['det_left_hand'])} "
            f"({_pct(m['in_view_left_hand'])}) | {_pct(m['det_right_hand'])} "
            f"({_pct(m['in_view_right_hand'])}) | {_pct(m['wrong_side'])} | "
            f"{_pct(m['det_pose'])} | "
            f"{_fmt(m['akd_face'], 2)} | {_fmt(m['akd_left_hand'])} | "
            f"{_fmt(m['akd_right_hand'])} | {_fmt(m['akd_torso'])} |")
    lines += ["", "| clip | head deg | jaw deg (true max) | expr. landmarks mm (expr. motion) | "
                  "elbow flex deg | wrist deg | fingers deg (mean hand) | TJE px raw | "
                  "TJE px One Euro | TJE face raw / One Euro | track / +fit ms | FPS |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, _, m in rows:
        lines.append(
            f"| {name} | {_fmt(m['head_deg'])} | {_fmt(m['jaw_deg'])} "
            f"({_fmt(m['jaw_true_max_deg'])}) | {_fmt(m['expr_mm'])} "
            f"({_fmt(m['expr_motion_mm'])}) | {_fmt(m['elbow_deg'])} | "
            f"{_fmt(m['wrist_deg'])} | {_fmt(m['finger_deg'])} "
            f"({_fmt(m['finger_mean_hand_deg'])}) | {_fmt(m.get('tje_raw', np.nan), 2)} | "
            f"{_fmt(m.get('tje_smooth', np.nan), 2)} | "
            f"{_fmt(m.get('tje_face_raw', np.nan), 2)} / "
            f"{_fmt(m.get('tje_face_smooth', np.nan), 2)} | {_fmt(m['track_ms'], 0)} / "
            f"{_fmt(m['ms'], 0)} | "
            f"{_fmt(1e3 / m['ms'])} |")
    return "\n".join(lines)


# Landmark classes for the offset table: (name, fitter-layout rows).
def _offset_classes() -> list[tuple[str, list[int]]]:
    from avatar_core.track.fit import correspondence as cor

    f, lh, rh, p = (cor.FACE_SLICE.start, cor.LEFT_HAND_SLICE.start,
                    cor.RIGHT_HAND_SLICE.start, cor.POSE_SLICE.start)
    return [("face contour (iBUG 0-16)", [f + k for k in range(17)]),
            ("face brows, nose, eyes (17-47)", [f + k for k in range(17, 48)]),
            ("face mouth (48-67)", [f + k for k in range(48, 68)]),
            ("hand wrists", [lh, rh]),
            ("hand finger joints", [s + k for s in (lh, rh) for k in range(1, 21)
                                    if k % 4]),
            ("hand fingertips", [s + k for s in (lh, rh) for k in (4, 8, 12, 16, 20)]),
            ("pose nose + eyes", [p + 0, p + 2, p + 5]), ("pose ears", [p + 7, p + 8]),
            ("pose shoulders", [p + 11, p + 12]), ("pose elbows", [p + 13, p + 14]),
            ("pose wrists", [p + 15, p + 16]), ("pose hips", [p + 23, p + 24])]


def offset_table(results: list[ClipResult]) -> str:
    """How far the tracked landmarks lie from the true model keypoints they are matched to
    (the fitter's correspondences), before any fitting: a bias here is a landmark-definition
    mismatch the fit cannot undo. dx is signed outward (away from the midline: the subject's
    left is the image's right) for points with a side, y down."""
    from avatar_core.track.fit import correspondence as cor

    off = np.concatenate([np.stack(r.offsets) for r in results if r.offsets])  # [N, K, 2]
    lines = ["| landmarks | frames x points | mean abs px | mean dx out px | mean dy px |",
             "|---|---:|---:|---:|---:|"]
    side = np.zeros(cor.NUM_KEYPOINTS)
    side[cor.FACE_SLICE.start:cor.FACE_SLICE.start + 8] = -1.0  # iBUG 0-7: the right cheek
    side[cor.FACE_SLICE.start + 9:cor.FACE_SLICE.start + 17] = 1.0
    for sl, s in ((cor.LEFT_HAND_SLICE, 1.0), (cor.RIGHT_HAND_SLICE, -1.0)):
        side[sl] = s
    for k, name in enumerate(cor.POSE_MP_TO_SMPLX):
        if name and ("left" in name or name.endswith((":leye", ":lear"))):
            side[cor.POSE_SLICE.start + k] = 1.0
        elif name and ("right" in name or name.endswith((":reye", ":rear"))):
            side[cor.POSE_SLICE.start + k] = -1.0
    for name, rows in _offset_classes():
        d = off[:, rows]  # [N, R, 2]
        ok = np.isfinite(d).all(-1)
        if not ok.any():
            lines.append(f"| {name} | 0 | - | - | - |")
            continue
        out_x = (d[..., 0] * side[rows][None])[ok]
        lines.append(f"| {name} | {int(ok.sum())} | {np.linalg.norm(d[ok], axis=-1).mean():.1f} "
                     f"| {out_x.mean() if side[rows].any() else float('nan'):.1f} "
                     f"| {d[..., 1][ok].mean():.1f} |")
    return "\n".join(lines).replace("| nan |", "| - |")
