"""Fusing FLAME face and MANO hand parameters into an SMPL-X parameter set (the MVFGA recipe).

Conventions
-----------
Joint roles. FLAME's joints play SMPL-X's: root -> neck (12), neck -> head (15), jaw -> jaw (22),
left/right eye -> left/right eye (23/24). MANO's wrist -> the SMPL-X wrist (20 left, 21 right)
and its 15 finger joints -> the hand joints in the same order (index, middle, pinky, ring, thumb).
Rest frames of all three families are world-aligned (identity rest rotations, y up, +z front).

Kept from the body. `betas`, `global_orient`, `transl` and every body joint except those the
face or a hand drives (neck, head, wrists) are kept.

FLAME -> SMPL-X.
- `expr` -> `expression`: SMPL-X's expression space is FLAME's (true of SMPL-X 2020 and of the
  synthetic models). Extra FLAME components beyond the SMPL-X model's are dropped with a warning.
- `jaw_pose` -> `jaw_pose`; `eyes_pose[:3]` -> `leye_pose`, `eyes_pose[3:]` -> `reye_pose`.
- `neck_pose` -> the SMPL-X head joint's local rotation (body_pose[14]).
- `rotation` (head_rotation=):
  "world" (default): FLAME's root rotation is the head's orientation in the world (camera)
  frame, as a face tracker reports it; the SMPL-X neck's local rotation is solved so that the
  neck's world rotation equals it, given the body's global orientation and spine.
  "local": it becomes the SMPL-X neck's local rotation as is. "keep": the body's neck is kept.
- `translation` is ignored: the body places the head.
- `shape` (identity): FLAME's shape space is not SMPL-X's betas. Its displacement, computed by
  the FLAME model, is carried to SMPL-X as `vertex_offsets` through the vertex correspondence,
  faded to zero toward the neck by the SMPL-X skinning weight of head, jaw and eyes, so the
  seam stays closed. Needs `flame_model` and the correspondence.

MANO -> SMPL-X.
- `hand_pose` is made absolute with the MANO model's own PCA and mean (`hand_pca`,
  `flat_hand_mean`), then re-expressed relative to the SMPL-X model's hand mean. Fusion writes
  full 45-D poses, so the SMPL-X model must have hand_pca=None.
- Mirroring (mirror=True): parameters of one hand's model used for the other hand (e.g. a
  right-hand model run on a flipped image of a left hand). Reflection x -> -x maps an
  axis-angle (x, y, z) to (x, -y, -z), for finger joints and for the global orientation.
- `global_orient` (wrist=): "world" (default) solves the SMPL-X wrist's local rotation so the
  wrist's world rotation equals it; "local" uses it as the wrist's local rotation; "keep"
  keeps the body's wrist.
- `betas` and `transl` are ignored: SMPL-X's body shape defines its hands, and the arm places them.

The front door. :class:`FusionModels` bundles the models fusion needs, built once by the caller
(trainer, evaluator, streaming session); ``models.fuse(body, flame, hands)`` fuses one parameter
set (one frame or a batch), :func:`fuse_sequence` a sequence's ``params.npz`` arrays (SMPL-X
keys, FLAME keys prefixed ``flame_``, MANO keys ``mano_left_`` / ``mano_right_``).
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..dataset.params import frame_slice
from . import lbs
from .errors import ParameterError
from .models import FLAMEModel, MANOModel, SMPLXModel
from .params import FLAMEParams, MANOParams, SMPLXParams
from .skeleton import JOINT

_FACE_JOINTS = (JOINT["head"], JOINT["jaw"], JOINT["left_eye_smplhf"], JOINT["right_eye_smplhf"])
_MODES = ("world", "local", "keep")

log = logging.getLogger(__name__)

SMPLX_KEYS = ("betas", "expression", "global_orient", "body_pose", "jaw_pose", "leye_pose",
              "reye_pose", "left_hand_pose", "right_hand_pose", "transl", "vertex_offsets")
# FLAME keys fusion uses; static/dynamic offsets (VHAP) have no SMPL-X counterpart here.
FLAME_FUSED = ("shape", "expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation")

_MIRROR = torch.tensor([1.0, -1.0, -1.0])


def mirror_axis_angle(pose: Tensor) -> Tensor:
    """Reflect rotations through the x = 0 plane. [..., 3] -> [..., 3]."""
    return pose * _MIRROR.to(dtype=pose.dtype, device=pose.device)


def _body_index(joint: int) -> int:
    return joint - 1  # body_pose holds joints 1..21


def _local_from_world(p: dict[str, Tensor], model: SMPLXModel, joint: int,
                      world_aa: Tensor) -> Tensor:
    """Local axis-angle of `joint` that gives it the world rotation `world_aa` [B, 3]."""
    full = model.full_pose(p)  # [B, 55, 3]
    chain, j = [], model.parents[joint]
    while j != -1:
        chain.append(j)
        j = model.parents[j]
    rot = lbs.rodrigues(full[:, chain[::-1]])  # [B, n, 3, 3] root first
    parent_world = rot[:, 0]
    for i in range(1, rot.shape[1]):
        parent_world = parent_world @ rot[:, i]
    return lbs.rotation_to_axis_angle(parent_world.transpose(-1, -2) @ lbs.rodrigues(world_aa))


def _split_body(body: SMPLXParams | dict[str, Any], model: SMPLXModel
                ) -> tuple[dict[str, Tensor], Any]:
    """Normalised pose and shape tensors, and the vertex offsets (passed through untouched)."""
    raw = body.to_dict() if isinstance(body, SMPLXParams) else dict(body)
    offsets = raw.pop("vertex_offsets", None)
    spec = {k: v for k, v in model.param_spec().items() if k != "vertex_offsets"}
    return model._normalize(raw, spec, model.family), offsets


def _broadcast(p: dict[str, Tensor], batch: int) -> dict[str, Tensor]:
    return {k: v.expand(batch, *v.shape[1:]).clone() for k, v in p.items()}


def _set_rotation(p: dict[str, Tensor], model: SMPLXModel, joint: int, aa: Tensor,
                  mode: str) -> None:
    if mode == "keep":
        return
    if mode == "world":
        aa = _local_from_world(p, model, joint, aa)
    p["body_pose"][:, _body_index(joint)] = aa


def _check_mode(name: str, mode: str) -> None:
    if mode not in _MODES:
        raise ParameterError(f"{name} must be one of {_MODES}, got {mode!r}")


def fuse_flame(body: SMPLXParams | dict[str, Any], flame: FLAMEParams | dict[str, Any],
               model: SMPLXModel, *, flame_model: FLAMEModel | None = None,
               correspondence: np.ndarray | None = None,
               head_rotation: str = "world") -> SMPLXParams:
    """SMPL-X parameters with the face driven by FLAME parameters (see the module docstring)."""
    _check_mode("head_rotation", head_rotation)
    p, offsets = _split_body(body, model)
    fspec = (flame_model.param_spec() if flame_model is not None else
             {"shape": (0,), "expr": (model.num_expression,), "rotation": (3,), "neck_pose": (3,),
              "jaw_pose": (3,), "eyes_pose": (6,), "translation": (3,)})
    f_raw = flame.to_dict() if isinstance(flame, FLAMEParams) else dict(flame)
    if flame_model is None and f_raw.get("shape") is not None:
        raise ParameterError("fusing a FLAME shape needs flame_model= and correspondence=")
    if flame_model is None and f_raw.get("expr") is not None:
        fspec["expr"] = (np.shape(f_raw["expr"])[-1],)
    f = model._normalize(f_raw, fspec, "FLAME")
    batch = max(p["betas"].shape[0], f["expr"].shape[0])
    p, f = _broadcast(p, batch), _broadcast(f, batch)

    n = min(model.num_expression, f["expr"].shape[1])
    if f["expr"].shape[1] > n and f["expr"][:, n:].abs().max() > 0:
        warnings.warn(f"FLAME expression has {f['expr'].shape[1]} components; the SMPL-X model "
                      f"takes {model.num_expression}, the rest are dropped", stacklevel=2)
    p["expression"] = torch.zeros_like(p["expression"])
    p["expression"][:, :n] = f["expr"][:, :n]
    p["jaw_pose"] = f["jaw_pose"]
    p["leye_pose"], p["reye_pose"] = f["eyes_pose"][:, :3], f["eyes_pose"][:, 3:]
    p["body_pose"][:, _body_index(JOINT["head"])] = f["neck_pose"]
    _set_rotation(p, model, JOINT["neck"], f["rotation"], head_rotation)

    out = {**p, "vertex_offsets": offsets}
    if flame_model is not None and f["shape"].shape[1] and f["shape"].abs().max() > 0:
        if correspondence is None:
            raise ParameterError("fusing a FLAME shape needs the FLAME -> SMPL-X correspondence")
        out["vertex_offsets"] = _face_shape_offsets(f["shape"], flame_model, model,
                                                    np.asarray(correspondence), offsets)
    return SMPLXParams.from_dict(out)


def _face_shape_offsets(shape: Tensor, flame_model: FLAMEModel, model: SMPLXModel,
                        correspondence: np.ndarray, base: Any) -> Tensor:
    if len(correspondence) != flame_model.num_vertices:
        raise ParameterError(f"correspondence has {len(correspondence)} entries, the FLAME model "
                             f"{flame_model.num_vertices} vertices")
    local = _model_indices(model, correspondence)
    disp = lbs.blend_shapes(shape, flame_model.shapedirs)  # [B, Vf, 3]
    fade = model.weights[:, list(_FACE_JOINTS)].sum(-1)  # [V]
    idx = torch.as_tensor(local, device=model.device)
    offsets = torch.zeros(shape.shape[0], model.num_vertices, 3, dtype=model.dtype,
                          device=model.device)
    offsets[:, idx] = disp * fade[idx, None]
    if base is not None:
        offsets = offsets + torch.as_tensor(np.asarray(base) if not isinstance(base, Tensor)
                                            else base, dtype=model.dtype, device=model.device)
    return offsets


def _model_indices(model: SMPLXModel, smplx_ids: np.ndarray) -> np.ndarray:
    """Map SMPL-X vertex indices to the model's own (the upper-body model is a subset)."""
    ids = model.data.vertex_ids
    if ids is None:
        return smplx_ids.astype(np.int64)
    lookup = np.full(int(max(ids.max(), smplx_ids.max())) + 1, -1, dtype=np.int64)
    lookup[ids] = np.arange(len(ids))
    local = lookup[smplx_ids]
    if (local < 0).any():
        raise ParameterError(f"{int((local < 0).sum())} corresponding vertices are not in the "
                             f"model (cut away?)")
    return local


