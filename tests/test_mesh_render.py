import numpy as np
import pytest

from avatar_core.render.camera import Camera, orbit
from avatar_core.synth.mesh_render import (
    MeshRenderOutput,
    face_label_image,
    numba_available,
    render_mesh,
    vertex_normals,
)

BACKENDS = ["reference"] + (["numba"] if numba_available() else [])
FIELDS = ("rgb", "alpha", "depth", "face_id", "bary")


def _pinhole(f: float, width: int, height: int, cx: float = 0.0, cy: float = 0.0) -> Camera:
    """Camera at the origin looking down +z (camera frame == world frame)."""
    K = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
    return Camera(K, np.eye(3), np.zeros(3), width, height)


def _uv_sphere(n_lat: int, n_lon: int, r: float = 0.5):
    th = np.linspace(0.0, np.pi, n_lat + 1)
    ph = np.linspace(0.0, 2 * np.pi, n_lon, endpoint=False)
    T, P = np.meshgrid(th, ph, indexing="ij")
    v = np.stack([r * np.sin(T) * np.sin(P), r * np.cos(T), r * np.sin(T) * np.cos(P)], -1)
    v = v.reshape(-1, 3)
    faces = []
    for i in range(n_lat):
        for j in range(n_lon):
            a, b = i * n_lon + j, i * n_lon + (j + 1) % n_lon
            faces += [[a, a + n_lon, b], [b, a + n_lon, b + n_lon]]
    return v, np.array(faces)


def _raycast(vertices, faces, camera, near=0.01):
    """Independent brute-force ray caster through pixel centres (j + 0.5, i + 0.5).

    Returns (depth [H, W] with inf = miss, face_id [H, W], barycentrics [H, W, 3]) using the
    nearest hit with camera z >= near (the same set of points near-plane clipping keeps)."""
    W, H = camera.width, camera.height
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d = np.linalg.solve(camera.K, np.stack([jj, ii, np.ones_like(jj)], 0).reshape(3, -1)).T
    vc = camera.world_to_camera(np.asarray(vertices, dtype=np.float64))
    depth = np.full(H * W, np.inf)
    fid = np.full(H * W, -1)
    bary = np.zeros((H * W, 3))
    for k, (a, b, c) in enumerate(np.asarray(faces)):
        p0, e1, e2 = vc[a], vc[b] - vc[a], vc[c] - vc[a]
        h = np.cross(d, e2)
        det = h @ e1
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = -p0
        u = (h @ s) * inv
        q = np.cross(s, e1)
        v = (d @ q) * inv
        t = (q @ e2) * inv  # d has z == 1, so the ray parameter is the camera depth
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= near) & (t < depth)
        depth[hit], fid[hit] = t[hit], k
        bary[hit] = np.stack([1 - u - v, u, v], -1)[hit]
    return depth.reshape(H, W), fid.reshape(H, W), bary.reshape(H, W, 3)


def _assert_same(a: MeshRenderOutput, b: MeshRenderOutput, atol: float = 1e-5, bary=True):
    np.testing.assert_array_equal(a.face_id, b.face_id)
    if bary:  # off when the faces list their vertices in another order
        np.testing.assert_allclose(a.bary, b.bary, rtol=0, atol=atol)
    np.testing.assert_array_equal(a.alpha, b.alpha)
    np.testing.assert_array_equal(np.isinf(a.depth), np.isinf(b.depth))
    fin = np.isfinite(a.depth)
    np.testing.assert_allclose(a.depth[fin], b.depth[fin], rtol=0, atol=atol)
    np.testing.assert_allclose(a.rgb, b.rgb, rtol=0, atol=atol)


# Pixel-aligned scene: f = 8 maps world (x, y, 1) to pixel (8x, 8y); all values are exact.
_TRI = np.array([[0.125, 0.125, 1.0], [1.125, 0.125, 1.0], [0.125, 1.125, 1.0]])


