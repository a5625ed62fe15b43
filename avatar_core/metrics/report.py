"""Evaluation results and how they are written: ``metrics.json``, ``metrics.md``, side-by-side
PNGs and the ablation table that merges several runs.

``EvalResult`` is plain data (JSON round-trips through ``to_dict`` / ``from_dict``), so an
ablation table can be built from saved ``metrics.json`` files as well as from live runs.
Undefined values (a metric that is off, NaN, or infinite) are ``None`` in Python and ``null``
in JSON; ``notes`` says why a metric is null.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import cv2
import numpy as np

__all__ = ["ABLATION_COLUMNS", "METRIC_KEYS", "PROTOCOLS", "EvalResult", "ablation_json",
           "ablation_table", "ablation_table_from_json", "load_result", "result_markdown",
           "side_by_side", "write_result"]

# Protocol (CLI name) -> dataset split.
PROTOCOLS = {"novel-view": "novel_view", "self-reenactment": "self_reenactment",
             "cross-identity": "cross_identity"}
METRIC_KEYS = ("l1", "psnr", "ssim", "lpips", "akd_face", "akd_hands", "akd_torso", "tje",
               "csim")
LABELS = {"l1": "L1", "psnr": "PSNR (dB)", "ssim": "SSIM", "lpips": "LPIPS",
          "akd_face": "AKD face (px)", "akd_hands": "AKD hands (px)",
          "akd_torso": "AKD torso (px)", "tje": "TJE", "csim": "CSIM"}
DIGITS = {"l1": 4, "psnr": 2, "ssim": 4, "lpips": 4, "akd_face": 2, "akd_hands": 2,
          "akd_torso": 2, "tje": 4, "csim": 4}
ABLATION_COLUMNS = ("l1", "psnr", "ssim", "lpips", "akd_face", "akd_hands")
ERROR_SCALE = 0.25  # mean absolute error (per pixel, over channels) shown as full heat
EXCLUDED_GREY = 128  # heatmap colour of the lower-body pixels that are not scored


@dataclass
class EvalResult:
    """One avatar evaluated under one protocol. ``metrics``: ``METRIC_KEYS`` -> mean over
    views (TJE: over cameras) or None; ``per_camera``: camera -> the same keys plus
    ``views``; ``views``: one record per view (key, metrics, timings)."""

    protocol: str
    split: str
    avatar: str
    dataset: str
    fusion: bool                   # fusion asked for
    fused: bool                    # FLAME / MANO keys were present and fused
    num_views: int
    num_gaussians: int
    image_size: list[int]          # [H, W] the metrics were computed at
    frame_stride: int
    metrics: dict[str, float | None]
    per_camera: dict[str, dict[str, float | None]] = field(default_factory=dict)
    timing: dict[str, float | None] = field(default_factory=dict)
    notes: dict[str, str] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    images: list[str] = field(default_factory=list)  # relative to the output folder
    views: list[dict[str, Any]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return _json_safe(asdict(self))

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> EvalResult:
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in names})


def load_result(path: str | Path) -> EvalResult:
    """An ``EvalResult`` from a ``metrics.json`` (or the folder holding it)."""
    path = Path(path)
    if path.is_dir():
        path = path / "metrics.json"
    return EvalResult.from_dict(json.loads(path.read_text()))


def _json_safe(obj: Any) -> Any:
    """NaN / inf -> None (strict JSON), tuples -> lists, numpy scalars -> Python numbers."""
    if isinstance(obj, Mapping):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _fmt(value: float | None, key: str) -> str:
    return "n/a" if value is None else f"{value:.{DIGITS.get(key, 4)}f}"


# -- one result ----------------------------------------------------------------------------


def result_markdown(result: EvalResult) -> str:
    """The Markdown report of one run: headline table, per-camera table, notes, images."""
    h, w = result.image_size
    render = result.timing.get("render_ms_median")
    lines = [
        f"# {result.avatar}: {result.protocol} on {result.dataset}",
        "",
        f"Split `{result.split}`, {result.num_views} views at {w}x{h}, frame stride "
        f"{result.frame_stride}, fusion {'on' if result.fusion else 'off'}"
        f"{'' if result.fused or not result.fusion else ' (no FLAME/MANO keys to fuse)'}, "
        f"{result.num_gaussians} Gaussians, render "
        f"{'n/a' if render is None else f'{render:.1f}'} ms/view (median).",
        "",
        "| metric | value |",
        "|---|---|",
    ]
    for key in METRIC_KEYS:
        value = result.metrics.get(key)
        reason = f" ({result.notes[key]})" if value is None and key in result.notes else ""
        lines.append(f"| {LABELS[key]} | {_fmt(value, key)}{reason} |")
    if result.per_camera:
        keys = [k for k in METRIC_KEYS if k not in ("lpips", "csim")]
        lines += ["", "## Per camera", "",
                  "| camera | views | " + " | ".join(LABELS[k] for k in keys) + " |",
                  "|---|---|" + "---|" * len(keys)]
        for cam, row in result.per_camera.items():
            cells = " | ".join(_fmt(row.get(k), k) for k in keys)
            lines.append(f"| {cam} | {int(row.get('views') or 0)} | {cells} |")
    if result.timing:
        lines += ["", "## Timing", ""]
        lines += [f"- {k}: {'n/a' if v is None else f'{v:.2f}'}"
                  for k, v in result.timing.items()]
    if result.notes:
        lines += ["", "## Notes", ""] + [f"- **{k}**: {v}" for k, v in result.notes.items()]
    if result.warnings:
        lines += ["", "## Warnings", ""] + [f"- {w}" for w in result.warnings]
    if result.images:
        caption = ("driver | avatar" if result.protocol == "cross-identity"
                   else "ground truth | render | |error| (lower body grey)")
        lines += ["", f"## Images ({caption})", ""]
        lines += [f"![{Path(p).stem}]({p})" for p in result.images]
    return "\n".join(lines) + "\n"


def write_report(out_dir: str | Path, stem: str, data: dict, markdown: str
                 ) -> tuple[Path, Path]:
    """``{stem}.json`` (strict JSON: no NaN) and ``{stem}.md`` in ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    js, md = out / f"{stem}.json", out / f"{stem}.md"
    js.write_text(json.dumps(data, indent=2, allow_nan=False) + "\n")
    md.write_text(markdown)
    return js, md


