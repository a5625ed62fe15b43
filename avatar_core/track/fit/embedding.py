"""The learned landmark embedding: where each MediaPipe landmark lies on our body model.

Each row of the fitter's keypoint layout (`correspondence`: face iBUG-68 from the face mesh,
hands 21 x 2, pose 33) keeps its model point (a joint, a vertex or a face triangle with its
barycentric weights) and gains an offset carried by one joint's frame:

    keypoint_k(theta) = base_k(theta) + Rw_j(theta) (offset_k + B_k [theta_j, theta_par(j)])

(j = joint_k) so the offset turns with the bone (BlazePose's ears sit above the ear vertices
whichever way the head turns); B_k, a pose-dependent correction linear in the anchor's and
its parent's axis-angle, is non-zero only where cross-validation calls for it. Fitted on
studio renders with known parameters (`avatar_core.synth.embedding_build`,
`telesplat track build-embedding`) and stored as a versioned asset: an .npz of arrays beside
a .json of its version and metadata. The fitter loads it as data; nothing here imports the studio.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...body.skeleton import JOINT
from . import correspondence as cor

EMBEDDING_FORMAT = "telesplat-landmark-embedding"
EMBEDDING_VERSION = 1
# The committed asset (built by the command in docs/tracking.md).
DEFAULT_EMBEDDING = Path(__file__).parent / "assets" / "landmark_embedding.npz"
MAX_OFFSET_M = 0.25  # an offset larger than this is no landmark definition: a corrupt file


class EmbeddingError(ValueError):
    """A landmark embedding file that is missing, of another version, or malformed."""


def anchor_joints() -> np.ndarray:
    """[K] the joint whose frame carries each row's offset: the head for the face and the
    head points of the pose, each hand point its own finger joint (tips: the last one), each
    body joint itself, the hips the pelvis; -1 where the layout has no model point."""
    out = np.full(cor.NUM_KEYPOINTS, -1, dtype=np.int64)
    out[cor.FACE_SLICE] = JOINT["head"]
    for side, sl in (("left", cor.LEFT_HAND_SLICE), ("right", cor.RIGHT_HAND_SLICE)):
        for k, name in enumerate(cor.HAND_MP_TO_SMPLX):
            finger = name[4:] + "3" if name.startswith("tip:") else name
            out[sl.start + k] = JOINT[f"{side}_{finger}"]
    for k, name in enumerate(cor.POSE_MP_TO_SMPLX):
        if name is None:
            continue
        kind, key = name.split(":")
        if kind == "vertex":
            out[cor.POSE_SLICE.start + k] = JOINT["head"]
        elif key.endswith("_hip"):
            out[cor.POSE_SLICE.start + k] = JOINT["pelvis"]
        else:
            out[cor.POSE_SLICE.start + k] = JOINT[key]
    return out


@dataclass(frozen=True)
class LandmarkEmbedding:
    joint: np.ndarray    # [K] int64: anchor joint of each row (-1: no offset)
    offset: np.ndarray   # [K, 3] float64 m, in the anchor joint's frame
    # BlazePose's z against our model's depth differences: model dz = world_z_scale x world
    # dz (metres), and f dz / d = image_z_scale x image dz (px), fitted by the builder.
    world_z_scale: float = 1.0
    image_z_scale: float = 1.0
    metadata: dict = field(default_factory=dict)
    # [K, 3, 6] m/rad: the pose-dependent correction (None: none).
    pose_basis: np.ndarray | None = None

    def __post_init__(self) -> None:
        joint, offset = np.asarray(self.joint), np.asarray(self.offset)
        if self.pose_basis is not None:
            basis = np.asarray(self.pose_basis)
            if basis.shape != (cor.NUM_KEYPOINTS, 3, 6) or not np.isfinite(basis).all() or \
                    np.abs(basis).max(initial=0) > MAX_OFFSET_M:
                raise EmbeddingError(f"pose_basis must be finite [{cor.NUM_KEYPOINTS}, 3, 6] "
                                     f"within {MAX_OFFSET_M} m/rad, got {list(basis.shape)}")
        if joint.shape != (cor.NUM_KEYPOINTS,) or offset.shape != (cor.NUM_KEYPOINTS, 3):
            raise EmbeddingError(
                f"embedding arrays must be joint [{cor.NUM_KEYPOINTS}] and offset "
                f"[{cor.NUM_KEYPOINTS}, 3], got {list(joint.shape)} and {list(offset.shape)}")
        if not np.isfinite(offset).all() or np.abs(offset).max(initial=0) > MAX_OFFSET_M:
            raise EmbeddingError(f"embedding offsets must be finite and within "
                                 f"{MAX_OFFSET_M} m")
        if joint.min() < -1 or joint.max() >= 55:
            raise EmbeddingError("embedding anchor joints must be in [-1, 55)")
        for name in ("world_z_scale", "image_z_scale"):
            value = getattr(self, name)
            if not (np.isfinite(value) and 0.1 <= value <= 10.0):
                raise EmbeddingError(f"{name} must be in [0.1, 10], got {value}")

    @classmethod
    def zero(cls) -> LandmarkEmbedding:
        """Today's correspondence: every offset 0."""
        return cls(anchor_joints(), np.zeros((cor.NUM_KEYPOINTS, 3)))

    def save(self, path: str | Path) -> tuple[Path, Path]:
        """Writes PATH (.npz) and its .json sidecar; returns both paths."""
        npz = Path(path).with_suffix(".npz")
        npz.parent.mkdir(parents=True, exist_ok=True)
        basis = np.zeros((cor.NUM_KEYPOINTS, 3, 6)) if self.pose_basis is None else \
            self.pose_basis
        np.savez_compressed(npz, joint=np.asarray(self.joint, dtype=np.int64),
                            offset=np.asarray(self.offset, dtype=np.float64),
                            pose_basis=np.asarray(basis, dtype=np.float64))
        meta = {"format": EMBEDDING_FORMAT, "version": EMBEDDING_VERSION,
                "layout": {"keypoints": cor.NUM_KEYPOINTS, "face": "ibug68",
                           "hands": 21, "pose": cor.NUM_POSE},
                "world_z_scale": float(self.world_z_scale),
                "image_z_scale": float(self.image_z_scale), "metadata": self.metadata}
        sidecar = npz.with_suffix(".json")
        sidecar.write_text(json.dumps(meta, indent=1, sort_keys=True) + "\n")
        return npz, sidecar


