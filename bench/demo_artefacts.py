"""Region errors of a trained avatar where the demo avatar showed artefacts (issue 26).

The studio's actor is posed in held-out poses (arms raised, so the armpits show; and the
relaxed stance of the training takes) and filmed by held-out cameras (the rig's novel-view
camera and two low cameras looking up at the shoulders); the avatar is driven with the same
(true) parameters and rendered by the ordinary render path. Three regions, from the mesh:

- ``armpit``: pixels of the triangles near either armpit (rest-pose centroid within
  ``ARMPIT_RADIUS`` of the shoulder joint and below it), grown by ``GROW`` px;
- ``hem``: pixels of the triangles within ``HEM_BAND`` of the upper-body cut (both sides:
  the avatar should end at the cut), grown by ``GROW`` px;
- ``floaters``: pixels where the upper-body truth has no alpha, farther than ``CLEAR`` px
  from its silhouette and outside the hem region.

The truth is the upper body alone: lower-body pixels (legs and hips, which the avatar does
not have) are the background. Per region: PSNR and L1 against the truth (mean over views of
the region's pixels) and, for floaters, the rendered alpha summed over the region per view.
Crops (truth | render | 4x abs error) are written per region and view.

    OMP_NUM_THREADS=1 python bench/demo_artefacts.py PACKAGE --out DIR [--size 512]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import torch
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from avatar_core.body.skeleton import JOINT, SMPLX_PART_NAMES, UPPER_BODY_PARTS  # noqa: E402
from avatar_core.gaussians.loading import load_avatar  # noqa: E402
from avatar_core.metrics.image import l1, psnr  # noqa: E402
from avatar_core.motion.keyframes import Pose, pose_to_params  # noqa: E402
from avatar_core.motion.rig import model_rig  # noqa: E402
from avatar_core.render.camera import Camera, look_at  # noqa: E402
from avatar_core.render.rasterize import rasterize  # noqa: E402
from avatar_core.render.types import RenderRequest  # noqa: E402
from avatar_core.synth.actor import Actor  # noqa: E402
from avatar_core.synth.capture import default_holdout  # noqa: E402
from avatar_core.synth.mesh_render import render_mesh  # noqa: E402
from avatar_core.synth.model_writer import ensure_models  # noqa: E402
from avatar_core.synth.studio import StudioConfig, studio_rig  # noqa: E402

ARMPIT_RADIUS = 0.10  # m, around the shoulder joint in the rest (T) pose
HEM_BAND = 0.05       # m, from the cut's vertices in the rest pose
GROW = 3              # px: smudges and frays reach a little past their triangles
CLEAR = 4             # px between the silhouette and the floater region (anti-aliasing)
BACKGROUND = (1.0, 1.0, 1.0)  # the demo's (DataConfig and CaptureSpec defaults)
REGIONS = ("armpit", "hem", "floaters")

# Held-out poses: the arms raised (abduction past horizontal) and lowered half-way, which
# the training takes never show, and the training takes' relaxed stance.
POSES = {
    "arms_raised": Pose({"left_shoulder": (0.0, 0.0, 0.45), "right_shoulder": (0.0, 0.0, -0.45),
                         "left_elbow": (0.0, -0.2, 0.0), "right_elbow": (0.0, 0.2, 0.0)}),
    "arms_half": Pose({"left_shoulder": (0.0, 0.0, -0.45), "right_shoulder": (0.0, 0.0, 0.45),
                       "left_elbow": (0.0, -0.5, 0.0), "right_elbow": (0.0, 0.5, 0.0)}),
    "relaxed": Pose(),
}


def cameras(size: int) -> dict[str, Camera]:
    """The rig's novel-view camera and two low cameras (not in the rig) looking up at the
    shoulders from the front-left and front-right."""
    rig = studio_rig(size, StudioConfig(), seed=0)
    held = default_holdout(rig)[0]
    out = {held: next(c.camera for c in rig if c.name == held)}
    fov = np.degrees(2 * np.arctan(540.0 / StudioConfig().focal_px))  # the rig's lens
    for name, azimuth in (("low_left", 40.0), ("low_right", -40.0)):
        a = np.radians(azimuth)
        eye = (1.4 * np.sin(a), 0.05, 1.4 * np.cos(a))
        out[name] = look_at(eye, (0.0, 0.35, 0.0), width=size, height=size, fov_y_deg=fov)
    return out


def face_regions(actor: Actor, rig) -> dict[str, np.ndarray]:
    """bool [F] per region over the actor's body faces, fixed in the rest (T) pose."""
    tpose = pose_to_params(Pose({k: (0.0, 0.0, 0.0) for k in (
        "left_shoulder", "right_shoulder", "left_elbow", "right_elbow")}), rig)
    posed = actor.pose(tpose)
    v = posed.body_vertices
    faces = actor.faces[: actor.num_body_faces]
    centroid = v[faces].mean(1)
    out = {}
    for side in ("left", "right"):
        joint = posed.joints[JOINT[f"{side}_shoulder"]]
        near = np.linalg.norm(centroid - joint, axis=1) < ARMPIT_RADIUS
        out[f"armpit_{side}"] = near & (centroid[:, 1] < joint[1] - 0.01)
    upper_ids = [SMPLX_PART_NAMES.index(p) for p in UPPER_BODY_PARTS]
    upper = np.isin(actor.face_parts[: actor.num_body_faces], upper_ids)
    cut = np.intersect1d(np.unique(faces[upper]), np.unique(faces[~upper]))
    dist, _ = cKDTree(v[cut]).query(centroid)
    return {**out, "hem": dist < HEM_BAND}


