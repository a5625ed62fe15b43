"""Eye rotations (`leye_pose`, `reye_pose`) from the tracked iris centres.

The body is fitted first; the eyes then turn about their joints (left_eye_smplhf,
right_eye_smplhf) so that the model's iris centres project onto the tracked ones.

- **The model's iris centre.** Each eyeball is the set of vertices skinned at least
  `MIN_EYE_WEIGHT` to its eye joint; its front pole is the one farthest forward (+z) in the
  template. The iris model reports the centre of the visible iris disc, which lies inside the
  eyeball, not on it: an iris of ~6 mm radius on an eyeball of ~12 mm is seen at ~30 deg from
  the eye's centre, so its disc sits at cos 30 deg = `IRIS_DEPTH` of the way from the eye joint
  to the front pole (the synthetic actor's texture: 29 deg). A model with no eyeball vertices
  gets no gaze: the solver says why and leaves the eye rotations as they are.
- **Solve.** For each eye, the camera ray through the iris pixel meets the sphere swept by the
  iris centre (centre: the posed eye joint) at the iris centre's new place (closed form; a
  ray that misses takes the sphere's point nearest to it); the rotation from the rest
  direction to it starts Gauss-Newton on the pixel error of (pitch, yaw): the axis-angle
  (x, y, 0) in the head's frame, no roll. Each step is clamped to the eye's joint limit
  (`JOINT_LIMITS_DEG`, 30 deg, as a cone).
- **Shared gaze** (default): people move both eyes together, so one rotation is fitted to
  both iris centres (when only one is usable, it drives both). That halves the variance of a
  per-eye fit; it ignores vergence (eyes converging on a near point: ~3 deg each at 0.6 m).
- **Unusable eyes** (left unchanged, or driven by the other eye when shared): an iris centre
  that is NaN or off the frame, an eye behind the camera, an eye turned more than
  `MAX_VIEW_DEG` away from the camera.

Iris centres come in `FaceLandmarks.iris` order: the person's right eye, then the left eye.
Signs (the model faces +z, y up): +pitch turns the gaze down, +yaw to the person's left. Use:

    params.update(fit_gaze(model, params, face.iris[:, 0, :2], camera, betas))
"""

from __future__ import annotations

import dataclasses
import math
import weakref
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from ...body import lbs
from ...body.joint_limits import JOINT_LIMITS_DEG
from ...body.models import SMPLXModel
from ...body.skeleton import JOINT
from .camera import MIN_DEPTH_M, WebcamCamera, project_points

EYES = ("right", "left")  # rows of iris_px: the person's right eye, then left eye
EYE_JOINT = {"right": JOINT["right_eye_smplhf"], "left": JOINT["left_eye_smplhf"]}
EYE_PARAM = {"right": "reye_pose", "left": "leye_pose"}
EYE_LIMIT_DEG = JOINT_LIMITS_DEG.get("left_eye_smplhf", 30.0)
MIN_EYE_WEIGHT = 0.5
IRIS_DEPTH = math.cos(math.radians(30.0))
MAX_VIEW_DEG = 70.0
ITERATIONS = 8
STEP_TOL = 1e-7  # radians: Gauss-Newton has converged
FD_STEP = 1e-6   # radians: the Jacobian's forward difference


@dataclass(frozen=True)
class GazeFit:
    params: dict[str, np.ndarray]  # {"leye_pose": [3], "reye_pose": [3]} axis-angle
    used: tuple[bool, bool]        # (right eye, left eye): iris centres that were fitted
    residual_px: float             # RMS reprojection error over the used eyes (NaN: none)
    reason: str | None = None      # why nothing was fitted (params unchanged), else None


@dataclass(frozen=True)
class _Eye:
    """One eye in the current body pose (model space): joint, parent rotation, rest offset."""

    joint: np.ndarray   # [3] posed eye joint: the centre of rotation
    parent: np.ndarray  # [3, 3] world rotation of the head (the eye's frame at zero pose)
    offset: np.ndarray  # [3] iris centre - joint at zero eye pose, in the head's frame

    def iris(self, pitch_yaw: np.ndarray) -> np.ndarray:
        rot = _rotation(np.array([pitch_yaw[0], pitch_yaw[1], 0.0]))
        return self.joint + self.parent @ (rot @ self.offset)  # [3]


