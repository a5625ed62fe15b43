"""Writers of small datasets: ours (through DatasetWriter) and foreign layouts (VHAP /
GaussianAvatars, EasyMocap) written the way those tools write them, with the ground truth."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from avatar_core.body.skeleton import SMPLX_PART_NAMES, UPPER_BODY_PARTS
from avatar_core.dataset import CameraSpec, DatasetWriter
from avatar_core.render.camera import look_at

BOX = [[-0.3, -0.5, -0.3], [0.3, 0.5, 0.3]]  # the subject's world box, metres


def ring_cameras(n: int, width: int, height: int, *, radius: float = 2.0, seed: int = 0
                 ) -> list[CameraSpec]:
    """n cameras on a frontal arc around the origin, with jittered intrinsics."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        a = np.radians(-40 + 80 * i / max(n - 1, 1))
        cam = look_at((radius * np.sin(a), 0.1 * i, radius * np.cos(a)), (0, 0, 0),
                      width=width, height=height, fov_y_deg=40)
        K = cam.K.copy()
        K[0, 0] *= 1.0 + rng.uniform(-0.05, 0.05)
        K[:2, 2] += rng.uniform(-1.0, 1.0, 2)
        out.append(CameraSpec(f"cam{i:02d}", K, cam.R, cam.t, width, height, role="front"))
    return out


def random_smplx(T: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    return {
        "betas": rng.normal(0, 1, 10),
        "expression": rng.normal(0, 1, (T, 10)),
        "global_orient": rng.normal(0, 0.2, (T, 3)),
        "body_pose": rng.normal(0, 0.2, (T, 21, 3)),
        "jaw_pose": rng.normal(0, 0.1, (T, 3)),
        "leye_pose": rng.normal(0, 0.1, (T, 3)),
        "reye_pose": rng.normal(0, 0.1, (T, 3)),
        "left_hand_pose": rng.normal(0, 0.2, (T, 15, 3)),
        "right_hand_pose": rng.normal(0, 0.2, (T, 15, 3)),
        "transl": rng.normal(0, 0.05, (T, 3)),
    }


@dataclass
class Tiny:
    root: Path
    cameras: list[CameraSpec]
    params: dict[str, dict[str, np.ndarray]]
    rgb: dict[tuple[str, int, str], np.ndarray] = field(default_factory=dict)
    alpha: dict[tuple[str, int, str], np.ndarray] = field(default_factory=dict)
    parts: dict[tuple[str, int, str], np.ndarray] = field(default_factory=dict)


def write_tiny_dataset(root: Path, *, num_cameras: int = 2, frames: int = 3, width: int = 32,
                       height: int = 24, sequences: tuple[str, ...] = ("seq0",),
                       masks: bool = True, parts: bool = True, seed: int = 0,
                       image_format: str = "png") -> Tiny:
    """A dataset of random pictures: every view gets a random foreground rectangle."""
    rng = np.random.default_rng(seed)
    cams = ring_cameras(num_cameras, width, height, seed=seed)
    tiny = Tiny(Path(root), cams, {s: random_smplx(frames, rng) for s in sequences})
    writer = DatasetWriter(
        root, name="tiny", fps=25.0, cameras=cams, part_names=list(SMPLX_PART_NAMES),
        upper_body_parts=list(UPPER_BODY_PARTS), subject={"identity": "tiny-0"},
        body_model={"type": "smplx", "num_betas": 10, "num_expression": 10, "source": "test"},
        image_format=image_format, subject_bounds=BOX, synthetic=True)
    for seq in sequences:
        for f in range(frames):
            for cam in cams:
                key = (seq, f, cam.name)
                tiny.rgb[key] = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
                a = np.zeros((height, width), np.uint8)
                a[4:18, 6:20] = 255
                tiny.alpha[key] = a
                tiny.parts[key] = np.where(a > 0, rng.integers(1, 28, a.shape), 0).astype(
                    np.uint8)
                writer.write_view(seq, f, cam.name, tiny.rgb[key],
                                  a if masks else None, tiny.parts[key] if parts else None)
        writer.write_params(seq, tiny.params[seq])
    names = [c.name for c in cams]
    writer.write_splits({
        "train": {"sequences": list(sequences), "cameras": names[:-1] or names},
        "novel_view": {"sequences": list(sequences), "cameras": names[-1:]},
    })
    writer.close()
    return tiny


# -- VHAP / GaussianAvatars ------------------------------------------------------------------

def opengl_c2w(spec: CameraSpec) -> np.ndarray:
    """NeRF/Blender `transform_matrix`: camera-to-world with y up, z backward."""
    c2w = np.eye(4)
    c2w[:3, :3] = spec.R.T
    c2w[:3, 3] = -spec.R.T @ spec.t
    c2w[:3, 1:3] *= -1
    return c2w


@dataclass
class VhapTruth:
    src: Path                                         # the folder to import
    cameras: list[CameraSpec]
    sequences: dict[str, list[int]]                   # expected sequence -> source timesteps
    flame: dict[str, dict[str, np.ndarray]]           # expected sequence -> flame_* arrays
    rgb: dict[tuple[str, int, str], np.ndarray]       # (expected seq, frame, cam) -> RGB
    alpha: dict[tuple[str, int, str], np.ndarray]
    splits: dict[str, dict[str, list[str]]]


def _flame_step(rng: np.random.Generator, shape: np.ndarray, static: np.ndarray) -> dict:
    return {"translation": rng.normal(0, 0.02, (1, 3)), "rotation": rng.normal(0, 0.2, (1, 3)),
            "neck_pose": rng.normal(0, 0.1, (1, 3)), "jaw_pose": rng.normal(0, 0.1, (1, 3)),
            "eyes_pose": rng.normal(0, 0.1, (1, 6)), "expr": rng.normal(0, 1, (1, 4)),
            "shape": shape, "static_offset": static}


def _write_png(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR) if img.ndim == 3 else img)


