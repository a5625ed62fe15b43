"""The Gaussian avatar: world transform, initialisation, packages, .ply export, the animator."""

import json
import zipfile

import numpy as np
import pytest
import torch

from avatar_core.gaussians.animate import AvatarAnimator, synthetic_package
from avatar_core.gaussians.avatar import GaussianAvatar, pose_gaussians, to_world
from avatar_core.gaussians.package import PackageError, load_package, save_package
from avatar_core.gaussians.ply import export_ply
from avatar_core.rotations import quaternion_to_matrix

plyfile = pytest.importorskip("plyfile")


def _random_avatar(n=50, faces=20, degree=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    return GaussianAvatar(parents=torch.randint(0, faces, (n,), generator=g),
                          local_means=torch.randn(n, 3, generator=g),
                          log_scales=torch.randn(n, 3, generator=g) - 2,
                          quats=torch.randn(n, 4, generator=g),
                          opacity_logits=torch.randn(n, generator=g),
                          sh=torch.randn(n, (degree + 1) ** 2, 3, generator=g))


def test_world_transform_follows_the_triangle_frame():
    avatar = _random_avatar()
    g = torch.Generator().manual_seed(1)
    rot = quaternion_to_matrix(torch.randn(20, 4, generator=g))
    trans, scale = torch.randn(20, 3, generator=g), torch.rand(20, generator=g) + 0.1
    world = to_world(avatar, rot, trans, scale)
    p = avatar.parents
    expected = scale[p, None] * (rot[p] @ avatar.local_means[..., None])[..., 0] + trans[p]
    assert torch.allclose(world.means, expected, atol=1e-5)
    assert torch.allclose(world.scales, scale[p, None] * avatar.log_scales.exp(), atol=1e-6)
    local_rot = quaternion_to_matrix(avatar.quats)
    assert torch.allclose(quaternion_to_matrix(world.quats), rot[p] @ local_rot, atol=1e-5)


def test_bad_shapes_are_refused():
    a = _random_avatar()
    with pytest.raises(ValueError, match="local_means"):
        GaussianAvatar(**{**a.tensors(), "local_means": torch.zeros(3, 3)})
    with pytest.raises(ValueError, match="sh"):
        GaussianAvatar(**{**a.tensors(), "sh": torch.zeros(50, 5, 3)})


def test_untrained_avatar_sits_on_the_mesh(synthetic_files):
    package, model = synthetic_package(synthetic_files.root, identity=1)
    avatar = package.avatar
    assert avatar.num == model.faces.shape[0] and avatar.sh_degree == 3
    posed = pose_gaussians(avatar, model.v_template, model.faces)
    centroids = model.v_template[model.faces].mean(1)
    assert torch.allclose(posed.means, centroids, atol=1e-6)
    assert ((posed.opacities > 0.5) & torch.isfinite(posed.scales).all(1)).all()


def test_initial_colours_from_a_texture():
    texture = np.zeros((2, 2, 3))
    texture[0, :, 0] = 1.0  # top row red (v = 1), bottom row black
    uvs = np.array([[0.0, 1.0], [1.0, 1.0], [0.0, 0.0], [1.0, 0.0]])
    avatar = GaussianAvatar.from_mesh(np.array([[0, 1, 2], [1, 2, 3]]), texture=texture,
                                      uvs=uvs, face_uvs=np.array([[0, 1, 0], [2, 3, 2]]),
                                      sh_degree=0)
    from avatar_core.render.sh import sh0_to_rgb

    rgb = sh0_to_rgb(avatar.sh[:, 0])
    assert torch.allclose(rgb, torch.tensor([[1.0, 0, 0], [0, 0, 0]]), atol=1e-6)
    with pytest.raises(ValueError, match="face_uvs"):
        GaussianAvatar.from_mesh(np.array([[0, 1, 2]]), texture=texture)


def test_package_round_trip_dir_and_zip(tmp_path, synthetic_files):
    package, _ = synthetic_package(synthetic_files.root)
    package.metrics = {"psnr": 31.5}
    for target in (tmp_path / "pkg", tmp_path / "pkg.zip"):
        save_package(package, target)
        back = load_package(target)
        for name, t in package.avatar.tensors().items():
            assert torch.equal(getattr(back.avatar, name), t), name
        assert back.body == package.body and back.metrics == {"psnr": 31.5}


def test_package_errors(tmp_path, synthetic_files):
    package, model = synthetic_package(synthetic_files.root)
    good = save_package(package, tmp_path / "good")
    manifest = json.loads((good / "avatar.json").read_text())
    with pytest.raises(PackageError, match="no avatar package"):
        load_package(tmp_path / "missing")
    (good / "avatar.json").write_text(json.dumps({**manifest, "schema_version": 99}))
    with pytest.raises(PackageError, match="schema_version"):
        load_package(good)
    (good / "avatar.json").write_text("{not json")
    with pytest.raises(PackageError, match="not valid JSON"):
        load_package(good)
    evil = tmp_path / "evil.zip"
    with zipfile.ZipFile(evil, "w") as z:
        z.writestr("../avatar.json", "{}")
        z.writestr("gaussians.npz", b"")
    with pytest.raises(PackageError, match="unsafe member"):
        load_package(evil)
    with pytest.raises(PackageError, match="byte limit"):
        load_package(save_package(package, tmp_path / "big.zip"), max_bytes=1000)
    bad = package.avatar.tensors()
    bad["local_means"] = bad["local_means"].clone()
    bad["local_means"][0, 0] = float("nan")
    package.avatar = GaussianAvatar(**bad)
    with pytest.raises(PackageError, match="NaN"):
        load_package(save_package(package, tmp_path / "nan"))
    with pytest.raises(PackageError, match="another mesh"):
        package.body.check_faces(model.faces.numpy()[:-1])


def test_ply_export_reads_back_with_plyfile(tmp_path):
    avatar = _random_avatar(degree=3)
    world = to_world(avatar, torch.eye(3).expand(20, 3, 3), torch.zeros(20, 3), torch.ones(20))
    path = export_ply(world, tmp_path / "frame.ply")
    v = plyfile.PlyData.read(str(path))["vertex"]
    assert len(v) == 50
    names = [p.name for p in v.properties]
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert len([n for n in names if n.startswith("f_rest_")]) == 45
    assert np.allclose(v["x"], world.means[:, 0].numpy(), atol=1e-6)
    assert np.allclose(v["f_rest_0"], world.sh[:, 1, 0].numpy(), atol=1e-6)  # red, coeff 1
    assert np.allclose(v["f_rest_15"], world.sh[:, 1, 1].numpy(), atol=1e-6)  # green, coeff 1
    assert np.allclose(1 / (1 + np.exp(-v["opacity"])), world.opacities.numpy(), atol=1e-5)
    assert np.allclose(np.exp(v["scale_1"]), world.scales[:, 1].numpy(), rtol=1e-5)
    empty = to_world(_random_avatar(n=0), torch.eye(3)[None], torch.zeros(1, 3), torch.ones(1))
    assert len(plyfile.PlyData.read(str(export_ply(empty, tmp_path / "e.ply")))["vertex"]) == 0


def test_animator_reuses_the_pose_when_only_the_camera_moves(synthetic_files):
    package, model = synthetic_package(synthetic_files.root)
    animator = AvatarAnimator(model, package.avatar, betas=package.body.betas)
    params = {"jaw_pose": [0.2, 0.0, 0.0], "expression": np.ones(10)}
    with torch.no_grad():
        a = animator.pose(params)
        b = animator.pose({k: np.array(v) for k, v in params.items()})  # equal values
        assert b is a and animator.hits == 1
        c = animator.pose({**params, "jaw_pose": [0.3, 0.0, 0.0]})
        assert animator.misses == 2 and not torch.equal(c.vertices, a.vertices)
    jaw = torch.tensor([0.2, 0.0, 0.0], requires_grad=True)
    d = animator.pose({"jaw_pose": jaw})
    d.gaussians.means.sum().backward()
    assert torch.isfinite(jaw.grad).all() and jaw.grad.abs().sum() > 0