def write_result(result: EvalResult, out_dir: str | Path) -> tuple[Path, Path]:
    """``metrics.json`` and ``metrics.md`` in ``out_dir``."""
    return write_report(out_dir, "metrics", result.to_dict(), result_markdown(result))


# -- side-by-side images -------------------------------------------------------------------


def _to_u8(img: np.ndarray) -> np.ndarray:
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def error_heatmap(render: np.ndarray, gt: np.ndarray, keep: np.ndarray | None = None, *,
                  scale: float = ERROR_SCALE) -> np.ndarray:
    """uint8 RGB [H, W, 3]: mean |render - gt| over channels, ``scale`` = full heat
    (inferno); pixels outside ``keep`` (not scored) grey."""
    err = np.abs(render.astype(np.float32) - gt.astype(np.float32)).mean(axis=-1)  # [H, W]
    heat = cv2.applyColorMap(_to_u8(err / scale), cv2.COLORMAP_INFERNO)[..., ::-1]  # BGR->RGB
    if keep is not None:
        heat = np.where(keep[..., None], heat, np.uint8(EXCLUDED_GREY))
    return np.ascontiguousarray(heat)


def side_by_side(gt: np.ndarray, render: np.ndarray, keep: np.ndarray | None = None, *,
                 error: bool = True, min_height: int = 128, gap: int = 2) -> np.ndarray:
    """uint8 RGB ``[GT | render | error heatmap]`` (or ``[GT | render]``), float images
    ``[H, W, 3]`` in [0, 1]; small images are enlarged (nearest) to ``min_height``."""
    panels = [_to_u8(gt), _to_u8(render)]
    if error:
        panels.append(error_heatmap(render, gt, keep))
    h = gt.shape[0]
    k = max(1, math.ceil(min_height / h))  # integer zoom keeps pixels square and sharp
    panels = [np.repeat(np.repeat(p, k, axis=0), k, axis=1) for p in panels]
    sep = np.full((h * k, gap, 3), 40, dtype=np.uint8)
    out = [panels[0]]
    for p in panels[1:]:
        out += [sep, p]
    return np.concatenate(out, axis=1)


# -- ablation table ------------------------------------------------------------------------


def _protocols_in(results: Mapping[str, Mapping[str, EvalResult]]) -> list[str]:
    seen = {p for row in results.values() for p in row}
    order = [p for p in PROTOCOLS if p in seen]
    return order + sorted(seen - set(order))


def ablation_json(results: Mapping[str, Mapping[str, EvalResult]]) -> dict[str, Any]:
    """``{"columns": [...], "rows": {row: {protocol: {metric: value or None}}}}`` with the
    ``ABLATION_COLUMNS`` metrics of each run (row: full model or an ablation)."""
    protocols = _protocols_in(results)
    rows = {name: {p: {k: runs[p].metrics.get(k) for k in ABLATION_COLUMNS}
                   for p in protocols if p in runs}
            for name, runs in results.items()}
    return _json_safe({"protocols": protocols, "columns": list(ABLATION_COLUMNS),
                       "rows": rows})


def ablation_table(results: Mapping[str, Mapping[str, EvalResult]]) -> str:
    """Markdown table: one row per model (full model, each ablation), per protocol the
    columns L1, PSNR, SSIM, LPIPS, AKD face, AKD hands; "n/a" where a metric is off (LPIPS
    without weights, image metrics of cross-identity) and "-" where a run is missing."""
    if not results:
        raise ValueError("no results to tabulate")
    return ablation_table_from_json(ablation_json(results))


def ablation_table_from_json(table: Mapping[str, Any]) -> str:
    """:func:`ablation_table` from :func:`ablation_json`'s output (or several runs' rows
    merged into one), so separately trained models land in one table."""
    protocols, columns = table["protocols"], table["columns"]
    header = ["model"] + [f"{p} {LABELS[k]}" for p in protocols for k in columns]
    lines = ["| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
    for name, runs in table["rows"].items():
        cells = [name]
        for p in protocols:
            run = runs.get(p)
            cells += (["-"] * len(columns) if run is None else
                      [_fmt(run.get(k), k) for k in columns])
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