def _vhap_sequence(folder: Path, cams: list[CameraSpec], steps: int, rng, shape, static
                   ) -> tuple[list[dict], list[dict], list[np.ndarray], list[np.ndarray]]:
    """One exported sequence folder: images, fg_masks, flame_param; returns its frame records
    (paths relative to the folder), the FLAME dicts, and the images and masks in order."""
    records, flame, rgbs, alphas = [], [], [], []
    h, w = cams[0].height, cams[0].width
    for ts in range(steps):
        step = _flame_step(rng, shape, static)
        flame.append(step)
        (folder / "flame_param").mkdir(parents=True, exist_ok=True)
        np.savez(folder / "flame_param" / f"{ts:05d}.npz", **step)
        for ci, cam in enumerate(cams):
            rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
            alpha = np.zeros((h, w), np.uint8)
            alpha[3:20, 5:25] = rng.integers(2, 256)  # a 0/1 mask would be scaled
            _write_png(folder / "images" / f"{ts:05d}_{ci:02d}.png", rgb)
            _write_png(folder / "fg_masks" / f"{ts:05d}_{ci:02d}.png", alpha)
            rgbs.append(rgb)
            alphas.append(alpha)
            K = cam.K
            records.append({
                "timestep_index": ts, "timestep_index_original": ts, "timestep_id": f"f{ts}",
                "camera_index": ci, "camera_id": f"2222000{ci:02d}",
                "cx": K[0, 2], "cy": K[1, 2], "fl_x": K[0, 0], "fl_y": K[1, 1],
                "h": h, "w": w, "camera_angle_x": 2 * np.arctan(w / (2 * K[0, 0])),
                "camera_angle_y": 2 * np.arctan(h / (2 * K[1, 1])),
                "transform_matrix": opengl_c2w(cam).tolist(),
                "file_path": f"images/{ts:05d}_{ci:02d}.png",
                "fg_mask_path": f"fg_masks/{ts:05d}_{ci:02d}.png",
                "flame_param_path": f"flame_param/{ts:05d}.npz",
            })
    return records, flame, rgbs, alphas


def _write_transforms(folder: Path, division: str, frames: list[dict]) -> None:
    doc = {"frames": frames, "timestep_indices": sorted({f["timestep_index"] for f in frames}),
           "camera_indices": sorted({f["camera_index"] for f in frames})}
    if frames:  # shared intrinsics, as VHAP adds them
        doc.update({k: frames[-1][k] for k in ("cx", "cy", "fl_x", "fl_y", "h", "w")})
    (folder / f"transforms_{division}.json").write_text(json.dumps(doc, indent=1))


def _stack_flame(steps: list[dict]) -> dict[str, np.ndarray]:
    out = {f"flame_{k}": np.concatenate([s[k] for s in steps])
           for k in ("translation", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "expr")}
    out["flame_shape"] = steps[0]["shape"]
    out["flame_static_offset"] = steps[0]["static_offset"][0]
    return out


