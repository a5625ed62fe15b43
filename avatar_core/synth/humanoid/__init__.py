"""Procedural stand-in for the SMPL-X body: a stylised humanoid in the SMPL-X rest pose.

The mesh is assembled from simple parts (lofted cross-sections and tubes) that may
interpenetrate but are each closed, except the head, whose surface has slits for the mouth and
the eyes. Only the left half (+x) and the midline are modelled; the right half is an exact
mirror, so every attribute is symmetric by construction.

Conventions: metres, y up, the face looks toward +z, the subject's left is +x, T-pose with the
palms down. The pelvis joint sits near the origin; the soles are near y = -0.95.

Modules: `names` (public name tables), `primitives` (grids, tubes, lofts, weight blends),
`proportions` (the seeded individual), `pieces`, `trunk`, `head`, `limbs` (the body parts),
`fields` (shape and expression fields), `mirror`, `hands` (hand poses), `landmarks`, `rig`
(skinning, joints, regressor) and `build` (`make_humanoid`).
"""

from .build import Humanoid, make_humanoid
from .names import EXPRESSION_NAMES, MATERIALS, SEMANTIC_NAMES, SHAPE_NAMES

__all__ = ["EXPRESSION_NAMES", "MATERIALS", "SEMANTIC_NAMES", "SHAPE_NAMES", "Humanoid",
           "make_humanoid"]
