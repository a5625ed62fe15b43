"""Import an EasyMocap multi-view capture with its SMPL-X fit.

Layout::

    SRC/intri.yml   OpenCV FileStorage: names (list), K_<cam> 3x3, dist_<cam> (or D_<cam>)
                    1x5 / 1x4, optional H_<cam>, W_<cam>
    SRC/extri.yml   R_<cam> 3x1 Rodrigues (or Rot_<cam> 3x3), T_<cam> 3x1; world -> camera
    SRC/images/<cam>/<frame:06d>.jpg (or .png)
    SRC/mask/<cam>/<frame:06d>.png   optional foreground masks (0/1 or 0/255)
    SRC/output-smplx/smpl/<frame:06d>.json   [{"id", "Rh" [1,3], "Th" [1,3], "poses" [1,N],
                                               "shapes" [1,10], "expression" [1,10]}, ...]

Supported `poses` layouts (EasyMocap's SMPL-X, `easymocap/smplmodel/body_model.py`):

- N = 87: 22 x 3 body (the first 3, the root, zero), 6 + 6 hand PCA coefficients (left,
  right), jaw, left eye, right eye. Imported as hand_pca = 6, flat_hand_mean = false (EasyMocap
  adds the hand mean to the PCA pose, as `smplx` does with flat_hand_mean=False).
- N = 165: the full axis-angle pose in `smplx` order: root, 21 body joints, jaw, left eye,
  right eye, 15 + 15 finger joints. Imported as hand_pca = null, flat_hand_mean = true
  (EasyMocap uses a 165-D pose as it is, without the mean).

Root: EasyMocap rotates the root-less posed body X about the world origin, V = R(Rh) X + Th,
while `smplx` rotates about the pelvis joint J0: V = R(go) (X - J0) + J0 + transl. Given the
SMPL-X model file, the import converts: global_orient = Rh, transl = Th + R(Rh) J0 - J0
(J0 from betas and expression), body_model.root = "smplx". Without it, Rh / Th are stored as
global_orient / transl and body_model.root = "origin" records the convention.

Calibration is OpenCV's (pixel centres on integers): cx, cy get +0.5. Images with lens
distortion are undistorted (cv2.undistort, same K); the coefficients go to `distortion`.
"""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from ..format import CameraSpec, opencv_to_engine_K
from ..imageio import read_header
from ..writer import DatasetWriter
from .common import (
    Progress,
    is_plain_rgb,
    mask_to_uint8,
    nearest_rotation,
    read_image,
    safe_name,
)

if TYPE_CHECKING:
    from ...body.model_data import ModelData

__all__ = ["EasyMocapCamera", "import_easymocap", "pelvis_rest", "poses_to_smplx",
           "read_easymocap_cameras", "root_to_smplx"]

_BODY_MARGIN = 1.5  # metres around Th that hold a whole body, whatever its pose


@dataclass(frozen=True)
class EasyMocapCamera:
    name: str
    K: np.ndarray           # OpenCV convention (pixel centres on integers)
    dist: np.ndarray        # [5] k1, k2, p1, p2, k3
    R: np.ndarray
    T: np.ndarray           # [3]
    size: tuple[int, int] | None  # (W, H) when the file has it


def _mat(fs: cv2.FileStorage, key: str) -> np.ndarray | None:
    node = fs.getNode(key)
    if node.empty():
        return None
    m = node.mat()
    return None if m is None else np.asarray(m, dtype=np.float64)


def _int(fs: cv2.FileStorage, key: str) -> int | None:
    node = fs.getNode(key)
    return None if node.empty() else int(node.real())


def _names(fs: cv2.FileStorage) -> list[str]:
    node = fs.getNode("names")
    out = []
    for i in range(node.size()):
        item = node.at(i)
        out.append(item.string() if item.isString() else str(int(item.real())))
    return out