def avatar_faces(regions: dict[str, np.ndarray], actor: Actor, loaded) -> dict[str, np.ndarray]:
    """The same regions as bool [F'] over the avatar's (upper-body) faces."""
    full = actor.faces[: actor.num_body_faces]
    index = {tuple(sorted(f)): i for i, f in enumerate(full.tolist())}
    model = loaded.animator.body_model
    ids = np.asarray(model.vertex_ids)[model.faces.cpu().numpy()]
    rows = np.array([index.get(tuple(sorted(f)), -1) for f in ids.tolist()])
    return {k: np.where(rows >= 0, v[np.maximum(rows, 0)], False) for k, v in regions.items()}


def gaussian_stats(loaded, faces: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    """Per region: how many Gaussians, their median opacity and the share nearly clear."""
    a = loaded.animator.avatar
    parents = a.parents.cpu().numpy()
    opacity = torch.sigmoid(a.opacity_logits).detach().cpu().numpy().reshape(-1)
    out = {}
    for name, sel in {**faces, "all": np.ones_like(next(iter(faces.values())))}.items():
        mine = sel[parents]
        out[name] = {"gaussians": int(mine.sum()),
                     "median_opacity": float(np.median(opacity[mine])) if mine.any() else 0.0,
                     "clear_share": float((opacity[mine] < 0.05).mean()) if mine.any() else 0.0}
    return out


def _grow(mask: np.ndarray, px: int) -> np.ndarray:
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * px + 1, 2 * px + 1))
    return cv2.dilate(mask.astype(np.uint8), kernel) > 0


def pixel_regions(actor: Actor, posed, camera: Camera, regions: dict[str, np.ndarray],
                  upper_alpha: np.ndarray) -> dict[str, np.ndarray]:
    """bool [H, W] per region in one view (visible triangles only: the z-buffer's)."""
    faces = actor.faces[: actor.num_body_faces]
    face_id = render_mesh(posed.body_vertices, faces, camera, shading=False).face_id
    seen = face_id >= 0
    out = {}
    for name, sel in regions.items():
        hit = np.zeros(face_id.shape, bool)
        hit[seen] = sel[face_id[seen]]
        out[name] = _grow(hit, GROW)
    out["armpit"] = out["armpit_left"] | out["armpit_right"]
    out["floaters"] = ~_grow(upper_alpha > 0, CLEAR) & ~out["hem"]
    return out