def _rotation(axis_angle: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(axis_angle)[0]  # [3, 3]; a tenth of the torch version's time here


def pupil_vertices(model: SMPLXModel) -> dict[str, int] | str:
    """Each eye's front pole: of the vertices skinned >= MIN_EYE_WEIGHT to that eye joint, the
    one farthest forward (+z) in the template. A string saying why when an eye has none."""
    weights, template = model.data.weights, model.data.v_template
    out = {}
    for eye in EYES:
        ids = np.flatnonzero(weights[:, EYE_JOINT[eye]] >= MIN_EYE_WEIGHT)
        if ids.size == 0:
            return (f"the body model has no eyeball: no vertex is skinned to "
                    f"{eye}_eye_smplhf (weight >= {MIN_EYE_WEIGHT})")
        out[eye] = int(ids[np.argmax(template[ids, 2])])
    return out


class GazeSolver:
    """Eye rotations for one body model; `fit(params, iris_px, camera)` per frame. Holds a
    copy of the model cut down to the two pupil vertices (the joints are the full model's).
    iris_depth: where the iris disc sits, as a fraction of the joint -> front pole distance."""

    def __init__(self, model: SMPLXModel, iris_depth: float = IRIS_DEPTH) -> None:
        self.iris_depth = iris_depth
        found = pupil_vertices(model)
        self.reason = found if isinstance(found, str) else None
        self.model: SMPLXModel | None = None
        if self.reason is None:
            data = dataclasses.replace(model.data, lmk_faces=None, dynamic_lmk_faces=None)
            keep = np.sort([found[eye] for eye in EYES])  # subset keeps them sorted
            self.rows = {eye: int(np.searchsorted(keep, found[eye])) for eye in EYES}
            self.model = SMPLXModel(data.subset(keep), dtype=torch.float64, cache=False,
                                    hand_pca=model.hand_pca,
                                    flat_hand_mean=model.flat_hand_mean)
        self.limit = math.radians(EYE_LIMIT_DEG)

    def eyes(self, params: dict[str, np.ndarray], betas: np.ndarray | None = None
             ) -> dict[str, _Eye]:
        """Both eyes in the body pose of `params` (their own rotations ignored)."""
        assert self.model is not None
        spec = self.model.param_spec()
        p = {k: torch.as_tensor(np.asarray(v, dtype=np.float64))
             for k, v in params.items() if k in spec and k != "vertex_offsets"}
        for eye in EYES:
            p[EYE_PARAM[eye]] = torch.zeros(3, dtype=torch.float64)
        if betas is not None:
            b = np.ravel(np.asarray(betas, dtype=np.float64))[:self.model.num_betas]
            p["betas"] = torch.as_tensor(np.pad(b, (0, self.model.num_betas - b.size)))
        with torch.no_grad():
            out = self.model(p)
            world = lbs.global_rotations(lbs.rodrigues(out.full_pose), self.model.parents)[0]
        out_eyes = {}
        for eye in EYES:
            j = EYE_JOINT[eye]
            parent = world[self.model.parents[j]].numpy()  # [3, 3]
            joint = out.joints[0, j].numpy()
            front = out.vertices[0, self.rows[eye]].numpy()
            out_eyes[eye] = _Eye(joint, parent, self.iris_depth * parent.T @ (front - joint))
        return out_eyes

    def usable(self, eye: _Eye, px: np.ndarray, camera: WebcamCamera) -> bool:
        """The iris pixel is finite and on the frame; the eye is in front of the camera and
        turned no more than MAX_VIEW_DEG away from it."""
        if not (np.isfinite(px).all() and 0 <= px[0] < camera.width
                and 0 <= px[1] < camera.height):
            return False
        depth = -float(eye.joint[2])
        if depth < MIN_DEPTH_M:
            return False
        forward = eye.parent @ eye.offset
        to_camera = -eye.joint
        cos = float(forward @ to_camera) / (np.linalg.norm(forward) * np.linalg.norm(to_camera))
        return cos > math.cos(math.radians(MAX_VIEW_DEG))

    def clamp(self, pitch_yaw: np.ndarray) -> np.ndarray:
        norm = float(np.linalg.norm(pitch_yaw))
        return pitch_yaw * (self.limit / norm) if norm > self.limit else pitch_yaw

    def ray_start(self, eye: _Eye, px: np.ndarray, camera: WebcamCamera) -> np.ndarray:
        """Closed form: (pitch, yaw) turning the rest direction to where the camera ray
        through `px` meets the iris centre's sphere (the nearest sphere point on a miss)."""
        ray = camera.unproject_depth(np.asarray(px, dtype=np.float64), 1.0)
        ray = ray / np.linalg.norm(ray)  # [3] from the camera at the origin
        radius = float(np.linalg.norm(eye.offset))
        along = float(ray @ eye.joint)
        disc = along ** 2 - float(eye.joint @ eye.joint) + radius ** 2
        hit = ray * (along - math.sqrt(disc) if disc >= 0 else along)
        target = eye.parent.T @ (hit - eye.joint)  # in the head's frame
        rest = eye.offset / radius
        axis = np.cross(rest, target)
        sin, cos = float(np.linalg.norm(axis)), float(rest @ target)
        if sin < 1e-12:
            return np.zeros(2)
        return self.clamp((axis / sin * math.atan2(sin, cos))[:2])

    def solve(self, eyes: list[_Eye], px: np.ndarray, camera: WebcamCamera,
              start: np.ndarray) -> tuple[np.ndarray, float]:
        """Gauss-Newton on (pitch, yaw) shared by `eyes` against their pixels [n, 2];
        returns the rotation and the RMS pixel error."""

        def residual(x: np.ndarray) -> np.ndarray:
            points = np.stack([e.iris(x) for e in eyes])  # [n, 3]
            return (project_points(points, camera)[0] - px).ravel()  # [2n]

        x = self.clamp(np.asarray(start, dtype=np.float64))
        r = residual(x)
        for _ in range(ITERATIONS):
            jac = np.stack([(residual(x + FD_STEP * np.eye(2)[i]) - r) / FD_STEP
                            for i in range(2)], axis=1)  # [2n, 2]
            step = np.linalg.lstsq(jac, -r, rcond=None)[0]
            x = self.clamp(x + step)
            r = residual(x)
            if np.linalg.norm(step) < STEP_TOL:
                break
        return x, float(np.sqrt(np.mean(np.sum(r.reshape(-1, 2) ** 2, axis=1))))

    def fit(self, params: dict[str, np.ndarray], iris_px: np.ndarray, camera: WebcamCamera,
            betas: np.ndarray | None = None, shared: bool = True) -> GazeFit:
        """Eye rotations for the fitted body `params` (smplx names; betas from `params` or
        `betas`) and the iris centres `iris_px` [2, 2+] (person's right eye, left eye;
        NaN: not seen)."""
        before = {EYE_PARAM[e]: np.asarray(params.get(EYE_PARAM[e], np.zeros(3)),
                                           dtype=np.float64).reshape(3).copy() for e in EYES}
        if self.reason is not None:
            return GazeFit(before, (False, False), math.nan, self.reason)
        px = np.asarray(iris_px, dtype=np.float64).reshape(2, -1)[:, :2]  # [2, 2]
        if not np.isfinite(px).any():
            return GazeFit(before, (False, False), math.nan, "no iris seen")
        eyes = self.eyes(params, betas if betas is not None else params.get("betas"))
        used = tuple(bool(self.usable(eyes[e], px[k], camera)) for k, e in enumerate(EYES))
        seen = [k for k in range(2) if used[k]]
        if not seen:
            return GazeFit(before, (False, False), math.nan,
                           "no usable iris (off the frame, or the eye faces away)")
        starts = {k: self.ray_start(eyes[EYES[k]], px[k], camera) for k in seen}
        out = dict(before)
        if shared:
            x, rms = self.solve([eyes[EYES[k]] for k in seen], px[seen], camera,
                                np.mean([starts[k] for k in seen], axis=0))
            for e in EYES:
                out[EYE_PARAM[e]] = np.array([x[0], x[1], 0.0])
        else:
            errors = []
            for k in seen:
                x, rms = self.solve([eyes[EYES[k]]], px[[k]], camera, starts[k])
                out[EYE_PARAM[EYES[k]]] = np.array([x[0], x[1], 0.0])
                errors.append(rms)
            rms = float(np.sqrt(np.mean(np.square(errors))))
        return GazeFit(out, used, rms)


_SOLVERS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def gaze_solver(model: SMPLXModel) -> GazeSolver:
    """The model's solver, built once (finding the pupils and cutting the model)."""
    solver = _SOLVERS.get(model)
    if solver is None:
        solver = _SOLVERS[model] = GazeSolver(model)
    return solver


def fit_gaze(model: SMPLXModel, params: dict[str, np.ndarray], iris_px: np.ndarray,
             camera: WebcamCamera, betas: np.ndarray | None = None,
             shared: bool = True) -> dict[str, np.ndarray]:
    """{"leye_pose": [3], "reye_pose": [3]} turning the eyes of the fitted body `params` onto
    the iris centres `iris_px` [2, 2+] (`FaceLandmarks.iris[:, 0]`: the person's right eye,
    then left; NaN rows: not seen). Unchanged values when no eye can be fitted
    (`gaze_solver(model).fit(...)` says why)."""
    return gaze_solver(model).fit(params, iris_px, camera, betas, shared).params
