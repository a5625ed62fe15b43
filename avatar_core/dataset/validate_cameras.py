"""Checks of cameras.json: each camera record, and whether a camera can see the subject."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from .format import CAMERAS_JSON, CameraSpec, check_name
from .problems import Problem, problem

__all__ = ["box_visible", "check_cameras", "check_visibility"]

_NEAR = 0.01  # metres; the rasterizer's near plane


def _is_int(x: Any, minimum: int) -> bool:
    return isinstance(x, int) and not isinstance(x, bool) and x >= minimum


def _camera_problems(entry: Any, index: int) -> tuple[CameraSpec | None, list[Problem]]:
    name = entry.get("name") if isinstance(entry, dict) else None
    label = name if isinstance(name, str) else f"#{index}"

    def p(code: str, message: str) -> Problem:
        return problem(code, f"camera {label}: {message}", camera=label, path=CAMERAS_JSON)

    if not isinstance(entry, dict):
        return None, [p("camera_bad_field", "must be an object")]
    try:
        check_name(name, "camera")
    except ValueError as exc:
        return None, [p("camera_bad_field", str(exc))]
    out: list[Problem] = []
    arrays = {}
    for key, shape in (("K", (3, 3)), ("R", (3, 3)), ("t", (3,)), ("distortion", (5,))):
        if key not in entry:
            if key != "distortion":
                out.append(p("camera_bad_field", f"{key} is missing"))
            continue
        try:
            arr = np.array(entry[key], dtype=np.float64)
        except (TypeError, ValueError):
            arr = np.zeros(0)
        if arr.shape != shape:
            out.append(p("camera_bad_field", f"{key} must have shape {list(shape)}"))
        elif not np.all(np.isfinite(arr)):
            out.append(p("camera_nonfinite", f"{key} holds NaN/Inf"))
        else:
            arrays[key] = arr
    for key in ("width", "height"):
        value = entry.get(key)
        if not _is_int(value, 1):
            out.append(p("camera_bad_size", f"{key} must be a positive integer, got {value!r}"))
    if not isinstance(entry.get("role", "unknown"), str) or entry.get("role") == "":
        out.append(p("camera_bad_field", "role must be a non-empty string"))
    K, R = arrays.get("K"), arrays.get("R")
    if K is not None and (not np.allclose(K[2], (0, 0, 1), rtol=0, atol=1e-9) or K[1, 0] != 0
                          or K[0, 0] <= 0 or K[1, 1] <= 0):
        out.append(p("camera_bad_intrinsics", "K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] "
                                              f"with fx, fy > 0, got {K.tolist()}"))
    if R is not None:
        err = float(np.max(np.abs(R @ R.T - np.eye(3))))
        det = float(np.linalg.det(R))
        if err > 1e-6 or abs(det - 1.0) > 1e-6:
            out.append(p("camera_bad_rotation", f"R is not a rotation (max |R R^T - I| = "
                                                f"{err:.3g}, det = {det:.6g})"))
    if out:
        return None, out
    return CameraSpec.from_dict(entry), []


def _size(entry: dict) -> tuple[int, int] | None:
    w, h = entry.get("width"), entry.get("height")
    return (w, h) if _is_int(w, 1) and _is_int(h, 1) else None


def check_cameras(doc: Any) -> tuple[dict[str, CameraSpec],
                                      dict[str, tuple[int, int] | None], list[Problem]]:
    """(valid cameras, image size (W, H) of every well-named camera, problems): the files of
    a camera with a bad calibration are still checked."""
    entries = doc.get("cameras") if isinstance(doc, dict) else None
    if not isinstance(entries, list) or not entries:
        return {}, {}, [problem("no_cameras", "cameras.json must hold a non-empty 'cameras' "
                                "list", path=CAMERAS_JSON)]
    cams: dict[str, CameraSpec] = {}
    sizes: dict[str, tuple[int, int] | None] = {}
    problems: list[Problem] = []
    seen: set[str] = set()
    for i, entry in enumerate(entries):
        name = entry.get("name") if isinstance(entry, dict) else None
        if isinstance(name, str) and name in seen:
            problems.append(problem("camera_duplicate_name", f"camera name {name} repeats",
                                    camera=name, path=CAMERAS_JSON))
            continue
        if isinstance(name, str):
            seen.add(name)
        spec, more = _camera_problems(entry, i)
        problems += more
        if spec is not None:
            cams[spec.name] = spec
        try:
            sizes[check_name(name, "camera")] = _size(entry)
        except ValueError:
            pass  # reported above
    return cams, sizes, problems


def box_visible(spec: CameraSpec, box: np.ndarray) -> bool:
    """Whether the box [2, 3] can reach the image: False when all 8 corners lie outside one
    face of the view frustum (near plane or one of the four image edges). Conservative: a
    box that is reported visible may still miss the image by a little, never the reverse."""
    corners = np.array([[box[i, 0], box[j, 1], box[k, 2]]
                        for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    x = corners @ spec.R.T + spec.t                          # [8, 3] camera space
    a, b = x @ spec.K[0], x @ spec.K[1]                      # u * z, v * z
    z = x[:, 2]
    inside = [z - _NEAR, a, spec.width * z - a, b, spec.height * z - b]  # each >= 0 inside
    return not any(np.all(s < 0) for s in inside)


def check_visibility(cams: Mapping[str, CameraSpec], bounds: np.ndarray | None
                      ) -> list[Problem]:
    if bounds is None:
        return []
    return [problem("camera_sees_nothing", f"camera {name} cannot see the subject_bounds box "
                    "(behind it or outside its image)", camera=name, path=CAMERAS_JSON)
            for name, spec in cams.items() if not box_visible(spec, bounds)]
