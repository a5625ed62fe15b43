"""The keypoints and their exact Jacobian in one pass, for the fitter's Gauss-Newton steps.

The fast twin of :class:`BodyKeypoints` (which stays the reference: tests compare points and
an autograd Jacobian of it against this). One frame, float64 numpy, with the betas fixed:

    rest joints  J = J(betas) + Jdirs psi             rest vertices  v = v(betas) + Edirs psi
    local R_j = exp(theta_j)                          v_posed = v + posedirs . (R - I)
    world Rw_k = Rw_p R_k,  Jw_k = Jw_p + Rw_p (J_k - J_p),  t_k = Jw_k - Rw_k J_k
    vertex  v' = sum_k w_vk (Rw_k v_posed + t_k) + transl

Derivatives (d exp(theta) = skew(Jl(theta) d theta) exp(theta), Jl the left Jacobian of SO(3)):
turning joint j by d theta turns everything below it about its world position Jw_j with the
world angular velocity omega = Rw_parent(j) Jl(theta_j) d theta, so

    dJw_k = omega x (Jw_k - Jw_j)                                   (k below j)
    dv'   = omega x (Q_vj - s_vj Jw_j) + Rb_v d v_posed             (Q, s: v's skinning
                                                                      restricted to below j)
and t_k = sum over k's chain m of (Rw_parent(m) - Rw_m) J_m is linear in the rest joints, which
gives the expression's effect through the joints. Landmarks are barycentric in the vertices.

Cost: one forward + Jacobian is a few dozen small numpy operations, against the reference's
batched forward differences (one model pass per free variable).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ...body.lbs import kinematic_levels
from .keypoints import BodyKeypoints

_SMALL_ANGLE_SQ = 1e-8


def skew(v: np.ndarray) -> np.ndarray:
    """[..., 3] -> [..., 3, 3] cross-product matrices."""
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def rodrigues_and_left_jacobian(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-angle [J, 3] -> rotations [J, 3, 3] and left Jacobians [J, 3, 3] (Taylor series
    near 0, where the closed forms divide by ~0)."""
    t2 = (theta ** 2).sum(-1)[:, None, None]  # [J, 1, 1]
    small = t2 < _SMALL_ANGLE_SQ
    safe = np.where(small, 1.0, t2)
    t = np.sqrt(safe)
    a = np.where(small, 1 - t2 / 6 + t2 ** 2 / 120, np.sin(t) / t)             # sin t / t
    b = np.where(small, 0.5 - t2 / 24 + t2 ** 2 / 720, (1 - np.cos(t)) / safe)  # (1-cos t)/t^2
    c = np.where(small, 1 / 6 - t2 / 120 + t2 ** 2 / 5040, (t - np.sin(t)) / (safe * t))
    k = skew(theta)
    k2 = k @ k
    eye = np.eye(3)
    return eye + a * k + b * k2, eye + b * k + c * k2


def _contour_row(rot: np.ndarray, chain: Sequence[int]) -> int:
    """Row of the face-contour look-up table for the head's yaw (`SMPLXModel._contour_rows`)."""
    rel = rot[chain[0]]
    for j in chain[1:]:
        rel = rot[j] @ rel
    yaw = np.arctan2(-rel[2, 0], np.sqrt(rel[0, 0] ** 2 + rel[1, 0] ** 2))
    if not np.isfinite(yaw):
        return 0  # a non-finite pose: its keypoints are NaN anyway
    deg = int(np.round(min(-yaw * 180.0 / np.pi, 39.0)))
    return deg if deg >= 0 else (78 if deg < -39 else 39 - deg)


