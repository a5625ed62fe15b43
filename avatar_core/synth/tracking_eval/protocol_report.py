"""The studio webcam protocol over identities x framings (`run_protocol`) and its report
(`protocol_markdown`, `write_protocol`): the drive table with the part attribution, each
condition's PSNR, the landmark groups' presence and the One Euro jitter-vs-lag curve."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .protocol import (
    CURVE_SETTINGS,
    DEFAULT_DRIVES,
    DEFAULT_FRAMINGS,
    FRAMINGS,
    MIN_TAKE_S,
    TAKE,
    Condition,
    Progress,
    RunResult,
    check_drives,
    motion_of_frames,
    run_condition,
)
from .protocol_drives import DRIVE_LABELS

METRIC_KEYS = ("psnr", "root", "shoulders", "elbows", "wrists", "neck_head", "upper_arms",
               "forearms", "jitter_px", "fit_ms")


def load_runs(paths: Sequence[str | Path]) -> list[RunResult]:
    """The replayed runs of each runs.pkl in `paths` (bench/webcam_replay.py --replay), in
    order: our own pickles, never a stranger's file."""
    import pickle

    runs: list[RunResult] = []
    for path in paths:
        with open(path, "rb") as f:
            runs.extend(pickle.load(f))  # noqa: S301 (our own file)
    return runs


def _weighted(rows: list[tuple[float, int]]) -> float:
    vals = [(v, w) for v, w in rows if v is not None and np.isfinite(v) and w]
    return float(np.average([v for v, _ in vals], weights=[w for _, w in vals])) if vals \
        else float("nan")


def _presence(runs: list[RunResult]) -> dict[str, float]:
    """Face and pose: fraction of frames; each hand: of the frames it is wholly in view."""
    out = {}
    for g in ("face", "pose"):
        out[g] = float(np.mean(np.concatenate([r.seen[g] for r in runs])))
    for g in ("left_hand", "right_hand"):
        seen = np.concatenate([r.seen[g] for r in runs])
        view = np.concatenate([r.in_view[g] for r in runs])
        out[g] = float(seen[view].mean()) if view.any() else float("nan")
        out[f"{g}_in_view"] = float(view.mean())
        placed = [getattr(r, "placed", {}).get(g) for r in runs]
        if all(p is not None for p in placed):  # runs from before the pose's hand points
            placed = np.concatenate(placed)
            out[f"{g}_placed"] = float(placed[view].mean()) if view.any() else float("nan")
    return out


def summarise(runs: list[RunResult]) -> dict[str, Any]:
    drives = list(runs[0].metrics)
    overall = {d: {k: _weighted([(r.metrics[d].get(k), len(r.truth)) for r in runs])
                   for k in METRIC_KEYS} for d in drives}
    curve = []
    for j, setting in enumerate(runs[0].curve):
        row = {k: setting[k] for k in ("min_cutoff", "beta")}
        for k in setting:
            if k not in row:
                row[k] = _weighted([(r.curve[j][k], len(r.truth)) for r in runs if r.curve])
        curve.append(row)
    per_motion: dict[str, dict[str, float]] = {}
    for name in TAKE:
        per_motion[name] = {}
        for d in drives:
            vals = np.concatenate([np.asarray(r.psnr[d])[np.asarray(
                motion_of_frames(TAKE, r.fps, len(r.truth), r.start_frame)) == name]
                for r in runs])
            vals = vals[np.isfinite(vals)]
            per_motion[name][d] = float(vals.mean()) if len(vals) else float("nan")
    return {
        "take": list(TAKE), "fps": runs[0].fps, "per_motion_psnr": per_motion,
        "seconds": [len(r.truth) / r.fps for r in runs],
        "conditions": [{"identity": r.condition.identity,
                        "framing": r.condition.framing_label,
                        "frames": len(r.truth), "metrics": r.metrics,
                        "presence": _presence([r]),
                        "track_ms": float(np.median(r.track_ms[1:] or r.track_ms))}
                       for r in runs],
        "overall": overall, "presence": _presence(runs), "curve": curve,
        "track_ms": float(np.median(np.concatenate([r.track_ms[1:] for r in runs])))
        if any(len(r.track_ms) > 1 for r in runs) else float("nan")}


def run_protocol(identities: Sequence[int] = (0, 1), framings: Sequence[str] = DEFAULT_FRAMINGS,
                 fps: float = 15.0, *, max_frames: int | None = None,
                 score_size: tuple[int, int] = (320, 240),
                 drives: Sequence[str] = DEFAULT_DRIVES,
                 model_dir=None, curve: bool = True, start_frame: int = 0,
                 runs_out: list[RunResult] | None = None,
                 progress: Progress | None = None) -> dict[str, Any]:
    """Every identity in every framing (`run_condition`), summarised (`summarise`);
    `runs_out` receives the per-frame results."""
    if fps <= 0 or not identities or not framings:
        raise ValueError("fps must be > 0, with at least one identity and one framing")
    unknown = [f for f in framings if f not in FRAMINGS]
    if unknown:
        raise ValueError(f"unknown framing(s) {unknown}; known: {', '.join(FRAMINGS)}")
    check_drives(drives)
    runs = [run_condition(Condition(i, f), fps, max_frames=max_frames, score_size=score_size,
                          drives=drives, model_dir=model_dir, curve=curve,
                          start_frame=start_frame, progress=progress)
            for i in identities for f in framings]
    if runs_out is not None:
        runs_out.extend(runs)
    return summarise(runs)