def fuse_mano(body: SMPLXParams | dict[str, Any], hand: MANOParams | dict[str, Any],
              model: SMPLXModel, *, side: str, mano_model: MANOModel | None = None,
              mirror: bool = False, wrist: str = "world") -> SMPLXParams:
    """SMPL-X parameters with one hand driven by MANO parameters (see the module docstring).

    Without `mano_model`, `hand_pose` must be the absolute full pose [B, 15, 3].
    """
    _check_mode("wrist", wrist)
    if side not in ("left", "right"):
        raise ParameterError(f"side must be 'left' or 'right', got {side!r}")
    if model.hand_pca:
        raise ParameterError("fusion writes full hand poses: use an SMPL-X model with "
                             "hand_pca=None")
    p, offsets = _split_body(body, model)
    spec = (mano_model.param_spec() if mano_model is not None else
            {"betas": (10,), "global_orient": (3,), "hand_pose": (15, 3), "transl": (3,)})
    h = model._normalize(hand, spec, "MANO")
    batch = max(p["betas"].shape[0], h["hand_pose"].shape[0])
    p, h = _broadcast(p, batch), _broadcast(h, batch)
    full = mano_model.hand_pose_full(h["hand_pose"]) if mano_model is not None else h["hand_pose"]
    orient = h["global_orient"]
    if mirror:
        full, orient = mirror_axis_angle(full), mirror_axis_angle(orient)
    p[f"{side}_hand_pose"] = full - getattr(model, f"{side}_hand_mean")
    _set_rotation(p, model, JOINT[f"{side}_wrist"], orient, wrist)
    return SMPLXParams.from_dict({**p, "vertex_offsets": offsets})


