"""Binding's twins: the numba kernel against the torch reference, and the dispatch between them."""

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from avatar_core.gaussians import binding
from avatar_core.gaussians.animate import AvatarAnimator, synthetic_package
from avatar_core.gaussians.avatar import GaussianAvatar, pose_gaussians
from avatar_core.gaussians.binding import _face_kernel, can_use_numba
from avatar_core.gaussians.frames import COLLINEAR_SIN, triangle_frames
from avatar_core.rotations import matrix_to_quaternion

RTOL = {torch.float32: 1e-6, torch.float64: 1e-12}


def _avatar(n, faces, dtype=torch.float64, seed=0, parents=None, mean_scale=1.0,
            log_scale_shift=-2.0):
    g = torch.Generator().manual_seed(seed)
    if parents is None:
        parents = torch.randint(0, faces, (n,), generator=g) if faces else torch.zeros(0).long()
    return GaussianAvatar(parents=parents,
                          local_means=torch.randn(n, 3, generator=g, dtype=dtype) * mean_scale,
                          log_scales=torch.randn(n, 3, generator=g, dtype=dtype)
                          + log_scale_shift,
                          quats=torch.randn(n, 4, generator=g, dtype=dtype),
                          opacity_logits=torch.randn(n, generator=g, dtype=dtype),
                          sh=torch.randn(n, 4, 3, generator=g, dtype=dtype))


def _kernel(avatar, vertices, faces):
    with torch.no_grad():
        return pose_gaussians(avatar, vertices, faces, backend="numba")


def pose_gaussians_torch(avatar, vertices, faces):
    return pose_gaussians(avatar, vertices, faces, backend="torch")


def _close(a, b, rtol):
    """Equal up to rtol relative to the tensor's magnitude, NaN where the other is NaN."""
    assert a.shape == b.shape and a.dtype == b.dtype
    nan = torch.isnan(a)
    assert torch.equal(nan, torch.isnan(b))
    a, b = a[~nan], b[~nan]
    if a.numel():
        finite = torch.isfinite(a)
        assert torch.equal(a[~finite], b[~finite])
        scale = float(a[finite].abs().max()) if finite.any() else 0.0
        assert torch.allclose(a[finite], b[finite], rtol=rtol, atol=rtol * scale), \
            float((a[finite] - b[finite]).abs().max())


def _ill_faces(vertices, faces):
    """Faces at or within rounding of the collinear test (the sine of the corner angle below
    ~COLLINEAR_SIN): float32 rounding of the edges may put the reference and the kernel on
    either side of it, and either normal is right there."""
    v = vertices.double()
    e01, e02 = v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]]
    size = e01.norm(dim=-1) * e02.norm(dim=-1)
    sine = torch.cross(e01, e02, dim=-1).norm(dim=-1) / size.clamp(min=1e-300)
    return (size > 0) & (sine < COLLINEAR_SIN * 100)


def check_matches(avatar, vertices, faces):
    """Kernel == reference: means, scales, opacities, sh; quats up to the sign that
    matrix_to_quaternion's w >= 0 cannot pin down when the face quaternion's w is ~0.

    The kernel computes in float64 inside, so a float32 kernel is checked against the float64
    reference on the same inputs, and against the float32 reference wherever float32 rounding
    does not decide the reference's frame. On ill-conditioned faces (`_ill_faces`) only the
    edge, centroid and k are compared, and the kernel's frame must be orthonormal.
    """
    faces = torch.as_tensor(faces)
    out = _kernel(avatar, vertices, faces)
    assert out.sh is avatar.sh
    ill = _ill_faces(vertices, faces)
    rows = ~ill[avatar.parents] if avatar.num else torch.zeros(0, dtype=torch.bool)
    if ill.any():
        frames = np.empty((faces.shape[0], 17))
        _face_kernel(vertices.detach().numpy(), faces.numpy(), frames)
        rot, t, k = triangle_frames(vertices.double(), faces)
        fr = torch.from_numpy(frames)[ill]
        r = fr[:, :9].reshape(-1, 3, 3)
        _close(rot[ill][..., 0], r[..., 0], 1e-9)
        _close(t[ill], fr[:, 9:12], 1e-12)
        _close(k[ill], fr[:, 12], 1e-9)
        eye = torch.eye(3, dtype=torch.float64)
        assert torch.allclose(r.transpose(1, 2) @ r, eye.expand_as(r), atol=1e-9)
    if vertices.dtype == torch.float32:
        wide = avatar.to(dtype=torch.float64)
        ref = pose_gaussians_torch(wide, vertices.double(), faces)
        _compare(wide, vertices.double(), faces, ref, out, 1e-6, rows)
        r32, _, k32 = triangle_frames(vertices, faces)
        r64, _, k64 = triangle_frames(vertices.double(), faces)
        # Where float32 itself moves the frame by more than the tolerance (thin triangles),
        # only the float64 comparison above applies.
        good = ((r32.double() - r64).abs().amax((1, 2)) < 1e-6) & \
            ((k32.double() - k64).abs() <= 1e-6 * k64.abs())
        rows = rows & good[avatar.parents] if avatar.num else rows
    ref = pose_gaussians_torch(avatar, vertices, faces)
    _compare(avatar, vertices, faces, ref, out, RTOL[vertices.dtype], rows)
    return ref, out