def write_vhap_fixture(parent: Path, *, combined: bool, num_cameras: int = 3,
                       seed: int = 0) -> VhapTruth:
    """A VHAP export under `parent`. Single: one sequence, train/val on the first 7 of 10
    timesteps (val = the last camera), test on the rest. Combined (combine_nerf_datasets):
    two sequence folders and a UNION folder whose paths point into them with '../'."""
    rng = np.random.default_rng(seed)
    cams = ring_cameras(num_cameras, 32, 24, radius=1.0, seed=seed)
    # VHAP names cameras by their serial: camera_id.
    cams = [CameraSpec(f"2222000{i:02d}", c.K, c.R, c.t, c.width, c.height, role="front")
            for i, c in enumerate(cams)]
    shape, static = rng.normal(0, 1, 5), rng.normal(0, 0.01, (1, 7, 3))
    val_cam = num_cameras - 1
    rgb, alpha = {}, {}

    def record(seq: str, frame: int, ci: int, r: np.ndarray, a: np.ndarray) -> None:
        rgb[(seq, frame, cams[ci].name)] = r
        alpha[(seq, frame, cams[ci].name)] = a

    if not combined:
        src = parent / "306_EMO-1_v16_DS4"
        recs, flame, rgbs, alphas = _vhap_sequence(src, cams, 10, rng, shape, static)
        base = "306_EMO-1_v16_DS4"
        seqs = {f"{base}-train-val": list(range(7)), f"{base}-test": list(range(7, 10))}
        for rec, r, a in zip(recs, rgbs, alphas, strict=True):
            ts = rec["timestep_index"]
            seq = f"{base}-train-val" if ts < 7 else f"{base}-test"
            record(seq, ts if ts < 7 else ts - 7, rec["camera_index"], r, a)
        _write_transforms(src, "train", [r for r in recs if r["timestep_index"] < 7
                                         and r["camera_index"] != val_cam])
        _write_transforms(src, "val", [r for r in recs if r["timestep_index"] < 7
                                       and r["camera_index"] == val_cam])
        _write_transforms(src, "test", [r for r in recs if r["timestep_index"] >= 7])
        flames = {f"{base}-train-val": _stack_flame(flame[:7]),
                  f"{base}-test": _stack_flame(flame[7:])}
        train_seqs, test_seqs = [f"{base}-train-val"], [f"{base}-test"]
    else:
        src = parent / "UNION_306"
        src.mkdir(parents=True)
        seqs, flames, union = {}, {}, {"train": [], "val": [], "test": []}
        offset = 0
        for name, steps, division in (("306_EMO-1", 4, "train"), ("306_EMO-2", 3, "test")):
            recs, flame, rgbs, alphas = _vhap_sequence(parent / name, cams, steps, rng, shape,
                                                       static)
            seqs[name] = list(range(offset, offset + steps))
            flames[name] = _stack_flame(flame)
            for rec, r, a in zip(recs, rgbs, alphas, strict=True):
                record(name, rec["timestep_index"], rec["camera_index"], r, a)
                rec = dict(rec, timestep_index=rec["timestep_index"] + offset)
                for key in ("file_path", "fg_mask_path", "flame_param_path"):
                    rec[key] = f"../{name}/{rec[key]}"
                if division == "test":
                    union["test"].append(rec)
                else:
                    union["val" if rec["camera_index"] == val_cam else "train"].append(rec)
            offset += steps
        for division, frames in union.items():
            _write_transforms(src, division, frames)
        train_seqs, test_seqs = ["306_EMO-1"], ["306_EMO-2"]
    names = [c.name for c in cams]
    splits = {"train": {"sequences": train_seqs, "cameras": names[:val_cam]},
              "novel_view": {"sequences": train_seqs, "cameras": [names[val_cam]]},
              "self_reenactment": {"sequences": test_seqs, "cameras": names}}
    return VhapTruth(src, cams, seqs, flames, rgb, alpha, splits)


# -- EasyMocap -------------------------------------------------------------------------------

def _yml_matrix(key: str, m: np.ndarray) -> list[str]:
    m = np.atleast_2d(m)
    return [f"{key}: !!opencv-matrix", f"  rows: {m.shape[0]}", f"  cols: {m.shape[1]}",
            "  dt: d", "  data: [" + ", ".join(repr(float(x)) for x in m.reshape(-1)) + "]"]


def _write_yml(path: Path, names: list[str], entries: list[tuple[str, np.ndarray | int]]
               ) -> None:
    """OpenCV FileStorage YAML the way EasyMocap's FileStorage class writes it (with full
    precision instead of its 6 decimals, so a round trip can be exact)."""
    lines = ["%YAML:1.0", "---", "names:"] + [f'  - "{n}"' for n in names]
    for key, value in entries:
        lines += [f"{key}: {value}"] if isinstance(value, int) else _yml_matrix(key, value)
    path.write_text("\r\n".join(lines) + "\r\n")


@dataclass
class EasyMocapTruth:
    src: Path
    cameras: list[CameraSpec]          # engine convention (K with +0.5)
    K_cv: dict[str, np.ndarray]
    dist: dict[str, np.ndarray]
    frames: list[int]                  # source frame numbers
    params: dict[str, np.ndarray]      # expected SMPL-X arrays (origin convention)
    Rh: np.ndarray
    Th: np.ndarray
    root: np.ndarray                   # poses[:, :3]
    images: dict[tuple[int, str], np.ndarray] = field(default_factory=dict)  # decoded source
    masks: dict[tuple[int, str], np.ndarray] = field(default_factory=dict)   # 0/255