def fuse(body: SMPLXParams | dict[str, Any], model: SMPLXModel, *,
         flame: FLAMEParams | dict | None = None, flame_model: FLAMEModel | None = None,
         correspondence: np.ndarray | None = None, left_hand: MANOParams | dict | None = None,
         right_hand: MANOParams | dict | None = None,
         mano_models: dict[str, MANOModel] | None = None, head_rotation: str = "world",
         wrist: str = "world") -> SMPLXParams:
    """Face and both hands in one call; each part is optional."""
    out = body if isinstance(body, SMPLXParams) else SMPLXParams.from_dict(dict(body))
    if flame is not None:
        out = fuse_flame(out, flame, model, flame_model=flame_model,
                         correspondence=correspondence, head_rotation=head_rotation)
    for side, hand in (("left", left_hand), ("right", right_hand)):
        if hand is not None:
            out = fuse_mano(out, hand, model, side=side,
                            mano_model=(mano_models or {}).get(side), wrist=wrist)
    return out


# -- the front door -----------------------------------------------------------------------


@dataclass
class FusionModels:
    """What fusion needs: the SMPL-X model (full hand poses: ``hand_pca=None``; float64 for
    accuracy where the caller can afford it), the MANO models per side and, for a FLAME shape,
    FLAME and its SMPL-X vertex correspondence."""

    smplx: SMPLXModel
    mano: dict[str, MANOModel] = field(default_factory=dict)
    flame: FLAMEModel | None = None
    correspondence: np.ndarray | None = None

    def fuse(self, body: Mapping[str, Any], flame: Mapping[str, Any] | None = None,
             hands: Mapping[str, Mapping[str, Any] | None] | None = None) -> dict[str, Any]:
        """SMPL-X parameters (one frame or a batch) with the face and hands fused in, world-frame
        head and wrists, no gradient; ``body`` as it is when there is nothing to fuse. ``hands``:
        {side: MANO parameters}. None values are left out of the result."""
        hands = {side: h for side, h in (hands or {}).items() if h}
        if not flame and not hands:
            return dict(body)
        with torch.no_grad():
            fused = fuse(dict(body), self.smplx, flame=flame or None, flame_model=self.flame,
                         correspondence=self.correspondence, left_hand=hands.get("left"),
                         right_hand=hands.get("right"), mano_models=self.mano)
        return {k: v for k, v in fused.to_dict().items() if v is not None}