def _compare(avatar, vertices, faces, ref, out, rtol, rows):
    for name in ("means", "scales", "opacities"):
        _close(getattr(ref, name).to(out.means.dtype)[rows], getattr(out, name)[rows], rtol)
    rq, oq = ref.quats.to(out.quats.dtype)[rows], out.quats[rows]
    if rq.numel():
        w_face = matrix_to_quaternion(triangle_frames(vertices, faces)[0])[avatar.parents, 0]
        flip = (w_face[rows].abs() < 1e-5)[:, None] & ((rq + oq).abs() < (rq - oq).abs())
        _close(rq, torch.where(flip, -oq, oq), rtol)


def _random_mesh(v, f, dtype, seed):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(v, 3, generator=g, dtype=dtype), torch.randint(0, v, (f, 3), generator=g)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_matches_the_reference_on_random_meshes(dtype):
    for seed in range(3):
        vertices, faces = _random_mesh(300, 500, dtype, seed)
        check_matches(_avatar(2000, 500, dtype, seed), vertices, faces)


DEGENERATE = [
    [[0.0, 0, 0], [0, 0, 0], [0, 0, 0]],        # all coincident
    [[0.0, 0, 0], [0, 0, 0], [1, 2, 3]],        # zero-length first edge
    [[1.0, 2, 3], [1, 2, 3], [-4, 0, 0.5]],     # zero-length first edge, longest is e02
    [[0.0, 0, 0], [1, 2, 3], [2, 4, 6]],        # collinear (exactly, in float32 too)
    [[0.0, 0, 0], [2, 4, 6], [1, 2, 3]],        # collinear, third corner inside
    [[0.0, 0, 0], [0, 0, -3], [0, 0, 5]],       # collinear along an axis
    [[1.0, 0, 0], [0, 1, 0], [1, 0, 0]],        # duplicate corner
    [[0.0, 0, 0], [1e-20, 0, 0], [0, 1e-20, 0]],  # vanishing
    [[0.0, 0, 0], [-1, 0, 0], [0, 0, -1]],      # a 180-degree frame (w = 0)
    [[0.0, 0, 0], [2, 0, 0], [0, 1, 0]],        # the identity frame
]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_degenerate_triangles_take_the_same_fallbacks(dtype):
    vertices = torch.tensor(DEGENERATE, dtype=dtype).reshape(-1, 3)
    faces = torch.arange(vertices.shape[0]).reshape(-1, 3)
    avatar = _avatar(200, faces.shape[0], dtype)
    ref, out = check_matches(avatar, vertices, faces)
    assert torch.isfinite(out.means).all() and torch.isfinite(out.quats).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("size", ["huge", "tiny", "extreme_locals"])
def test_huge_tiny_and_extreme(dtype, size):
    vertices, faces = _random_mesh(100, 200, dtype, 7)
    kwargs = {}
    if size == "huge":  # float32's reference overflows past ~1e9 (see binding's docstring)
        vertices = vertices * (1e6 if dtype == torch.float32 else 1e60)
    elif size == "tiny":
        vertices = vertices * (1e-7 if dtype == torch.float32 else 1e-100)
    else:
        kwargs = {"mean_scale": 1e6, "log_scale_shift": 25.0}
    check_matches(_avatar(500, 200, dtype, 3, **kwargs), vertices, faces)
    small = _avatar(500, 200, dtype, 4, mean_scale=1e-6, log_scale_shift=-25.0)
    check_matches(small, vertices, faces)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_zero_gaussians_and_zero_faces(dtype):
    vertices, faces = _random_mesh(10, 5, dtype, 0)
    ref, out = check_matches(_avatar(0, 5, dtype), vertices, faces)
    assert out.means.shape == (0, 3) and out.quats.shape == (0, 4)
    check_matches(_avatar(0, 0, dtype), vertices, faces[:0])


def test_parents_hitting_only_some_faces_ignore_the_others():
    vertices, faces = _random_mesh(50, 40, torch.float64, 1)
    avatar = _avatar(300, 40, parents=torch.randint(10, 15, (300,)))
    vertices[faces[:10].flatten()] = float("nan")  # only faces the avatar does not use...
    keep = torch.isin(faces, faces[10:15]).any(1)
    vertices[faces[keep].flatten()] = torch.randn(int(keep.sum()) * 3, 3, dtype=torch.float64)
    ref, out = check_matches(avatar, vertices, faces)
    assert torch.isfinite(out.means).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_nan_and_inf_vertices_behave_as_the_reference(dtype):
    """The reference does not raise: a NaN corner makes the frame fall back (NaN fails every
    `n > eps` test), so quats stay finite while means and scales (k is NaN) are NaN."""
    vertices, faces = _random_mesh(60, 80, dtype, 2)
    vertices[3, 1] = float("nan")
    vertices[7] = float("nan")
    vertices[11, 0] = float("inf")
    ref, out = check_matches(_avatar(400, 80, dtype), vertices, faces)
    assert torch.isnan(out.means).any() and torch.isnan(out.scales).any()