@pytest.mark.parametrize("backend", BACKENDS)
def test_single_triangle_covers_expected_pixels(backend):
    # Screen triangle (1, 1), (9, 1), (1, 9): pixel (j, i) has its centre at (j+.5, i+.5)
    # and is covered iff j+.5 >= 1, i+.5 >= 1 and (j+.5) + (i+.5) <= 10 (edges inclusive).
    cam = _pinhole(8.0, 10, 10)
    out = render_mesh(_TRI, [[0, 1, 2]], cam, backend=backend)
    i, j = np.mgrid[0:10, 0:10]
    expected = (j >= 1) & (i >= 1) & (i + j <= 9)
    np.testing.assert_array_equal(out.alpha, expected.astype(np.float32))
    np.testing.assert_array_equal(out.face_id, np.where(expected, 0, -1))
    np.testing.assert_array_equal(out.depth, np.where(expected, 1.0, np.inf))
    assert out.rgb.dtype == np.float32 and out.rgb.shape == (10, 10, 3)
    np.testing.assert_array_equal(out.rgb[~expected], 1.0)  # white background
    # Reversed winding (a back face) covers exactly the same pixels.
    back = render_mesh(_TRI, [[0, 2, 1]], cam, backend=backend)
    _assert_same(out, back, atol=0, bary=False)
    np.testing.assert_array_equal(back.bary, out.bary[..., [0, 2, 1]])