def split_tracker_keys(params: Mapping[str, np.ndarray]
                       ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray],
                                  dict[str, dict[str, np.ndarray]]]:
    """(SMPL-X keys, FLAME keys without ``flame_``, {side: MANO keys without
    ``mano_<side>_``}); other keys are dropped."""
    body = {k: v for k, v in params.items() if k in SMPLX_KEYS}
    flame = {k[len("flame_"):]: v for k, v in params.items() if k.startswith("flame_")}
    hands = {s: {k[len(f"mano_{s}_"):]: v for k, v in params.items()
                 if k.startswith(f"mano_{s}_")} for s in ("left", "right")}
    return body, flame, hands


def per_frame(params: Mapping[str, np.ndarray], num_frames: int) -> dict[str, np.ndarray]:
    """Every array [T, ...]: shared ones (betas [B], offsets [V, 3]) repeated per frame."""
    frames = [frame_slice(params, f) for f in range(num_frames)]
    return {k: np.stack([np.asarray(fr[k]) for fr in frames]) for k in params}


def fuse_sequence(params: Mapping[str, np.ndarray], num_frames: int,
                  models: FusionModels | None, *, strict: bool = False
                  ) -> tuple[dict[str, np.ndarray], bool]:
    """float64 SMPL-X arrays [T, ...] of one sequence's ``params.npz`` arrays, fused with its
    FLAME/MANO keys when ``models`` is given and they exist (else its SMPL-X keys as they are),
    and whether it was fused. A FLAME shape without a FLAME model is dropped with a warning,
    or, ``strict``, raises ParameterError, as MANO keys without that side's MANO model do."""
    body, flame, hands = split_tracker_keys(per_frame(params, num_frames))
    flame = {k: v for k, v in flame.items() if k in FLAME_FUSED}
    hands = {side: h for side, h in hands.items() if h}
    fused = models is not None and bool(flame or hands)
    if fused:
        if "shape" in flame and models.flame is None:
            if strict:
                raise ParameterError("fusing a FLAME shape needs the FLAME model")
            log.warning("fusion: no FLAME model given, the FLAME shape is ignored")
            flame.pop("shape")
        if strict and set(hands) - set(models.mano):
            raise ParameterError("fusing MANO hand poses needs the MANO models")
        body = {k: v.detach().cpu().numpy() if isinstance(v, Tensor) else np.asarray(v)
                for k, v in models.fuse(body, flame, hands).items()}
    return {k: np.array(np.broadcast_to(np.asarray(v, dtype=np.float64),
                                        (num_frames, *np.shape(v)[1:])))
            for k, v in body.items()}, fused