def test_indices_follow_torch():
    vertices, faces = _random_mesh(30, 20, torch.float64, 5)
    avatar = _avatar(100, 20)
    avatar.parents[:5] = -1  # negative indices count from the end, as in torch
    check_matches(avatar, vertices, faces - 30 * (faces % 2))
    avatar.parents[0] = 20
    with pytest.raises(IndexError):
        pose_gaussians_torch(avatar, vertices, faces)
    with pytest.raises(IndexError):
        _kernel(avatar, vertices, faces)
    avatar.parents[0] = 0
    bad = faces.clone()
    bad[3, 1] = 30
    with pytest.raises(IndexError):
        pose_gaussians_torch(avatar, vertices, bad)
    with pytest.raises(IndexError):
        _kernel(avatar, vertices, bad)


_coord = st.sampled_from([0.0, 1.0, -1.0, 0.5, 2.0, 1e-9, -3.0, 1e3])


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(corners=st.lists(st.tuples(_coord, _coord, _coord), min_size=3, max_size=12),
       seed=st.integers(0, 2**16), jitter=st.booleans(),
       dtype=st.sampled_from([torch.float32, torch.float64]))
def test_property_matches_the_reference(corners, seed, jitter, dtype):
    """Corners from a small set of values, so coincident, collinear and axis-aligned triangles
    are common; optionally jittered into generic ones."""
    vertices = torch.tensor(corners, dtype=dtype)
    if jitter:
        g = torch.Generator().manual_seed(seed)
        vertices = vertices + 0.1 * torch.randn(vertices.shape, generator=g, dtype=dtype)
    g = torch.Generator().manual_seed(seed)
    faces = torch.randint(0, vertices.shape[0], (16, 3), generator=g)
    check_matches(_avatar(64, 16, dtype, seed), vertices, faces)


def test_dispatch_kernel_without_grad_torch_with_grad(monkeypatch):
    calls = []
    real = binding.bind_gaussians_numba
    monkeypatch.setattr(binding, "bind_gaussians_numba",
                        lambda *a: calls.append(1) or real(*a))
    vertices, faces = _random_mesh(40, 30, torch.float32, 0)
    avatar = _avatar(60, 30, torch.float32)
    with torch.no_grad():
        pose_gaussians(avatar, vertices, faces)
    assert len(calls) == 1
    pose_gaussians(avatar, vertices, faces)  # grad enabled, but nothing requires it
    assert len(calls) == 2
    verts = vertices.clone().requires_grad_(True)
    out = pose_gaussians(avatar, verts, faces)
    assert len(calls) == 2 and out.means.requires_grad
    (out.means.sum() + out.quats.sum() + out.scales.sum()).backward()
    assert torch.isfinite(verts.grad).all() and verts.grad.abs().sum() > 0
    avatar.local_means.requires_grad_(True)
    out = pose_gaussians(avatar, vertices, faces)
    assert len(calls) == 2
    out.means.sum().backward()
    assert avatar.local_means.grad.abs().sum() > 0
    assert not can_use_numba((avatar.local_means.detach().double(),), vertices, faces)


def test_animator_uses_the_kernel_and_caches_the_constants(synthetic_files):
    package, model = synthetic_package(synthetic_files.root)
    animator = AvatarAnimator(model, package.avatar, betas=package.body.betas)
    params = {"jaw_pose": [0.2, 0.0, 0.0], "expression": np.ones(10),
              "body_pose": np.random.default_rng(0).normal(0, 0.2, (21, 3))}
    with torch.no_grad():
        a = animator.pose(params)
        check_matches(animator.avatar, a.vertices, model.faces)
        ref = pose_gaussians_torch(animator.avatar, a.vertices, model.faces)
        for name in ("means", "quats", "scales", "opacities"):
            _close(getattr(ref, name), getattr(a.gaussians, name), 1e-6)
        b = animator.pose({**params, "jaw_pose": [0.3, 0.0, 0.0]})
        assert b.gaussians.opacities is a.gaussians.opacities  # computed once
        animator.avatar.log_scales.add_(1.0)  # changed in place: the cache notices
        c = animator.pose({**params, "jaw_pose": [0.4, 0.0, 0.0]})
        ref = pose_gaussians_torch(animator.avatar, c.vertices, model.faces)
        _close(ref.scales, c.gaussians.scales, 1e-6)


def test_unknown_backend_is_refused():
    vertices, faces = _random_mesh(10, 5, torch.float32, 0)
    with pytest.raises(ValueError, match="backend"):
        pose_gaussians(_avatar(4, 5, torch.float32), vertices, faces, backend="cuda")