def read_easymocap_cameras(intri: Path, extri: Path) -> list[EasyMocapCamera]:
    """The cameras of an intri.yml / extri.yml pair, in the order `names` lists them."""
    for p in (intri, extri):
        if not Path(p).is_file():
            raise ValueError(f"{p} is missing")
    fi = cv2.FileStorage(str(intri), cv2.FILE_STORAGE_READ)
    fe = cv2.FileStorage(str(extri), cv2.FILE_STORAGE_READ)
    try:
        names = _names(fi)
        if not names:
            raise ValueError(f"{intri} lists no camera names")
        cams = []
        for cam in names:
            K = _mat(fi, f"K_{cam}")
            dist = _mat(fi, f"dist_{cam}")
            dist = _mat(fi, f"D_{cam}") if dist is None else dist
            rvec, rot, T = _mat(fe, f"R_{cam}"), _mat(fe, f"Rot_{cam}"), _mat(fe, f"T_{cam}")
            if K is None or K.shape != (3, 3):
                raise ValueError(f"{intri}: K_{cam} missing or not 3x3")
            if T is None or T.size != 3:
                raise ValueError(f"{extri}: T_{cam} missing or not 3x1")
            if rvec is not None and rvec.size == 3:  # EasyMocap itself reads R_ (Rodrigues)
                R = cv2.Rodrigues(rvec.reshape(3, 1))[0]
            elif rot is not None:
                R = nearest_rotation(rot, f"{extri}: Rot_{cam}")
            else:
                raise ValueError(f"{extri}: neither R_{cam} nor Rot_{cam}")
            d = np.zeros(5) if dist is None else dist.reshape(-1)
            if d.size == 4:
                d = np.append(d, 0.0)
            if d.size != 5:
                raise ValueError(f"{intri}: dist_{cam} has {d.size} coefficients; only the "
                                 "4/5-coefficient OpenCV model is supported")
            w, h = _int(fi, f"W_{cam}"), _int(fi, f"H_{cam}")
            size = (w, h) if w and h and w > 0 and h > 0 else None
            cams.append(EasyMocapCamera(cam, K, d, R, T.reshape(3), size))
        return cams
    finally:
        fi.release()
        fe.release()


# -- SMPL-X parameters ----------------------------------------------------------------------

def _rotvec_to_matrix(v: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(v, dtype=np.float64).reshape(3, 1))[0]


def _matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(R)[0].reshape(3)


def poses_to_smplx(poses: np.ndarray) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """EasyMocap `poses` [T, N] -> (SMPL-X pose arrays incl. the root rotation under
    "root_pose", body_model fields for the hand convention). See the module docstring."""
    T, N = poses.shape
    out = {"root_pose": poses[:, 0:3], "body_pose": poses[:, 3:66].reshape(T, 21, 3)}
    if N == 87:
        out.update(left_hand_pose=poses[:, 66:72], right_hand_pose=poses[:, 72:78],
                   jaw_pose=poses[:, 78:81], leye_pose=poses[:, 81:84],
                   reye_pose=poses[:, 84:87])
        return out, {"hand_pca": 6, "flat_hand_mean": False}
    if N == 165:
        out.update(jaw_pose=poses[:, 66:69], leye_pose=poses[:, 69:72],
                   reye_pose=poses[:, 72:75], left_hand_pose=poses[:, 75:120].reshape(T, 15, 3),
                   right_hand_pose=poses[:, 120:165].reshape(T, 15, 3))
        return out, {"hand_pca": None, "flat_hand_mean": True}
    raise ValueError(f"EasyMocap poses have {N} values per frame; supported SMPL-X layouts: "
                     "87 (body 66 + hand PCA 6 + 6 + jaw/eyes 9) and 165 (full axis-angle)")


def pelvis_rest(model: ModelData, betas: np.ndarray, expression: np.ndarray | None
                ) -> np.ndarray:
    """The pelvis joint J0 [T, 3] of the shaped, unposed model (the smplx rotation centre)."""
    J0 = model.joint_template[0] + np.einsum("ck,tk->tc", model.joint_shapedirs[0], betas)
    if expression is not None and model.joint_exprdirs.shape[-1]:
        J0 = J0 + np.einsum("ck,tk->tc", model.joint_exprdirs[0], expression)
    return J0


