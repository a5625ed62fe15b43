"""A learned, pose-dependent correction of BlazePose's world arm bones.

BlazePose's metric world landmarks put the arm bones 8-33 deg from the body model's, and with
every 2D landmark true the fit's arms are still 29-33 deg off because of it (docs/results.md
"World bones and the elbow hinge"). This maps what the tracker saw in one frame (its world
points, its image points, where the shoulders sit in the picture) to the residual between
BlazePose's unit bone direction and the body model's, per arm bone, by ridge regression
solved on studio renders where the truth is known (`synth.world_correction_build`). The
corrected directions rebuild the elbows and wrists from the shoulders with BlazePose's bone
lengths, so the fit's world terms (`world_cues`) read them as they read BlazePose's.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import correspondence as cor
from .world_cues import ARM_BONES, WORLD_TO_CAMERA

VERSION = 1
ASSET = Path(__file__).resolve().parent / "assets" / "world_correction.npz"
# Chosen by leaving one of three training identities out (docs/results.md, "BlazePose's world
# bones corrected"); the correction is not live, so it was not tuned again on four.
DEFAULT_RIDGE = 1000.0
# Rows whose points describe the frame (BlazePose's numbering) and their mirror images.
ROWS = (0, 11, 12, 13, 14, 15, 16, 23, 24)
MIRROR_ROW = {0: 0, 11: 12, 12: 11, 13: 14, 14: 13, 15: 16, 16: 15, 23: 24, 24: 23}
MIN_SHOULDER_WIDTH = 1e-3   # m and px: narrower shoulders give no frame to correct in
NUM_FEATURES = len(ROWS) * 7 + len(ARM_BONES) * 3 + 3


@dataclass(frozen=True)
class WorldCorrection:
    mean: np.ndarray      # [F] feature means
    scale: np.ndarray     # [F] feature standard deviations (1 where constant)
    weights: np.ndarray   # [B, F + 1, 3] per bone: standardized features + bias -> residual
    version: int = VERSION


def _mirror_rows(a: np.ndarray) -> np.ndarray:
    """[33, D] with left and right rows of `ROWS` swapped (other rows as they are)."""
    out = a.copy()
    for r, m in MIRROR_ROW.items():
        out[r] = a[m]
    return out


def _frame_points(obs, mirror: bool) -> tuple[np.ndarray, np.ndarray] | None:
    """(world [33, 3] in the fit's camera frame, image [33, 2] px with y up, NaN where unused),
    mirrored if asked; None when the shoulders are not both seen."""
    if obs.world is None:
        return None
    world = np.asarray(obs.world, dtype=np.float64) * WORLD_TO_CAMERA
    sl = cor.POSE_SLICE
    pix = np.where((obs.weights[sl] > 0)[:, None], obs.pixels[sl], np.nan).astype(np.float64)
    image = np.stack([pix[:, 0], -pix[:, 1]], axis=1)
    if mirror:
        world, image = _mirror_rows(world), _mirror_rows(image)
        world[:, 0] *= -1.0
        image[:, 0] = obs.image_size[0] - image[:, 0]
    if not (np.isfinite(world[[11, 12]]).all() and np.isfinite(image[[11, 12]]).all()):
        return None
    return world, image


def bone_directions(world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(unit directions [B, 3], lengths [B]) of `ARM_BONES` in `world` [33, 3]; NaN where an
    end is missing."""
    vec = np.stack([world[b] - world[a] for a, b in ARM_BONES])
    length = np.linalg.norm(vec, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = vec / length[:, None]
    bad = ~np.isfinite(unit).all(axis=1) | (length < 1e-6)
    unit[bad], length[bad] = np.nan, np.nan
    return unit, length


def features(world: np.ndarray, image: np.ndarray, image_size: tuple[int, int],
             unit: np.ndarray) -> np.ndarray:
    """[F] one frame's features: per row of `ROWS` its world and image point relative to the
    shoulders' midpoint in shoulder widths (0 where unused) and whether each is used; the
    arm bones' unit directions `unit` [B, 3] (`bone_directions` of `world`; 0 where unused);
    where the shoulders sit in the picture and how wide they are."""
    w_mid, i_mid = world[[11, 12]].mean(0), image[[11, 12]].mean(0)
    w_width = max(float(np.linalg.norm(world[11] - world[12])), MIN_SHOULDER_WIDTH)
    i_width = max(float(np.linalg.norm(image[11] - image[12])), MIN_SHOULDER_WIDTH)
    rows = list(ROWS)
    w_rel, i_rel = (world[rows] - w_mid) / w_width, (image[rows] - i_mid) / i_width
    w_used, i_used = np.isfinite(w_rel).all(1), np.isfinite(i_rel).all(1)
    width = float(image_size[0])
    place = [(i_mid[0] - 0.5 * width) / width, (i_mid[1] + 0.5 * image_size[1]) / width,
             i_width / width]
    finite = lambda a: np.where(np.isfinite(a), a, 0.0).ravel()  # noqa: E731
    return np.concatenate([finite(w_rel), finite(i_rel), w_used, i_used, finite(unit),
                           finite(np.array(place))])


def training_pair(obs, true_points: np.ndarray, mirror: bool = False
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(features [F], residual targets [B, 3] flattened, mask [B]) of one frame against the
    true pose points [33, 3] (the fit's camera frame); mask False where BlazePose or the truth
    lacks the bone (and everywhere when the shoulders are not seen)."""
    bones = len(ARM_BONES)
    points = _frame_points(obs, mirror)
    if points is None:
        return np.zeros(NUM_FEATURES), np.zeros(3 * bones), np.zeros(bones, bool)
    world, image = points
    truth = np.asarray(true_points, dtype=np.float64).copy()
    if mirror:
        truth = _mirror_rows(truth)
        truth[:, 0] *= -1.0
    seen, _ = bone_directions(world)
    true, _ = bone_directions(truth)
    mask = np.isfinite(seen).all(1) & np.isfinite(true).all(1)
    residual = np.where(mask[:, None], true - seen, 0.0)
    return features(world, image, obs.image_size, seen), residual.ravel(), mask


def solve(x: np.ndarray, y: np.ndarray, mask: np.ndarray, ridge: float = DEFAULT_RIDGE
          ) -> WorldCorrection:
    """Ridge regression per bone on standardized features: x [M, F], y [M, 3B], mask [M, B]."""
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise ValueError("training pairs must be finite")
    mean = x.mean(0)
    scale = x.std(0)
    scale = np.where(scale > 1e-9, scale, 1.0)
    xs = np.concatenate([(x - mean) / scale, np.ones((len(x), 1))], axis=1)
    reg = ridge * np.eye(xs.shape[1])
    reg[-1, -1] = 0.0  # the bias is not shrunk
    weights = []
    for b in range(mask.shape[1]):
        rows = mask[:, b]
        a = xs[rows]
        target = y[rows, 3 * b:3 * b + 3]
        weights.append(np.linalg.solve(a.T @ a + reg, a.T @ target))
    return WorldCorrection(mean, scale, np.stack(weights))


def corrected_directions(obs, corr: WorldCorrection) -> tuple[np.ndarray, np.ndarray] | None:
    """(corrected unit directions [B, 3] in the fit's camera frame, BlazePose's lengths [B]),
    NaN where BlazePose lacks the bone; None when the shoulders are not seen."""
    points = _frame_points(obs, mirror=False)
    if points is None:
        return None
    world, image = points
    unit, length = bone_directions(world)
    x = (features(world, image, obs.image_size, unit) - corr.mean) / corr.scale
    residual = np.einsum("f,bfk->bk", np.append(x, 1.0), corr.weights)  # [B, 3]
    fixed = unit + residual
    with np.errstate(invalid="ignore", divide="ignore"):
        fixed = fixed / np.linalg.norm(fixed, axis=1, keepdims=True)
    return fixed, length


def correct_world(obs, corr: WorldCorrection) -> np.ndarray | None:
    """[33, 3] BlazePose-axes world points with the elbows and wrists moved so each arm bone
    takes its corrected direction at BlazePose's length; `obs.world` unchanged where no bone
    is corrected; None when `obs` has no world points."""
    if obs.world is None:
        return None
    fixed = corrected_directions(obs, corr)
    if fixed is None:
        return np.array(obs.world, dtype=np.float64)
    return with_bone_directions(obs.world, *fixed)


def with_bone_directions(world: np.ndarray, unit: np.ndarray, length: np.ndarray
                         ) -> np.ndarray:
    """[33, 3] BlazePose-axes `world` with each arm bone's far end moved to its near end plus
    `length` [B] along `unit` [B, 3] (the fit's camera frame); bones with a NaN left as
    they are."""
    cam = np.array(world, dtype=np.float64) * WORLD_TO_CAMERA
    for b, (a, end) in enumerate(ARM_BONES):  # upper arms before their forearms
        if np.isfinite(unit[b]).all() and np.isfinite(length[b]):
            cam[end] = cam[a] + length[b] * unit[b]
    return cam * WORLD_TO_CAMERA


def save(corr: WorldCorrection, path: Path) -> None:
    np.savez(path, version=np.array(corr.version), mean=corr.mean, scale=corr.scale,
             weights=corr.weights, rows=np.array(ROWS), bones=np.array(ARM_BONES))


def load_world_correction(path: str | Path | None = None) -> WorldCorrection:
    """The correction stored at `path` (default: the committed asset)."""
    path = Path(path) if path is not None else ASSET
    if not path.exists():
        raise FileNotFoundError(f"{path}: no world correction (build one with `telesplat "
                                f"track build-world-correction`)")
    with np.load(path) as data:
        version = int(data["version"])
        if version != VERSION:
            raise ValueError(f"{path}: world correction version {version}, this code reads "
                             f"{VERSION}")
        if tuple(data["rows"]) != ROWS or [tuple(b) for b in data["bones"]] != list(ARM_BONES):
            raise ValueError(f"{path}: built for other landmarks than this code's")
        corr = WorldCorrection(data["mean"], data["scale"], data["weights"], version)
    if corr.weights.shape != (len(ARM_BONES), NUM_FEATURES + 1, 3) or not all(
            np.isfinite(a).all() for a in (corr.mean, corr.scale, corr.weights)):
        raise ValueError(f"{path}: a world correction of the wrong shape or not finite")
    return corr


def bone_errors_deg(recordings, corr: WorldCorrection | None) -> dict[str, float]:
    """Median and p90 angle (deg) between the true arm bones and BlazePose's (`corr` None) or
    the corrected ones, upper arms and forearms apart, over every frame where both exist."""
    errors: dict[str, list[float]] = {"upper": [], "fore": []}
    for rec in recordings:
        for obs, points in zip(rec.live, rec.true_points, strict=True):
            fixed = _frame_points(obs, mirror=False) if corr is None else \
                corrected_directions(obs, corr)
            if fixed is None:
                continue
            unit = bone_directions(fixed[0])[0] if corr is None else fixed[0]
            true, _ = bone_directions(np.asarray(points, dtype=np.float64))
            for b in range(len(ARM_BONES)):
                if np.isfinite(unit[b]).all() and np.isfinite(true[b]).all():
                    cos = float(np.clip(unit[b] @ true[b], -1.0, 1.0))
                    errors["upper" if b % 2 == 0 else "fore"].append(np.degrees(np.arccos(cos)))
    out = {}
    for part, values in errors.items():
        out[f"{part}_median"] = float(np.median(values)) if values else float("nan")
        out[f"{part}_p90"] = float(np.percentile(values, 90)) if values else float("nan")
        out[f"{part}_count"] = len(values)
    return out