@pytest.mark.parametrize("backend", BACKENDS)
def test_matches_independent_raycaster(backend):
    v, f = _uv_sphere(8, 12)
    v = v + [0.1, 0.0, 0.0]
    cam = orbit((0.0, 0.0, 0.0), 17.0, 11.0, 1.9, width=41, height=33, fov_y_deg=35.0)
    out = render_mesh(v, f, cam, backend=backend)
    depth, fid, _ = _raycast(v, f, cam)
    # Ties only occur for pixel centres lying exactly on an edge; allow a handful.
    assert np.mean(out.face_id != fid) < 0.005
    same = (out.face_id == fid) & (fid >= 0)
    np.testing.assert_allclose(out.depth[same], depth[same], rtol=1e-6)
    assert same.sum() > 300


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("order", [(0, 1), (1, 0)])
def test_z_buffer_nearest_wins_regardless_of_order(backend, order):
    cam = _pinhole(10.0, 20, 20, 10.0, 10.0)
    near_tri = [[-0.5, -0.5, 2.0], [0.5, -0.5, 2.0], [0.0, 0.5, 2.0]]
    far_tri = [[-2.0, -2.0, 3.0], [2.0, -2.0, 3.0], [0.0, 2.0, 3.0]]
    tris = [near_tri, far_tri]
    colors = [[1.0, 0.0, 0.0]] * 3 + [[0.0, 1.0, 0.0]] * 3
    v = np.array(tris[order[0]] + tris[order[1]])
    c = np.array(colors[3 * order[0] : 3 * order[0] + 3] + colors[3 * order[1] : 3 * order[1] + 3])
    out = render_mesh(v, [[0, 1, 2], [3, 4, 5]], cam, vertex_colors=c, backend=backend, ambient=1.0)
    near_id = order.index(0)
    assert out.face_id[10, 10] == near_id
    np.testing.assert_allclose(out.depth[10, 10], 2.0, rtol=1e-6)
    np.testing.assert_allclose(out.rgb[10, 10], [1, 0, 0], atol=1e-6)
    assert out.face_id[5, 10] == 1 - near_id  # outside the near triangle: the far one
    np.testing.assert_allclose(out.depth[5, 10], 3.0, rtol=1e-6)
    np.testing.assert_allclose(out.rgb[5, 10], [0, 1, 0], atol=1e-6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_interpenetrating_triangles_resolved_per_pixel(backend):
    cam = _pinhole(10.0, 40, 20, 20.0, 10.0)
    flat = [[-3.0, -2.0, 2.0], [3.0, -2.0, 2.0], [0.0, 3.0, 2.0]]  # z = 2
    tilted = [[-3.0, -2.0, 1.0], [3.0, -2.0, 3.0], [0.0, 3.0, 2.0]]  # z = 2 + x / 3
    out = render_mesh(np.array(flat + tilted), [[0, 1, 2], [3, 4, 5]], cam, backend=backend)
    assert out.face_id[10, 10] == 1  # x < 0: the tilted face is nearer
    assert out.face_id[10, 25] == 0  # x > 0: the flat face is nearer
    assert np.all(out.depth[out.alpha > 0] <= 2.0 + 1e-6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_behind_and_straddling_near_plane(backend):
    cam = _pinhole(10.0, 24, 24, 12.0, 12.0)
    behind = [[-1.0, -1.0, -1.0], [1.0, -1.0, -1.0], [0.0, 1.0, -2.0]]
    out = render_mesh(np.array(behind), [[0, 1, 2]], cam, backend=backend)
    assert out.alpha.sum() == 0 and np.all(out.face_id == -1)

    # One vertex behind the camera, one exactly at z = 0, ... and two behind.
    near = 0.5
    for tri in (
        [[-1.0, -1.0, 2.0], [1.0, -1.0, 2.0], [0.0, 1.0, -1.0]],
        [[-1.0, -1.0, 2.0], [1.0, -1.0, 0.0], [0.0, 1.0, 2.0]],
        [[-1.0, -1.0, -2.0], [1.0, -1.0, 2.0], [0.3, 1.0, -1.0]],
    ):
        tri = np.array(tri)
        out = render_mesh(tri, [[0, 1, 2]], cam, backend=backend, near=near)
        drawn = out.alpha > 0
        assert drawn.any()
        assert np.all(out.depth[drawn] >= near * (1 - 1e-6))
        depth, fid, _ = _raycast(tri, [[0, 1, 2]], cam, near=near)
        assert np.mean(drawn != (fid >= 0)) < 0.01
        both = drawn & (fid >= 0)
        np.testing.assert_allclose(out.depth[both], depth[both], rtol=1e-5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_degenerate_and_edge_on_triangles_are_skipped(backend):
    cam = _pinhole(8.0, 10, 10)
    v = np.vstack(
        [
            [[0.1, 0.1, 1.0], [0.5, 0.5, 1.0], [0.9, 0.9, 1.0]],  # collinear
            [[0.2, 0.2, 1.0], [0.2, 0.2, 1.0], [0.9, 0.2, 1.0]],  # repeated position
            [[0.5, 0.0, 1.0], [0.5, 1.0, 1.0], [1.0, 0.5, 2.0]],  # edge-on: plane x = z / 2
            _TRI,
        ]
    )
    f = [[0, 1, 2], [3, 4, 5], [3, 3, 5], [6, 7, 8], [9, 10, 11]]
    out = render_mesh(v, f, cam, backend=backend)
    assert set(np.unique(out.face_id)) == {-1, 4}
    only = render_mesh(v, f[:4], cam, backend=backend)
    assert only.alpha.sum() == 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_empty_mesh_gives_background(backend):
    cam = _pinhole(8.0, 7, 5)
    for v, f in ((np.zeros((0, 3)), np.zeros((0, 3), dtype=int)), (_TRI, np.zeros((0, 3)))):
        out = render_mesh(v, f, cam, background=(0.1, 0.2, 0.3), backend=backend)
        np.testing.assert_allclose(out.rgb, np.broadcast_to([0.1, 0.2, 0.3], (5, 7, 3)))
        assert out.alpha.sum() == 0 and np.all(np.isinf(out.depth))
        assert np.all(out.face_id == -1) and out.face_id.dtype == np.int32


@pytest.mark.parametrize("backend", BACKENDS)
def test_colours_interpolate_perspective_correctly(backend):
    cam = _pinhole(20.0, 30, 30, 15.0, 15.0)
    tri = np.array([[-0.8, -0.8, 1.0], [2.0, -0.8, 4.0], [-0.8, 1.5, 2.0]])  # strongly tilted
    rgb = np.eye(3)
    out = render_mesh(tri, [[0, 1, 2]], cam, vertex_colors=rgb, ambient=1.0, backend=backend)
    _, fid, bary = _raycast(tri, [[0, 1, 2]], cam)
    inside = (fid == 0) & (bary.min(-1) > 1e-3)
    assert inside.sum() > 50
    np.testing.assert_allclose(out.rgb[inside], bary[inside], atol=1e-5)
    np.testing.assert_allclose(out.rgb[out.alpha > 0].sum(-1), 1.0, atol=1e-5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_barycentrics_of_the_original_face(backend):
    # Perspective-correct barycentrics against the ray caster, on whole faces and on pieces
    # of faces clipped by the near plane (which must report the original face's weights).
    v, f = _uv_sphere(8, 12)
    cam = orbit((0.0, 0.0, 0.0), 17.0, 11.0, 1.9, width=41, height=33, fov_y_deg=35.0)
    straddle = np.array([[-1.0, -1.0, 2.0], [1.0, -1.0, 2.0], [0.0, 1.0, -1.0]])
    for verts, faces, camera, near in (
        (v, f, cam, 0.01),
        (straddle, [[0, 1, 2]], _pinhole(10.0, 24, 24, 12.0, 12.0), 0.5),
    ):
        out = render_mesh(verts, faces, camera, near=near, backend=backend)
        _, fid, bary = _raycast(verts, faces, camera, near=near)
        assert out.bary.shape == (camera.height, camera.width, 3)
        assert out.bary.dtype == np.float32
        same = (out.face_id == fid) & (fid >= 0)
        assert same.sum() > 50
        np.testing.assert_allclose(out.bary[same], bary[same], atol=1e-5)
        hit = out.face_id >= 0
        np.testing.assert_allclose(out.bary[hit].sum(-1), 1.0, atol=1e-5)
        assert out.bary[hit].min() > -1e-5
        np.testing.assert_array_equal(out.bary[~hit], 0.0)
        # Interpolating vertex positions with them gives the surface point at that depth.
        vc = camera.world_to_camera(np.asarray(verts, dtype=np.float64))
        p = np.einsum("nk,nkc->nc", out.bary[hit], vc[np.asarray(faces)[out.face_id[hit]]])
        np.testing.assert_allclose(p[:, 2], out.depth[hit], rtol=1e-5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_shading_off_keeps_geometry(backend):
    v, f = _uv_sphere(8, 12)
    cam = orbit((0.0, 0.0, 0.0), 17.0, 11.0, 1.9, width=41, height=33, fov_y_deg=35.0)
    full = render_mesh(v, f, cam, backend=backend)
    bare = render_mesh(v, f, cam, backend=backend, shading=False, background=(0.2, 0.3, 0.4))
    for k in ("alpha", "depth", "face_id", "bary"):
        np.testing.assert_array_equal(getattr(bare, k), getattr(full, k))
    np.testing.assert_allclose(bare.rgb, np.broadcast_to([0.2, 0.3, 0.4], bare.rgb.shape),
                               atol=1e-7)


@pytest.mark.parametrize("backend", BACKENDS)
def test_back_face_culling_on_a_closed_mesh(backend):
    v, f = _uv_sphere(10, 16)
    cam = orbit((0.0, 0.0, 0.0), 17.0, 11.0, 1.9, width=41, height=33, fov_y_deg=35.0)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    facing = (n * v[f].mean(axis=1)).sum(-1)
    assert np.all(facing[np.linalg.norm(n, axis=1) > 1e-12] > 0)  # counter-clockwise outward
    both = render_mesh(v, f, cam, backend=backend)
    culled = render_mesh(v, f, cam, backend=backend, cull_back_faces=True)
    _assert_same(both, culled, atol=0)  # from outside only front faces are ever visible
    inverted = render_mesh(v, f[:, ::-1], cam, backend=backend, cull_back_faces=True)
    assert inverted.alpha.sum() > 0  # now the far inner half shows through
    assert np.all(inverted.depth[inverted.alpha > 0] > both.depth[inverted.alpha > 0])
    # Straddling the near plane: the face is culled or kept as a whole, pieces included.
    tri = np.array([[-1.0, -1.0, 2.0], [1.0, -1.0, 2.0], [0.0, 1.0, -1.0]])
    pin = _pinhole(10.0, 24, 24, 12.0, 12.0)
    kept = [render_mesh(tri, [order], pin, backend=backend, near=0.5, cull_back_faces=True)
            for order in ([0, 1, 2], [0, 2, 1])]
    assert sorted(k.alpha.sum() > 0 for k in kept) == [False, True]
    # A mask culls only the marked faces (here the upper half of the inverted sphere): there
    # the far side shows, elsewhere the near side as without culling.
    mask = v[f].mean(axis=1)[:, 1] > 0.0
    part = render_mesh(v, f[:, ::-1], cam, backend=backend, cull_back_faces=mask)
    none = render_mesh(v, f[:, ::-1], cam, backend=backend)
    np.testing.assert_array_equal(part.alpha, none.alpha)
    hit = part.alpha > 0
    farther = part.depth[hit] > none.depth[hit]
    assert farther.any() and (part.depth[hit] == none.depth[hit]).any()
    assert np.all(mask[none.face_id[hit][farther]])
    with pytest.raises(ValueError, match="cull_back_faces"):
        render_mesh(v, f, cam, backend=backend, cull_back_faces=mask[:-1])


@pytest.mark.parametrize("backend", BACKENDS)
def test_two_sided_lambert(backend):
    cam = _pinhole(8.0, 10, 10)
    light = (0.0, 0.0, -1.0)  # headlight; the face normal is +-z
    kw = dict(vertex_colors=np.full((3, 3), 0.5), light_dir=light, backend=backend)
    front = render_mesh(_TRI, [[0, 1, 2]], cam, ambient=0.2, **kw)
    back = render_mesh(_TRI, [[0, 2, 1]], cam, ambient=0.2, **kw)
    np.testing.assert_allclose(front.rgb[front.alpha > 0], 0.5, atol=1e-6)
    np.testing.assert_array_equal(front.rgb, back.rgb)
    grazing = render_mesh(_TRI, [[0, 1, 2]], cam, ambient=0.2, **{**kw, "light_dir": (1, 0, 0)})
    np.testing.assert_allclose(grazing.rgb[grazing.alpha > 0], 0.1, atol=1e-6)
    # A doubled sheet (same vertices, both windings) has cancelling smooth normals; shading
    # falls back to the geometric face normal.
    sheet = render_mesh(_TRI, [[0, 1, 2], [0, 2, 1]], cam, ambient=0.2, **kw)
    np.testing.assert_allclose(sheet.rgb[sheet.alpha > 0], 0.5, atol=1e-6)
    assert set(np.unique(sheet.face_id)) == {-1, 0}  # equal depth: lower face index wins


def test_image_orientation_front_camera():
    # Camera on +z looking at the origin: world +x (the subject's left) lands on the image's
    # right half and world +y on its top half.
    cam = orbit((0.0, 0.0, 0.0), 0.0, 0.0, 3.0, width=32, height=32)
    s = 0.15
    right = np.array([[0.2, 0.0, 0.0], [0.2 + s, 0.0, 0.0], [0.2, s, 0.0]])
    up = right[:, [1, 0, 2]]
    out = render_mesh(np.vstack([right, up]), [[0, 1, 2], [3, 4, 5]], cam)
    rows, cols = np.nonzero(out.face_id == 0)
    assert cols.min() >= 16 and rows.max() < 17 and rows.min() >= 13
    rows, cols = np.nonzero(out.face_id == 1)
    assert rows.max() < 16 and cols.min() >= 15


def test_face_labels_and_helpers():
    cam = _pinhole(8.0, 10, 10)
    out = render_mesh(_TRI, [[0, 1, 2]], cam, face_labels=np.array([7]))
    np.testing.assert_array_equal(out.labels, np.where(out.face_id == 0, 7, -1))
    np.testing.assert_array_equal(
        face_label_image(out.face_id, [3], empty=99), np.where(out.face_id == 0, 3, 99)
    )
    assert render_mesh(_TRI, [[0, 1, 2]], cam).labels is None
    n = vertex_normals(_TRI, [[0, 1, 2]])
    np.testing.assert_allclose(n, np.tile([0.0, 0.0, 1.0], (3, 1)))


@pytest.mark.skipif(not numba_available(), reason="numba not installed")
def test_numba_matches_reference_on_random_mesh():
    rng = np.random.default_rng(42)
    v = rng.uniform(-1.0, 1.0, size=(90, 3)) * [1.0, 1.0, 1.5]  # some vertices behind near
    f = rng.integers(0, 90, size=(60, 3))
    colors = rng.uniform(size=(90, 3))
    for W, H, near in ((37, 29, 0.05), (8, 3, 0.3)):
        cam = orbit((0.0, 0.0, 0.0), 25.0, -15.0, 1.2, width=W, height=H, fov_y_deg=70.0)
        a = render_mesh(v, f, cam, vertex_colors=colors, near=near, backend="numba")
        b = render_mesh(v, f, cam, vertex_colors=colors, near=near, backend="reference")
        _assert_same(a, b)
        assert a.alpha.sum() > 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_tiny_and_odd_sizes(backend):
    big = np.array([[-5.0, -5.0, 2.0], [5.0, -5.0, 2.0], [0.0, 5.0, 2.0]])
    one = Camera(np.array([[1.0, 0, 0.5], [0, 1.0, 0.5], [0, 0, 1]]), np.eye(3), np.zeros(3), 1, 1)
    out = render_mesh(big, [[0, 1, 2]], one, backend=backend)
    assert out.rgb.shape == (1, 1, 3) and out.alpha[0, 0] == 1 and out.face_id[0, 0] == 0
    miss = render_mesh(big + [20.0, 0.0, 0.0], [[0, 1, 2]], one, backend=backend)
    assert miss.alpha[0, 0] == 0
    # Odd sizes against the ray caster.
    v, f = _uv_sphere(6, 9)
    for W, H in ((7, 5), (13, 1), (1, 9)):
        cam = orbit((0.0, 0.0, 0.0), 31.0, 7.0, 1.7, width=W, height=H, fov_y_deg=40.0)
        out = render_mesh(v, f, cam, backend=backend)
        assert out.rgb.shape == (H, W, 3) and out.depth.shape == (H, W)
        _, fid, _ = _raycast(v, f, cam)
        np.testing.assert_array_equal(out.face_id, fid)


def test_deterministic_and_validates_input():
    v, f = _uv_sphere(6, 9)
    cam = orbit((0.0, 0.0, 0.0), 10.0, 5.0, 2.0, width=24, height=20)
    a, b = render_mesh(v, f, cam), render_mesh(v, f, cam)
    for k in FIELDS:
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    with pytest.raises(ValueError, match="faces"):
        render_mesh(v, np.array([[0, 1, len(v)]]), cam)
    with pytest.raises(ValueError, match="vertices"):
        render_mesh(v[:, :2], f, cam)
    with pytest.raises(ValueError, match="vertex_colors"):
        render_mesh(v, f, cam, vertex_colors=np.ones((3, 3)))
    with pytest.raises(ValueError, match="near"):
        render_mesh(v, f, cam, near=0.0)
    with pytest.raises(ValueError, match="backend"):
        render_mesh(v, f, cam, backend="gpu")


def test_auto_falls_back_to_reference_without_numba(monkeypatch):
    from avatar_core.synth import mesh_render as mr

    monkeypatch.setattr(mr, "_KERNELS", {"reference": mr._KERNELS["reference"]})
    monkeypatch.setattr(mr, "_numba_error", "No module named 'numba'")
    assert not mr.numba_available()
    cam = _pinhole(8.0, 10, 10)
    with pytest.warns(RuntimeWarning, match="numba unavailable"):
        out = render_mesh(_TRI, [[0, 1, 2]], cam)
    _assert_same(out, render_mesh(_TRI, [[0, 1, 2]], cam, backend="reference"), atol=0)
    with pytest.raises(ImportError, match="numba"):
        render_mesh(_TRI, [[0, 1, 2]], cam, backend="numba")
