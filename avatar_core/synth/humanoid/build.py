"""`make_humanoid`: assembles the pieces into a `Humanoid`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from avatar_core.body.skeleton import SMPLX_PART_NAMES, swap_left_right

from .fields import _expressions, _shape_fields
from .hands import _hand_poses
from .head import _MOUTH_Y, _ear, _eye, _head, _head_grid, _mouth_pocket, _teeth
from .landmarks import _landmarks
from .limbs import _arm, _finger, _foot, _leg, _palm
from .mirror import _mirror
from .names import _FINGER_NAMES, _PART, EXPRESSION_NAMES, SHAPE_NAMES
from .proportions import _body
from .rig import _joints, _mirrored_weights, _semantic
from .trunk import _neck, _torso


@dataclass(frozen=True)
class Humanoid:
    """A rest-pose body mesh with everything a parametric body model file needs."""

    vertices: np.ndarray  # [V, 3] float64, rest pose
    faces: np.ndarray  # [F, 3] int64, outward CCW
    joints: np.ndarray  # [55, 3] rest joints, SMPL-X order
    joint_regressor: np.ndarray  # [55, V] convex rows, joint_regressor @ vertices == joints
    skinning_weights: np.ndarray  # [V, 55] convex rows
    part_labels: np.ndarray  # [V] index into SMPLX_PART_NAMES
    materials: np.ndarray  # [V] index into MATERIALS
    flame_region: np.ndarray  # [V] bool: head (eyes, ears, mouth interior) + upper neck
    hand_region: dict[str, np.ndarray]  # {"left", "right"}: [V] bool, hand + wrist cuff
    mirror_index: np.ndarray  # [V] vertex reflected by x -> -x
    semantic_vertices: dict[str, int]
    landmark_faces: np.ndarray  # [51] iBUG 17..67
    landmark_bary: np.ndarray  # [51, 3]
    contour_faces: np.ndarray  # [17] iBUG 0..16
    contour_bary: np.ndarray  # [17, 3]
    shape_basis: np.ndarray  # [V, 3, 10]
    shape_names: tuple[str, ...]
    expression_basis: np.ndarray  # [V, 3, 10], zero outside flame_region
    expression_names: tuple[str, ...]
    hand_poses: dict[str, np.ndarray]  # right hand, name -> [15, 3] axis-angle


def make_humanoid(seed: int = 0, resolution: float = 1.0) -> Humanoid:
    """Build the humanoid; `seed` perturbs proportions, `resolution` scales the vertex count
    (1.0 gives slightly more vertices than SMPL-X's 10,475)."""
    if not 0.1 <= resolution <= 2.0:
        raise ValueError("resolution must lie in [0.1, 2.0]")
    res = float(resolution)
    b = _body(seed)
    hg = _head_grid(res)
    head = _head(b, hg)
    loc = head.attrs["local"]
    lips_z = float(loc[(head.attrs["design_y"] == _MOUTH_Y) & (loc[:, 0] == 0.0), 2].max())
    pieces = [_torso(b, res), _neck(b, res), head, _eye(b, res), _ear(b, res, hg),
              _mouth_pocket(b, res, lips_z), _teeth(b, res, lips_z, True),
              _teeth(b, res, lips_z, False), _arm(b, res), _palm(b, res),
              *[_finger(b, res, k) for k in range(5)], _leg(b, res), _foot(b, res)]
    m = _mirror(pieces)
    weights = _mirrored_weights(np.concatenate([p.weights for p in pieces]), m)
    part_h = np.concatenate([p.part for p in pieces])
    pmap = np.array([_PART[swap_left_right(n)] for n in SMPLX_PART_NAMES])
    hand_left = np.concatenate([np.concatenate([p.hand for p in pieces]),
                                np.zeros(len(m.off_seam), dtype=bool)])
    regressor, joints = _joints(m, pieces, b)
    sem = _semantic(pieces, m, b)
    lf, lb = _landmarks(hg, m.face_start[id(head)], m.num_half_faces)
    tips = m.verts[[sem[f"r{f}"] for f in _FINGER_NAMES]]
    return Humanoid(
        vertices=m.verts, faces=m.faces, joints=joints, joint_regressor=regressor,
        skinning_weights=weights,
        part_labels=np.concatenate([part_h, pmap[part_h[m.off_seam]]]).astype(np.int64),
        materials=m.rows(np.concatenate([p.material for p in pieces])).astype(np.int64),
        flame_region=m.rows(np.concatenate([p.flame for p in pieces])),
        hand_region={"left": hand_left, "right": hand_left[m.mirror]}, mirror_index=m.mirror,
        semantic_vertices=sem, landmark_faces=lf[17:], landmark_bary=lb[17:],
        contour_faces=lf[:17], contour_bary=lb[:17],
        shape_basis=m.field(np.concatenate([_shape_fields(p, b) for p in pieces])),
        shape_names=SHAPE_NAMES, expression_basis=_expressions(pieces, m, b),
        expression_names=EXPRESSION_NAMES, hand_poses=_hand_poses(joints, tips),
    )