def load_embedding(path: str | Path = DEFAULT_EMBEDDING) -> LandmarkEmbedding:
    """Reads an embedding (.npz + .json); EmbeddingError says what is wrong with it."""
    npz = Path(path).with_suffix(".npz")
    sidecar = npz.with_suffix(".json")
    for p in (npz, sidecar):
        if not p.is_file():
            raise EmbeddingError(f"landmark embedding file not found: {p}")
    try:
        meta = json.loads(sidecar.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise EmbeddingError(f"{sidecar}: not a readable JSON file ({exc})") from exc
    if not isinstance(meta, dict) or meta.get("format") != EMBEDDING_FORMAT:
        raise EmbeddingError(f"{sidecar}: not a landmark embedding (format "
                             f"{meta.get('format') if isinstance(meta, dict) else None!r})")
    if meta.get("version") != EMBEDDING_VERSION:
        raise EmbeddingError(f"{sidecar}: embedding version {meta.get('version')!r}, this "
                             f"code reads version {EMBEDDING_VERSION}; rebuild it with "
                             f"'telesplat track build-embedding'")
    try:
        with np.load(npz, allow_pickle=False) as data:
            joint, offset = np.asarray(data["joint"]), np.asarray(data["offset"])
            basis = np.asarray(data["pose_basis"]) if "pose_basis" in data.files else None
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise EmbeddingError(f"{npz}: not a readable embedding array file ({exc})") from exc
    if joint.dtype.kind != "i" or offset.dtype.kind != "f":
        raise EmbeddingError(f"{npz}: joint must be integer and offset float arrays")
    scales = []
    for name in ("world_z_scale", "image_z_scale"):
        try:
            scales.append(float(meta.get(name, 1.0)))
        except (TypeError, ValueError) as exc:
            raise EmbeddingError(f"{sidecar}: {name} is not a number") from exc
    if basis is not None and basis.dtype.kind != "f":
        raise EmbeddingError(f"{npz}: pose_basis must be a float array")
    return LandmarkEmbedding(joint.astype(np.int64), offset.astype(np.float64), *scales,
                             dict(meta.get("metadata") or {}),
                             None if basis is None else basis.astype(np.float64))
