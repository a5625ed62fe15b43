"""Avatar packages: one directory (or its zip) that a server can load and serve.

    avatar.json     schema version, name, metadata, metrics, body-model reference, training config
    gaussians.npz   parents, local_means, log_scales, quats, opacity_logits, sh

The body-model reference names the model (e.g. "synthetic:seed0" or "SMPLX_NEUTRAL.npz"), the
upper-body parts, the identity's betas and a fingerprint of the triangle list the Gaussians
are bound to, so loading onto a different mesh fails clearly instead of rendering garbage.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np
import torch

from ..bounded_npz import NpzError, NpzLimits, check_zip_members, open_zip, read_npz
from .avatar import GaussianAvatar
from .validate import GaussianRanges, RangeError, check_gaussian_ranges

SCHEMA_VERSION = 1
MANIFEST, GAUSSIANS = "avatar.json", "gaussians.npz"
MAX_PACKAGE_BYTES = 512 * 2**20  # uncompressed; configurable per call
MAX_PACKAGE_MEMBERS = 16  # a package zip holds two files (and maybe their folder)
MAX_MANIFEST_BYTES = 4 * 2**20  # avatar.json: metadata and config, sent to clients


class PackageError(ValueError):
    """An avatar package is missing, malformed, from a newer schema, or unsafe to unpack."""


def faces_fingerprint(faces: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(faces, dtype=np.int64).tobytes()).hexdigest()


@dataclass
class BodyReference:
    model: str                       # "synthetic:seed0", or the model file's name
    parts: list[str]                 # upper-body part names of the cut
    num_faces: int
    faces_sha256: str
    betas: list[float] = field(default_factory=list)

    def check_faces(self, faces: np.ndarray) -> None:
        if len(faces) != self.num_faces or faces_fingerprint(faces) != self.faces_sha256:
            raise PackageError(f"the avatar is bound to another mesh ({self.num_faces} faces, "
                               f"{self.faces_sha256[:12]}...), not this one ({len(faces)} faces)")


@dataclass
class AvatarPackage:
    avatar: GaussianAvatar
    body: BodyReference
    name: str = "avatar"
    metadata: dict[str, Any] = field(default_factory=dict)
    metrics: dict[str, Any] = field(default_factory=dict)
    training: dict[str, Any] = field(default_factory=dict)

    def manifest(self) -> dict[str, Any]:
        return {"schema_version": SCHEMA_VERSION, "name": self.name, "metadata": self.metadata,
                "metrics": self.metrics, "training": self.training,
                "gaussians": {"file": GAUSSIANS, "count": self.avatar.num,
                              "sh_degree": self.avatar.sh_degree},
                "body_model": self.body.__dict__}


def save_package(package: AvatarPackage, path: str | Path) -> Path:
    """Write a package directory, or a zip if `path` ends in .zip."""
    path = Path(path)
    arrays = {k: v.detach().cpu().numpy() for k, v in package.avatar.tensors().items()}
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    manifest = json.dumps(package.manifest(), indent=2).encode()
    if path.suffix == ".zip":
        path.parent.mkdir(parents=True, exist_ok=True)
        with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
            z.writestr(MANIFEST, manifest)
            z.writestr(GAUSSIANS, buf.getvalue())
    else:
        path.mkdir(parents=True, exist_ok=True)
        (path / MANIFEST).write_bytes(manifest)
        (path / GAUSSIANS).write_bytes(buf.getvalue())
    return path


def _read_members(path: Path, max_bytes: int, limits: NpzLimits) -> tuple[bytes, bytes]:
    if path.is_dir():
        files = [path / MANIFEST, path / GAUSSIANS]
        for f in files:
            if not f.is_file():
                raise PackageError(f"{path}: missing {f.name}")
        if sum(f.stat().st_size for f in files) > max_bytes:
            raise PackageError(f"{path}: larger than the {max_bytes} byte limit")
        return files[0].read_bytes(), files[1].read_bytes()
    if not zipfile.is_zipfile(path):
        raise PackageError(f"{path}: not an avatar package (a directory or a .zip)")
    with open_zip(path, MAX_PACKAGE_MEMBERS, what="package") as z:
        infos = z.infolist()
        check_zip_members(infos, limits, what="package")
        for info in infos:  # nothing is extracted to disk, but refuse suspicious archives
            name = PurePosixPath(info.filename)
            if name.is_absolute() or ".." in name.parts or "\\" in info.filename:
                raise PackageError(f"{path}: unsafe member name {info.filename!r}")
        if sum(i.file_size for i in infos) > max_bytes:
            raise PackageError(f"{path}: unpacks to more than the {max_bytes} byte limit")
        names = {PurePosixPath(i.filename).name: i for i in infos if not i.is_dir()}
        for required in (MANIFEST, GAUSSIANS):
            if required not in names:
                raise PackageError(f"{path}: missing {required}")
        if names[MANIFEST].file_size > MAX_MANIFEST_BYTES:
            raise PackageError(f"{path}: {MANIFEST} is larger than {MAX_MANIFEST_BYTES} bytes")
        return z.read(names[MANIFEST]), z.read(names[GAUSSIANS])


def _check_manifest_types(path: Path, manifest: dict, body: BodyReference) -> None:
    """JSON types a loader relies on (a wrong one would fail later, far from its cause)."""
    ok = (isinstance(body.model, str) and isinstance(body.faces_sha256, str)
          and isinstance(body.parts, list) and all(isinstance(p, str) for p in body.parts)
          and type(body.num_faces) is int and body.num_faces >= 0
          and isinstance(body.betas, list)
          and all(type(b) in (int, float) for b in body.betas))
    if not ok:
        raise PackageError(f"{path}: body_model in {MANIFEST} has a field of the wrong type")
    for key in ("metadata", "metrics", "training"):
        if not isinstance(manifest.get(key, {}), dict):
            raise PackageError(f"{path}: '{key}' in {MANIFEST} must be an object")


def load_package(path: str | Path, *, max_bytes: int = MAX_PACKAGE_BYTES,
                 dtype: torch.dtype = torch.float32,
                 npz_limits: NpzLimits | None = None,
                 ranges: GaussianRanges | None = None) -> AvatarPackage:
    """Read and validate a package directory or zip; ``ranges`` bounds the Gaussians' values
    (default :class:`GaussianRanges`). ``max_bytes`` bounds the files, and
    (unless ``npz_limits`` says otherwise) each array and all of them, unpacked."""
    path = Path(path)
    if not path.exists():
        raise PackageError(f"no avatar package at {path}")
    limits = npz_limits or NpzLimits(max_array_bytes=max_bytes, max_total_bytes=max_bytes)
    try:
        manifest_bytes, npz_bytes = _read_members(path, max_bytes, limits)
    except (NpzError, zipfile.BadZipFile, zlib.error, EOFError, OSError, NotImplementedError,
            RuntimeError) as exc:  # a damaged zip: bad CRC, truncated stream, odd method
        raise PackageError(f"{path}: unreadable: {exc}") from None
    try:
        manifest = json.loads(manifest_bytes)
    except (ValueError, RecursionError) as exc:
        raise PackageError(f"{path}: {MANIFEST} is not valid JSON: {exc}") from None
    version = manifest.get("schema_version") if isinstance(manifest, dict) else None
    if not isinstance(version, int) or not 1 <= version <= SCHEMA_VERSION:
        raise PackageError(f"{path}: unsupported schema_version {version!r} "
                           f"(this build reads 1..{SCHEMA_VERSION})")
    try:
        body = BodyReference(**manifest["body_model"])
    except (KeyError, TypeError) as exc:
        raise PackageError(f"{path}: bad or missing body_model in {MANIFEST}: {exc}") from exc
    _check_manifest_types(path, manifest, body)
    try:
        arrays = read_npz(npz_bytes, limits)  # shapes and sizes checked before reading
    except NpzError as exc:
        raise PackageError(f"{path}: {GAUSSIANS} is unreadable: {exc}") from None
    tensors = {}
    for name in ("parents", "local_means", "log_scales", "quats", "opacity_logits", "sh"):
        if name not in arrays:
            raise PackageError(f"{path}: {GAUSSIANS} lacks '{name}'")
        arr = arrays[name]
        if name != "parents" and not np.isfinite(arr).all():
            raise PackageError(f"{path}: '{name}' contains NaN or Inf")
        if arr.dtype.kind not in ("iu" if name == "parents" else "iuf"):
            raise PackageError(f"{path}: '{name}' has dtype {arr.dtype}, not a real number type")
        arr = arr.astype(arr.dtype.newbyteorder("="), copy=False)  # torch takes native order
        tensors[name] = torch.as_tensor(arr, dtype=torch.long if name == "parents" else dtype)
    parents = tensors["parents"]
    if parents.dim() != 1:
        raise PackageError(f"{path}: 'parents' must be [N], not {list(parents.shape)}")
    if parents.numel() and (parents.min() < 0 or parents.max() >= body.num_faces):
        raise PackageError(f"{path}: parent triangle indices outside [0, {body.num_faces})")
    try:
        avatar = GaussianAvatar(**tensors)
        check_gaussian_ranges(**avatar.tensors(), num_faces=body.num_faces, ranges=ranges)
    except (ValueError, RangeError) as exc:
        raise PackageError(f"{path}: {exc}") from exc
    return AvatarPackage(avatar=avatar, body=body, name=str(manifest.get("name", path.stem)),
                         metadata=manifest.get("metadata", {}), metrics=manifest.get("metrics", {}),
                         training=manifest.get("training", {}))