def write_easymocap_fixture(root: Path, *, layout: int = 165, num_cameras: int = 3,
                            distortion: bool = False, with_size: bool = True,
                            seed: int = 0) -> EasyMocapTruth:
    """intri/extri.yml, images/<cam>/<frame:06d>.jpg, 0/1 masks and SMPL-X json for two
    people (ids 3 and 7; person 3 is the one in every frame) at frames 0, 5, 10, 15."""
    rng = np.random.default_rng(seed)
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    cams = ring_cameras(num_cameras, 40, 30, radius=3.0, seed=seed)
    names = [f"{i + 1:02d}" for i in range(num_cameras)]
    cams = [CameraSpec(n, c.K, c.R, c.t, c.width, c.height) for n, c in zip(names, cams,
                                                                           strict=True)]
    K_cv = {c.name: c.K - np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]]) for c in cams}
    dist = {c.name: (np.array([-0.2, 0.05, 0.001, -0.002, 0.01]) if distortion
                     else np.zeros(5)) for c in cams}
    intri, extri = [], []
    for c in cams:
        intri += [(f"K_{c.name}", K_cv[c.name]), (f"dist_{c.name}", dist[c.name][None])]
        if with_size:
            intri += [(f"H_{c.name}", c.height), (f"W_{c.name}", c.width)]
        extri += [(f"R_{c.name}", cv2.Rodrigues(c.R)[0]), (f"Rot_{c.name}", c.R),
                  (f"T_{c.name}", c.t.reshape(3, 1))]
    _write_yml(root / "intri.yml", names, intri)
    _write_yml(root / "extri.yml", names, extri)

    frames = [0, 5, 10, 15]
    T = len(frames)
    p = random_smplx(T, rng)
    Rh, Th = rng.normal(0, 0.3, (T, 3)), rng.normal(0, 0.1, (T, 3))
    if layout == 165:
        poses = np.concatenate([np.zeros((T, 3)), p["body_pose"].reshape(T, 63), p["jaw_pose"],
                                p["leye_pose"], p["reye_pose"], p["left_hand_pose"].reshape(T, 45),
                                p["right_hand_pose"].reshape(T, 45)], axis=1)
        hands = {"left_hand_pose": p["left_hand_pose"], "right_hand_pose": p["right_hand_pose"]}
    else:
        lh, rh = rng.normal(0, 1, (T, 6)), rng.normal(0, 1, (T, 6))
        poses = np.concatenate([np.zeros((T, 3)), p["body_pose"].reshape(T, 63), lh, rh,
                                p["jaw_pose"], p["leye_pose"], p["reye_pose"]], axis=1)
        hands = {"left_hand_pose": lh, "right_hand_pose": rh}
    truth = EasyMocapTruth(root, cams, K_cv, dist, frames, {
        "betas": p["betas"], "expression": p["expression"], "global_orient": Rh,
        "transl": Th, "body_pose": p["body_pose"], "jaw_pose": p["jaw_pose"],
        "leye_pose": p["leye_pose"], "reye_pose": p["reye_pose"], **hands}, Rh, Th,
        np.zeros((T, 3)))
    smpl = root / "output-smplx" / "smpl"
    smpl.mkdir(parents=True)
    for i, f in enumerate(frames):
        people = [{"id": 3, "Rh": [Rh[i].tolist()], "Th": [Th[i].tolist()],
                   "poses": [poses[i].tolist()], "shapes": [p["betas"].tolist()],
                   "expression": [p["expression"][i].tolist()]}]
        if i % 2 == 0:  # a second person, not in every frame
            people.insert(0, {"id": 7, "Rh": [[0, 0, 0]], "Th": [[1, 0, 0]],
                              "poses": [np.zeros(layout).tolist()], "shapes": [[0] * 10],
                              "expression": [[0] * 10]})
        (smpl / f"{f:06d}.json").write_text(json.dumps(people))
        for c in cams:
            img = rng.integers(0, 256, (c.height, c.width, 3), dtype=np.uint8)
            path = root / "images" / c.name / f"{f:06d}.jpg"
            path.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(path), img)  # BGR on disk; the truth is what decodes back
            truth.images[(f, c.name)] = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
            mask = np.zeros((c.height, c.width), np.uint8)
            mask[5:25, 8 + i:30] = 1
            _write_png(root / "mask" / c.name / f"{f:06d}.png", mask)
            truth.masks[(f, c.name)] = mask * 255
    return truth