def _f(x: Any, digits: int = 1) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"


def protocol_markdown(summary: dict[str, Any]) -> str:
    secs = summary["seconds"]
    short = "" if min(secs) >= MIN_TAKE_S else f" (shorter than the protocol's {MIN_TAKE_S:.0f} s)"
    conds = ", ".join(f"identity {c['identity']} {c['framing']}" for c in summary["conditions"])
    lines = [f"Take `{'+'.join(summary['take'])}`, {min(secs):.1f} s at {summary['fps']:g} fps"
             f"{short}; {conds}. PSNR (dB) at the score camera against the studio actor "
             "posed by the truth (the ideal avatar: true parameters are exact); angles in "
             "degrees; jitter = keypoint TJE px at the score camera; fit ms = median per frame.",
             "Upper arm / forearm: the bones' world directions (what the landmarks show), "
             "beside the local joint angles (which also carry the arm's twist).",
             "", "| drive | PSNR | root° | shoulders° | elbows° | neck/head° | wrists° | "
             "upper arm / forearm dir° | jitter px | fit ms/frame |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
             "| true parameters | exact | 0 | 0 | 0 | 0 | 0 | 0 / 0 | 0 | - |"]
    for d, m in summary["overall"].items():
        lines.append(f"| {DRIVE_LABELS.get(d, d)} | {_f(m['psnr'], 2)} | {_f(m['root'])} | "
                     f"{_f(m['shoulders'])} | {_f(m['elbows'])} | {_f(m['neck_head'])} | "
                     f"{_f(m.get('wrists'))} | "
                     f"{_f(m['upper_arms'])} / {_f(m['forearms'])} | "
                     f"{_f(m['jitter_px'], 2)} | {_f(m['fit_ms'])} |")
    drives = list(summary["overall"])
    lines += ["", "PSNR per condition (dB):", "",
              "| identity | framing | frames | " + " | ".join(DRIVE_LABELS.get(d, d)
                                                           for d in drives) + " |",
              "|---:|---|---:|" + "---:|" * len(drives)]
    for c in summary["conditions"]:
        lines.append(f"| {c['identity']} | {c['framing']} | {c['frames']} | "
                     + " | ".join(_f(c["metrics"][d]["psnr"], 2) for d in drives) + " |")
    if summary.get("per_motion_psnr"):
        lines += ["", "PSNR per motion of the take (dB, all conditions):", "",
                  "| motion | " + " | ".join(DRIVE_LABELS.get(d, d) for d in drives) + " |",
                  "|---|" + "---:|" * len(drives)]
        for name, row in summary["per_motion_psnr"].items():
            lines.append(f"| {name} | " + " | ".join(_f(row.get(d), 2) for d in drives) + " |")
    lines += ["", "Presence (live tracker; a hand over the frames where all its true keypoints "
                  "are inside the image, the share of such frames in brackets):", "",
              "| identity | framing | face | pose | left hand | right hand | left / right "
              "hand placed (own or pose points) | track ms |",
              "|---:|---|---:|---:|---:|---:|---:|---:|"]
    pct = lambda x: "-" if not np.isfinite(x) else f"{100 * x:.0f}%"  # noqa: E731
    for c in summary["conditions"]:
        p = c["presence"]
        lines.append(f"| {c['identity']} | {c['framing']} | {pct(p['face'])} | "
                     f"{pct(p['pose'])} | {pct(p['left_hand'])} ({pct(p['left_hand_in_view'])}) "
                     f"| {pct(p['right_hand'])} ({pct(p['right_hand_in_view'])}) | "
                     f"{pct(p.get('left_hand_placed', np.nan))} / "
                     f"{pct(p.get('right_hand_placed', np.nan))} | {_f(c['track_ms'], 0)} |")
    if summary["curve"]:
        lines += ["", "One Euro on the live fit (the same frames, smoothed afterwards): jitter "
                      "vs the lag it adds:", "",
                  "| min_cutoff Hz | beta | jitter px | lag ms | keypoint px | root° | "
                  "shoulders° | elbows° | neck/head° |",
                  "|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for r in summary["curve"]:
            name = ("none", "-") if r["min_cutoff"] is None else (f"{r['min_cutoff']:g}",
                                                                 f"{r['beta']:g}")
            lines.append(f"| {name[0]} | {name[1]} | {_f(r['jitter_px'], 2)} | "
                         f"{_f(r['lag_ms'], 0)} | {_f(r['keypoint_px'], 1)} | {_f(r['root'])} "
                         f"| {_f(r['shoulders'])} | {_f(r['elbows'])} | "
                         f"{_f(r['neck_head'])} |")
    return "\n".join(lines) + "\n"


def write_protocol(summary: dict[str, Any], out_dir: str | Path) -> tuple[Path, Path]:
    """`webcam_protocol.json` and `webcam_protocol.md` in `out_dir`."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    js, md = out / "webcam_protocol.json", out / "webcam_protocol.md"
    js.write_text(json.dumps(summary, indent=1, default=float, allow_nan=True))
    md.write_text(protocol_markdown(summary))
    return js, md


__all__ = ["CURVE_SETTINGS", "METRIC_KEYS", "protocol_markdown", "run_protocol", "summarise",
           "write_protocol"]