def root_to_smplx(Rh: np.ndarray, Th: np.ndarray, root_pose: np.ndarray,
                  J0: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(global_orient, transl) [T, 3] from EasyMocap's Rh, Th and poses[:3].

    With J0 (pelvis [T, 3]): smplx's convention, global_orient = Rh * root_pose and
    transl = Th + R(Rh) J0 - J0. Without: Rh / Th as they are ("origin" convention), which
    needs a zero root_pose."""
    if J0 is None:
        if np.abs(root_pose).max(initial=0.0) > 1e-8:
            raise ValueError("EasyMocap poses[:3] (the root) is not zero: converting needs the "
                             "SMPL-X model (--smplx-model)")
        return Rh.copy(), Th.copy()
    orient, transl = np.empty_like(Rh), np.empty_like(Th)
    for i in range(len(Rh)):
        Rr = _rotvec_to_matrix(Rh[i])
        orient[i] = _matrix_to_rotvec(Rr @ _rotvec_to_matrix(root_pose[i]))
        transl[i] = Th[i] + Rr @ J0[i] - J0[i]
    return orient, transl


def _people(path: Path) -> list[dict[str, Any]]:
    doc = json.loads(path.read_text(encoding="utf-8"))
    people = doc.get("annots", doc) if isinstance(doc, dict) else doc
    if not isinstance(people, list):
        raise ValueError(f"{path}: expected a list of people")
    return people


def _pick_person(per_frame: list[list[dict[str, Any]]], person: int | None,
                 files: list[Path]) -> list[dict[str, Any]]:
    ids = [{int(p.get("id", 0)) for p in people} for people in per_frame]
    if person is None:
        common = set.intersection(*ids) if ids else set()
        if not common:
            raise ValueError("no person id appears in every frame; pick one with --person")
        person = min(common)
    out = []
    for people, path in zip(per_frame, files, strict=True):
        match = [p for p in people if int(p.get("id", 0)) == person]
        if not match:
            raise ValueError(f"{path}: person {person} is missing")
        out.append(match[0])
    return out


def _smplx_params(records: list[dict[str, Any]], files: list[Path], model_path: Path | None
                  ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    def stack(key: str) -> np.ndarray | None:
        if any(key not in r for r in records):
            return None
        rows = [np.asarray(r[key], dtype=np.float64).reshape(-1) for r in records]
        for row, path in zip(rows, files, strict=True):
            if row.shape != rows[0].shape:
                raise ValueError(f"{path.name} has {row.size} {key} values, {files[0].name} "
                                 f"{rows[0].size}: one layout per capture")
        return np.stack(rows)

    poses, Rh, Th = stack("poses"), stack("Rh"), stack("Th")
    if poses is None or Rh is None or Th is None:
        raise ValueError("every SMPL-X record needs poses, Rh and Th")
    if Rh.shape[1] != 3 or Th.shape[1] != 3:
        raise ValueError("Rh and Th must hold 3 values each")
    shapes, expression = stack("shapes"), stack("expression")
    pose, hands = poses_to_smplx(poses)
    T = len(records)
    betas = np.zeros((T, 10)) if shapes is None else shapes
    expression = np.zeros((T, 10)) if expression is None else expression
    J0 = None
    if model_path is not None:
        from ...body.model_data import load_smplx  # the body model only when converting

        model = load_smplx(model_path, num_betas=betas.shape[1],
                           num_expression=expression.shape[1])
        J0 = pelvis_rest(model, betas, expression)
    orient, transl = root_to_smplx(Rh, Th, pose.pop("root_pose"), J0)
    params = {"global_orient": orient, "transl": transl, **pose}
    shared = bool(np.all(betas == betas[0]))
    params["betas"] = betas[0] if shared else betas
    params["expression"] = expression
    body = {"type": "smplx", "num_betas": int(betas.shape[1]),
            "num_expression": int(expression.shape[1]),
            "source": "easymocap", **hands, "root": "origin" if J0 is None else "smplx"}
    return params, body


# -- images ---------------------------------------------------------------------------------

def _frame_file(folder: Path, frame: int) -> Path | None:
    for ext in (".jpg", ".png", ".jpeg"):
        p = folder / f"{frame:06d}{ext}"
        if p.is_file():
            return p
    return None


def _camera_spec(cam: EasyMocapCamera, image: Path) -> CameraSpec:
    if cam.size is not None:
        w, h = cam.size
    else:
        header = read_header(image)
        w, h = header.width, header.height
    return CameraSpec(cam.name, opencv_to_engine_K(cam.K), cam.R, cam.T, w, h,
                      distortion=cam.dist)


def import_easymocap(src: str | Path, out: str | Path, *, sequence: str | None = None,
                     person: int | None = None, smpl_dir: str = "output-smplx/smpl",
                     mask_dir: str | None = "mask", smplx_model: str | Path | None = None,
                     holdout_cameras: tuple[str, ...] = (), fps: float = 30.0,
                     image_format: str | None = None, identity: str | None = None,
                     progress: Progress | None = None, workers: int = 4) -> Path:
    """Convert the EasyMocap capture at `src` into a one-sequence dataset at `out`.
    `mask_dir` is used when it exists; `smplx_model` (a SMPL-X .npz/.pkl) converts Rh/Th to
    smplx's root convention; `holdout_cameras` form the novel_view split."""
    src = Path(src)
    cams = read_easymocap_cameras(src / "intri.yml", src / "extri.yml")
    files = sorted((p for p in (src / smpl_dir).glob("*.json") if p.stem.isdigit()),
                   key=lambda p: int(p.stem))
    if not files:
        raise ValueError(f"{src / smpl_dir}: no <frame>.json SMPL-X files")
    frames = [int(p.stem) for p in files]
    records = _pick_person([_people(p) for p in files], person, files)
    params, body_model = _smplx_params(records, files, None if smplx_model is None
                                       else Path(smplx_model))

    def lookup(kind: str, cam: str, frame: int) -> Path | None:
        return _frame_file(src / kind / cam, frame)

    images = {(c.name, f): lookup("images", c.name, f) for c in cams for f in frames}
    missing = [k for k, p in images.items() if p is None]
    if missing:
        raise ValueError(f"{len(missing)} images missing, e.g. {src}/images/{missing[0][0]}/"
                         f"{missing[0][1]:06d}.jpg")
    use_masks = mask_dir is not None and (src / mask_dir).is_dir()
    masks = {k: lookup(mask_dir, *k) for k in images} if use_masks else {}
    if use_masks and any(p is None for p in masks.values()):
        raise ValueError(f"{src / mask_dir} lacks masks for some views")
    specs = [_camera_spec(c, images[(c.name, frames[0])]) for c in cams]
    ext = image_format or images[(cams[0].name, frames[0])].suffix.lstrip(".").lower()
    ext = "jpg" if ext == "jpeg" else ext
    seq = safe_name(sequence or src.name)
    unknown = sorted(set(holdout_cameras) - {c.name for c in cams})
    if unknown:
        raise ValueError(f"unknown held-out camera(s) {unknown}")
    Th = np.asarray([np.asarray(r["Th"], dtype=np.float64).reshape(3) for r in records])
    bounds = [(Th.min(0) - _BODY_MARGIN).tolist(), (Th.max(0) + _BODY_MARGIN).tolist()]
    writer = DatasetWriter(
        out, name=f"easymocap-{src.name}", fps=fps, cameras=specs, part_names=[],
        upper_body_parts=[], subject={"identity": identity or src.name, "source": str(src),
                                      "person": int(records[0].get("id", 0))},
        body_model=body_model, image_format=ext, subject_bounds=bounds)
    by_name = {c.name: c for c in cams}

    def one(job: tuple[int, int, str]) -> None:
        i, frame, name = job
        cam, image, mask = by_name[name], images[(name, frame)], masks.get((name, frame))
        alpha = None if mask is None else mask_to_uint8(mask)
        distorted = bool(np.any(cam.dist != 0))
        if not distorted and is_plain_rgb(image, ext):
            writer.copy_view(seq, i, name, image, alpha)
            return
        rgb, _ = read_image(image)
        if distorted:
            rgb = cv2.undistort(rgb, cam.K, cam.dist)
            alpha = None if alpha is None else cv2.undistort(alpha, cam.K, cam.dist)
        writer.write_view(seq, i, name, rgb, alpha)

    jobs = [(i, f, c.name) for i, f in enumerate(frames) for c in cams]
    with ThreadPoolExecutor(workers) as pool:
        for done, _ in enumerate(pool.map(one, jobs), 1):
            if progress:
                progress(done, len(jobs))
    writer.write_params(seq, params, {"source_frames": frames})
    train = [c.name for c in cams if c.name not in holdout_cameras]
    splits = {"train": {"sequences": [seq], "cameras": train}}
    if holdout_cameras:
        splits["novel_view"] = {"sequences": [seq], "cameras": list(holdout_cameras)}
    writer.write_splits(splits)
    return writer.close()