def upper_truth(actor: Actor, posed, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(rgb, alpha) of the upper body alone: lower-body pixels become the background."""
    view = actor.render(posed, camera, background=BACKGROUND)
    upper_ids = [SMPLX_PART_NAMES.index(p) for p in UPPER_BODY_PARTS]
    keep = np.isin(view.parts, upper_ids)
    alpha = np.where(keep, view.alpha, 0.0).astype(np.float32)
    rgb = np.where(keep[..., None], view.rgb, np.asarray(BACKGROUND, np.float32))
    return rgb.astype(np.float32), alpha


def _crop(images: list[np.ndarray], mask: np.ndarray, pad: int = 12) -> np.ndarray | None:
    ys, xs = np.nonzero(mask)
    if ys.size == 0:
        return None
    h, w = mask.shape
    y0, y1 = max(ys.min() - pad, 0), min(ys.max() + pad + 1, h)
    x0, x1 = max(xs.min() - pad, 0), min(xs.max() + pad + 1, w)
    tiles = [img[y0:y1, x0:x1] for img in images]
    return np.concatenate(tiles, axis=1)


def _png(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    u8 = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
    cv2.imwrite(str(path), cv2.cvtColor(u8, cv2.COLOR_RGB2BGR))


def evaluate(package: Path, out: Path, size: int, crops: bool = True,
             sh_degree: int | None = None, poses: tuple[str, ...] = tuple(POSES)) -> dict:
    files = ensure_models(None, seed=0)
    actor = Actor.load(files, 0)
    rig = model_rig(files, actor.model)
    regions = face_regions(actor, rig)
    loaded = load_avatar(str(package))
    stats = gaussian_stats(loaded, avatar_faces(regions, actor, loaded))
    request = RenderRequest(outputs=("rgb", "alpha"), background=BACKGROUND,
                            sh_degree=sh_degree)
    rows = []
    for pose_name in poses:
        pose = POSES[pose_name]
        params = pose_to_params(pose, rig)
        params["betas"] = np.asarray(actor.betas, dtype=np.float64)
        posed_actor = actor.pose(params)
        posed = loaded.animator.pose({k: v[None] if k != "betas" else v[None]
                                      for k, v in params.items()})
        for cam_name, cam in cameras(size).items():
            gt, gt_alpha = upper_truth(actor, posed_actor, cam)
            with torch.no_grad():
                res = rasterize(posed.gaussians, cam, request)
            pred = res.rgb.clamp(0, 1).cpu().numpy().astype(np.float32)
            alpha = res.alpha.cpu().numpy().reshape(gt_alpha.shape)
            masks = pixel_regions(actor, posed_actor, cam, regions, gt_alpha)
            row = {"pose": pose_name, "camera": cam_name}
            p, g = torch.from_numpy(pred), torch.from_numpy(gt)
            for name in REGIONS:
                m = torch.from_numpy(masks[name])
                row[f"{name}_px"] = int(m.sum())
                if row[f"{name}_px"]:
                    row[f"{name}_psnr"] = float(psnr(p, g, m))
                    row[f"{name}_l1"] = float(l1(p, g, m))
            if crops:
                diff = np.clip(np.abs(pred - gt) * 4, 0, 1)
                for name in ("armpit_left", "armpit_right", "hem"):
                    tile = _crop([gt, pred, diff], masks[name])
                    if tile is not None:
                        _png(out / "crops" / f"{name}_{pose_name}_{cam_name}.png", tile)
            fl = masks["floaters"]
            row["floaters_alpha_sum"] = float(alpha[fl].sum())
            # the floaters' own colour: the render less the background showing through
            premult = pred[fl] - (1.0 - alpha[fl, None]) * np.asarray(BACKGROUND, np.float32)
            row["floaters_color"] = (premult.sum(0) / max(alpha[fl].sum(), 1e-6)).tolist()
            row["psnr_all"] = float(psnr(p, g))
            if crops:  # floaters: their alpha x 20 in the floater region (faint made visible)
                amp = np.where(fl, np.clip(alpha * 20, 0, 1), 0.0)[..., None].repeat(3, -1)
                _png(out / "crops" / f"floaters_{pose_name}_{cam_name}.png",
                     np.concatenate([gt, pred, 1.0 - amp], 1))
                _png(out / "full" / f"{pose_name}_{cam_name}.png",
                     np.concatenate([gt, pred, np.clip(np.abs(pred - gt) * 4, 0, 1)], 1))
            rows.append(row)
    summary = {f"{r}_{k}": float(np.mean([row[f"{r}_{k}"] for row in rows
                                           if f"{r}_{k}" in row]))
               for r in REGIONS for k in ("psnr", "l1")}
    summary["floaters_alpha_sum"] = float(np.mean([r["floaters_alpha_sum"] for r in rows]))
    weights = np.array([r["floaters_alpha_sum"] for r in rows])
    colors = np.array([r["floaters_color"] for r in rows])
    summary["floaters_gray"] = float((colors.mean(1) * weights).sum() / max(weights.sum(), 1e-6))
    summary["psnr_all"] = float(np.mean([r["psnr_all"] for r in rows]))
    summary["armpit_raised_psnr"] = float(np.mean(
        [r["armpit_psnr"] for r in rows if r["pose"] != "relaxed" and "armpit_psnr" in r]))
    result = {"package": str(package), "size": size, "sh_degree": sh_degree,
              "summary": summary, "gaussians": stats, "views": rows}
    out.mkdir(parents=True, exist_ok=True)
    (out / "regions.json").write_text(json.dumps(result, indent=2))
    return result


def coverage(motions: str, frames: int, size: int, stride: int = 3) -> dict[str, float]:
    """Per region: the share of its triangles that the training cameras see (z-buffer, at
    least one pixel) in any frame of the capture ``motions`` (every ``stride``-th frame),
    filmed as the demo films them: is the region in the training data at all?"""
    from avatar_core.motion.library import motion_sequence
    from avatar_core.synth.capture import parse_sequences

    files = ensure_models(None, seed=0)
    actor = Actor.load(files, 0)
    rig_params = model_rig(files, actor.model)
    regions = face_regions(actor, rig_params)
    rig = studio_rig(size, StudioConfig(), seed=0)
    held = default_holdout(rig)
    faces = actor.faces[: actor.num_body_faces]
    seen = np.zeros(len(faces), bool)
    for seq in parse_sequences(motions):
        track = motion_sequence(list(seq))
        for f in range(0, frames, stride):
            params = track.sample(f / StudioConfig().fps, rig_params)
            params["betas"] = np.asarray(actor.betas, dtype=np.float64)
            posed = actor.pose(params)
            for cam in rig:
                if cam.name in held:
                    continue
                ids = render_mesh(posed.body_vertices, faces, cam.camera, shading=False).face_id
                seen[np.unique(ids[ids >= 0])] = True
    upper = np.isin(actor.face_parts[: actor.num_body_faces],
                    [SMPLX_PART_NAMES.index(p) for p in UPPER_BODY_PARTS])
    out = {name: float(seen[sel].mean()) for name, sel in regions.items()}
    out["upper_body"] = float(seen[upper].mean())
    return out


def package_of(path: Path, out: Path, fill_unseen: bool = False) -> Path:
    """``path`` itself when it is a package, else a training folder's latest checkpoint
    exported under ``out`` (to measure a run part-way). ``fill_unseen`` (the swap
    experiment for the armpit): the Gaussians still at the grey initial colour take the
    colour that ``init_unseen = "neighbours"`` would have given them at the start; almost no
    gradient reached them, so this is about what that training would hold."""
    if (path / "avatar.json").is_file() and not fill_unseen:
        return path
    from dataclasses import replace

    from avatar_core.gaussians.avatar import DEFAULT_COLOR
    from avatar_core.render.sh import rgb_to_sh0
    from avatar_core.train.trainer import Trainer

    trainer = Trainer.resume(path)
    if fill_unseen:
        trainer.config = replace(trainer.config, init_unseen="neighbours")
        filled = torch.as_tensor(trainer._projected_colors(), dtype=torch.float32)
        sh0 = trainer.state["sh0"]
        grey = rgb_to_sh0(torch.tensor(DEFAULT_COLOR, dtype=sh0.dtype))
        # barely moved from grey: hidden Gaussians get only the tiny gradients that leak
        # through the surface in front of them (0.01 in SH units is 0.003 in colour)
        untouched = ((sh0[:, 0] - grey).abs() < 0.01).all(1) \
            & (trainer.state["sh_rest"].abs() < 0.01).all(2).all(1)
        with torch.no_grad():
            sh0[untouched, 0] = rgb_to_sh0(filled[trainer.state["parents"][untouched]])
        print(f"fill-unseen: {int(untouched.sum())} Gaussians still grey re-coloured")
    return trainer.export(out / "package")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("package", type=Path, nargs="?",
                        help="trained avatar package, or a training folder (its checkpoint)")
    parser.add_argument("--out", type=Path, help="regions.json and crops/")
    parser.add_argument("--coverage", default=None, metavar="MOTIONS",
                        help="instead: the share of each region the training cameras see "
                             "in a capture of MOTIONS (--frames per sequence)")
    parser.add_argument("--frames", type=int, default=40, help="with --coverage")
    parser.add_argument("--fill-unseen", action="store_true",
                        help="swap: Gaussians still grey from the start take their "
                             "neighbours' initial colour (a training folder only)")
    parser.add_argument("--size", type=int, default=512, help="image side, px")
    parser.add_argument("--no-crops", action="store_true")
    parser.add_argument("--sh-degree", type=int, default=None,
                        help="render with at most this SH degree (an experiment's swap)")
    parser.add_argument("--poses", default=",".join(POSES),
                        help=f"comma-separated, of {list(POSES)}")
    args = parser.parse_args(argv)
    if args.coverage:
        print(json.dumps(coverage(args.coverage, args.frames, args.size)))
        return 0
    if args.package is None or args.out is None:
        parser.error("give PACKAGE and --out (or --coverage)")
    poses = tuple(p for p in args.poses.split(",") if p)
    unknown = sorted(set(poses) - set(POSES))
    if unknown:
        parser.error(f"unknown pose(s) {unknown}; known: {list(POSES)}")
    result = evaluate(package_of(args.package, args.out, args.fill_unseen), args.out, args.size,
                      crops=not args.no_crops,
                      sh_degree=args.sh_degree, poses=poses)
    s = result["summary"]
    print(" ".join(f"{k}={v:.4g}" for k, v in s.items()))
    print(json.dumps(result["gaussians"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