class KeypointKinematics:
    """`evaluate(full_pose [J, 3], expression [E], transl [3], joints=...) ->
    (points [K, 3], dpoints_dpose [K, 3, len(joints), 3] | None, dpoints_dexpr [K, 3, E] | None)`
    for the keypoint layout of `keypoints` (rows it cannot produce are NaN, their
    derivatives 0). `betas` are fixed at construction."""

    def __init__(self, keypoints: BodyKeypoints, betas: np.ndarray) -> None:
        m = keypoints.model
        as_np = lambda t: t.detach().double().cpu().numpy()  # noqa: E731
        b = np.asarray(betas, dtype=np.float64).reshape(-1)
        self.parents = np.asarray(m.parents)
        n_j = len(self.parents)
        self.v_shape = as_np(m.v_template) + as_np(m.shapedirs) @ b           # [V, 3]
        self.j_shape = as_np(m.joint_template) + as_np(m.joint_shapedirs) @ b  # [J, 3]
        self.exprdirs = as_np(m.exprdirs)                                    # [V, 3, E]
        self.joint_exprdirs = as_np(m.joint_exprdirs)                        # [J, 3, E]
        n_v = self.v_shape.shape[0]
        # Pose correctives by joint: [J, 9, V*3] (root and inactive features zero).
        full = np.zeros((9 * (n_j - 1), n_v * 3))
        full[as_np(m.pose_feature_ids).astype(np.int64)] = as_np(m.posedirs)
        self.posedirs = np.concatenate([np.zeros((1, 9, n_v * 3)),
                                        full.reshape(n_j - 1, 9, n_v * 3)])
        self.feature_ids = as_np(m.pose_feature_ids).astype(np.int64)
        self.posedirs_active = as_np(m.posedirs)                             # [P', V*3]
        self.weights = as_np(m.weights)                                      # [V, J]
        self.levels = kinematic_levels(list(self.parents))
        # below[j, k]: k is j or one of its descendants.
        below = np.eye(n_j, dtype=bool)
        for j in range(n_j - 1, 0, -1):
            below[self.parents[j]] |= below[j]
        self.below = below.astype(np.float64)
        self.faces = as_np(m.faces).astype(np.int64)
        self.lmk_faces = None if m.lmk_faces is None else as_np(m.lmk_faces).astype(np.int64)
        self.lmk_bary = None if m.lmk_bary is None else as_np(m.lmk_bary)
        self.contour = m.face_contour
        if self.contour:
            self.dyn_faces = as_np(m.dynamic_lmk_faces).astype(np.int64)
            self.dyn_bary = as_np(m.dynamic_lmk_bary)
            self.contour_chain = m.contour_chain()
        self.table = keypoints.table.cpu().numpy()
        self.available = keypoints.available.cpu().numpy()
        self.num_joints, self.num_vertices = n_j, n_v
        # moved[j, v]: turning joint j moves vertex v (skinned below j, or a pose corrective).
        corrective = np.abs(self.posedirs.reshape(n_j, 9, n_v, 3)).sum((1, 3)) > 0
        self.moved = ((self.below @ self.weights.T) > 0) | corrective
        self._block_cache: dict[tuple[int, ...], list] = {}
        self.offset_rows = np.zeros(0, dtype=np.int64)  # `set_offsets`: none by default
        self.offset_joints = np.zeros(0, dtype=np.int64)
        self.offsets = np.zeros((0, 3))
        self.offset_basis = np.zeros((0, 3, 6))

    def set_offsets(self, joint: np.ndarray, offset: np.ndarray,
                    basis: np.ndarray | None = None) -> None:
        """A learned landmark embedding (`embedding.LandmarkEmbedding`): keypoint k moves by
        Rw_j (offset[k] + basis[k] @ [theta_j, theta_parent(j)]), j = joint[k] (rows with
        joint -1, no offset or no model point: none)."""
        joint, offset = np.asarray(joint), np.asarray(offset, dtype=np.float64)
        basis = np.zeros((len(joint), 3, 6)) if basis is None else np.asarray(
            basis, dtype=np.float64)
        some = (np.abs(offset).sum(1) > 0) | (np.abs(basis).sum((1, 2)) > 0)
        rows = np.flatnonzero((joint >= 0) & self.available & some)
        self.offset_rows, self.offset_joints = rows, joint[rows]
        self.offsets, self.offset_basis = offset[rows], basis[rows]
        self.offset_parents = self.parents[self.offset_joints]

    def _offset_features(self, theta: np.ndarray) -> np.ndarray:
        """[R, 6] each embedded row's pose features: its joint's and its parent's axis-angle."""
        par = theta[np.maximum(self.offset_parents, 0)] * (self.offset_parents >= 0)[:, None]
        return np.concatenate([theta[self.offset_joints], par], axis=1)

    def _landmark_map(self, rot: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(corner vertex ids [L, 3], barycentric weights [L, 3]) of the face landmarks."""
        if self.lmk_faces is None:
            return None
        corners, bary = [self.faces[self.lmk_faces]], [self.lmk_bary]
        if self.contour:
            row = _contour_row(rot, self.contour_chain)
            corners.append(self.faces[self.dyn_faces[row]])
            bary.append(self.dyn_bary[row])
        return np.concatenate(corners), np.concatenate(bary)

    def _gather(self, joints: np.ndarray, verts: np.ndarray, lmk: tuple | None) -> np.ndarray:
        """[J | V | L] rows of any trailing shape -> the keypoint layout [K, ...]."""
        parts = [joints, verts]
        if lmk is not None:
            corners, bary = lmk
            bary = bary.reshape(*bary.shape, *([1] * (verts.ndim - 1)))
            parts.append((verts[corners] * bary).sum(1))
        out = np.concatenate(parts)[self.table]
        out[~self.available] = np.nan
        return out

    def evaluate(self, full_pose: np.ndarray, expression: np.ndarray, transl: np.ndarray,
                 joints: Sequence[int] | None = None, expression_jacobian: bool = False
                 ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        theta = np.asarray(full_pose, dtype=np.float64).reshape(-1, 3)       # [J, 3]
        psi = np.asarray(expression, dtype=np.float64).reshape(-1)            # [E]
        rot, jl = rodrigues_and_left_jacobian(theta)                          # [J, 3, 3] x2
        v_rest = self.v_shape + self.exprdirs @ psi                           # [V, 3]
        j_rest = self.j_shape + self.joint_exprdirs @ psi                     # [J, 3]
        feats = (rot[1:] - np.eye(3)).reshape(-1)[self.feature_ids]
        v_posed = v_rest + (feats @ self.posedirs_active).reshape(-1, 3)
        # World frames level by level from the root.
        rw = rot.copy()
        jw = j_rest.copy()
        for level, parents in self.levels:
            jw[level] = jw[parents] + np.einsum("kab,kb->ka", rw[parents],
                                                j_rest[level] - j_rest[parents])
            rw[level] = rw[parents] @ rot[level]
        t = jw - np.einsum("kab,kb->ka", rw, j_rest)                          # [J, 3]
        rb = (self.weights @ rw.reshape(-1, 9)).reshape(-1, 3, 3)            # [V, 3, 3]
        verts = (rb @ v_posed[..., None])[..., 0] + self.weights @ t          # [V, 3]
        lmk = self._landmark_map(rot)
        shift = np.asarray(transl, dtype=np.float64).reshape(3)
        points = self._gather(jw + shift, verts + shift, lmk)
        local = self.offsets
        if len(self.offset_rows):
            local = local + np.einsum("rab,rb->ra", self.offset_basis,
                                      self._offset_features(theta))
        moved = np.einsum("rab,rb->ra", rw[self.offset_joints], local)  # [R, 3]
        points[self.offset_rows] += moved
        d_pose = d_expr = None
        if joints is not None:
            d_pose = self._gather(*self._pose_jacobian(list(joints), rot, jl, rw, jw, t,
                                                       v_posed, rb), lmk)
            if len(self.offset_rows):
                d_pose[self.offset_rows] += self._offset_jacobian(list(joints), jl, rw, moved)
        if expression_jacobian:
            d_expr = self._gather(*self._expression_jacobian(rw, rb), lmk)
        return points, d_pose, d_expr

    def world_rotations(self, full_pose: np.ndarray) -> np.ndarray:
        """[J, 3, 3] each joint's world rotation at `full_pose` [J, 3]."""
        rot, _ = rodrigues_and_left_jacobian(np.asarray(full_pose, dtype=np.float64))
        rw = rot.copy()
        for level, parents in self.levels:
            rw[level] = rw[parents] @ rot[level]
        return rw

    def _pose_jacobian(self, joints: list[int], rot, jl, rw, jw, t, v_posed, rb):
        """([J, 3, n, 3] joints', [V, 3, n, 3] vertices' derivatives) by joints[n]'s theta."""
        idx = np.asarray(joints)
        n = len(idx)
        par = self.parents[idx]
        rw_par = np.where((par >= 0)[:, None, None], rw[np.maximum(par, 0)], np.eye(3))
        # omega_i x a = skew(omega_i) a, all three i at once: [n, 3i * 3, 3].
        turn = skew((rw_par @ jl[idx]).transpose(0, 2, 1)).reshape(n, 9, 3)
        # Joints: omega x (Jw_k - Jw_j) below j.
        arm = (jw[None] - jw[idx][:, None]) * self.below[idx][..., None]   # [n, J, 3]
        d_joints = (turn @ arm.transpose(0, 2, 1)).reshape(n, 3, 3, -1)   # [n, 3i, 3, J]
        # Vertices, by blocks of joints and the vertices they move (the fingers move a few).
        skinned = (v_posed @ rw.transpose(0, 2, 1) + t[:, None]) * self.weights.T[..., None]
        skinned = skinned.reshape(self.num_joints, -1)                      # [J, V * 3]
        d_verts = np.zeros((self.num_vertices, 3, n, 3))
        for cols, verts in self._blocks(tuple(joints)):
            j, nv = idx[cols], len(verts)
            below = self.below[j]                                           # [n', J]
            every = nv == self.num_vertices
            q = (below @ skinned).reshape(len(j), -1, 3)
            q = q if every else q[:, verts]                                 # [n', V', 3]
            lever = q - (below @ self.weights[verts].T)[..., None] * jw[j][:, None]
            block = turn[cols] @ lever.transpose(0, 2, 1)                   # [n', 9, V']
            # Pose correctives: dR_j/dtheta_i = skew(Jl e_i) R_j, through posedirs, skinned.
            d_rot = skew(jl[j].transpose(0, 2, 1)) @ rot[j][:, None]       # [n', 3i, 3, 3]
            dirs = self.posedirs[j].reshape(len(j), 9, -1, 3)
            dirs = (dirs if every else dirs[:, :, verts]).reshape(len(j), 9, -1)
            d_posed = (d_rot.reshape(len(j), 3, 9) @ dirs).reshape(len(j) * 3, nv, 3)
            d_posed = rb[verts] @ d_posed.transpose(1, 2, 0)                # [V', 3, n' * 3i]
            block = block.reshape(len(j), 3, 3, nv).transpose(3, 2, 0, 1)   # [V', 3, n', 3i]
            block += d_posed.reshape(nv, 3, len(j), 3)
            if every:
                d_verts[:, :, cols] = block
            else:
                d_verts[verts[:, None], :, cols] = block.transpose(0, 2, 1, 3)
        return d_joints.transpose(3, 2, 0, 1), d_verts

    def _offset_jacobian(self, joints: list[int], jl, rw, moved) -> np.ndarray:
        """[R, 3, n, 3] derivatives of the embedded offsets Rw_j o by joints[n]'s theta:
        omega x (Rw_j o) for every joint at or above j."""
        idx = np.asarray(joints)
        n = len(idx)
        par = self.parents[idx]
        rw_par = np.where((par >= 0)[:, None, None], rw[np.maximum(par, 0)], np.eye(3))
        turn = skew((rw_par @ jl[idx]).transpose(0, 2, 1)).reshape(n, 9, 3)
        d = (turn @ moved.T).reshape(n, 3, 3, -1)                          # [n, 3i, 3, R]
        d = d * self.below[idx][:, self.offset_joints][:, None, None, :]
        d = d.transpose(3, 2, 0, 1).copy()                                 # [R, 3, n, 3i]
        # The pose-dependent part: d (Rw_j B f) / d theta = Rw_j B[:, the joint's 3 columns].
        column = {int(j): c for c, j in enumerate(idx)}
        direct = rw[self.offset_joints] @ self.offset_basis                 # [R, 3, 6]
        for r, (j, p) in enumerate(zip(self.offset_joints, self.offset_parents, strict=True)):
            for joint, cols in ((int(j), slice(0, 3)), (int(p), slice(3, 6))):
                if joint in column:
                    d[r, :, column[joint]] += direct[r, :, cols]
        return d

    def _blocks(self, joints: tuple[int, ...]) -> list[tuple[np.ndarray, np.ndarray]]:
        """(columns, vertices) blocks of a joint list: joints grouped by how many vertices they
        move (few: fingers; some: the jaw; many: the spine), each group over the union of the
        vertices its joints move. Cached."""
        if joints not in self._block_cache:
            moved = self.moved[list(joints)]                                # [n, V]
            count = moved.sum(1)
            tier = np.digitize(count, [16, self.num_vertices // 4])  # few / some / many
            blocks = []
            for cols in (np.flatnonzero(tier == k) for k in range(3)):
                verts = np.flatnonzero(moved[cols].any(0))
                if len(cols) and len(verts):
                    blocks.append((cols, verts))
            self._block_cache[joints] = blocks
        return self._block_cache[joints]

    def _expression_jacobian(self, rw, rb):
        """([J, 3, E] joints', [V, 3, E] vertices' derivatives) by the expression."""
        eye = np.eye(3)[None]
        rw_par = np.concatenate([eye, rw[self.parents[1:]]])              # [J, 3, 3]
        step = np.einsum("mab,mbe->mae", rw_par - rw, self.joint_exprdirs)  # [J, 3, E]
        d_t = np.einsum("mk,mae->kae", self.below, step)  # t_k sums its chain m (k below m)
        d_joints = d_t + np.einsum("kab,kbe->kae", rw, self.joint_exprdirs)
        d_verts = np.einsum("vab,vbe->vae", rb, self.exprdirs) + np.einsum(
            "vk,kae->vae", self.weights, d_t)
        return d_joints, d_verts
