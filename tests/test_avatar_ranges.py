"""Avatar packages are validated by value range, not only for NaN/Inf (issue 13, finding 1):
each field out of range is a clear error naming it, the synthetic avatar passes, and the
real server answers 422 to the log_scales=80 package that used to kill it, stores nothing
and keeps streaming."""

import asyncio
import io
import math
import zipfile

import httpx
import numpy as np
import pytest
import torch

from avatar_core.gaussians.loading import load_avatar
from avatar_core.gaussians.package import PackageError, load_package, save_package
from avatar_core.gaussians.validate import GaussianRanges, RangeError, check_gaussian_ranges
from server.config import load_settings
from server.registry import AvatarRegistry
from tests.server_fixtures import (
    is_type,
    recv_until,
    server_fixture,  # noqa: F401 (the `server` fixture)
    stream,
)


@pytest.fixture(scope="module")
def synthetic():
    return load_avatar("synthetic").package


def _fields(package) -> dict:
    return {k: v.clone() for k, v in package.avatar.tensors().items()}


def test_the_synthetic_avatar_passes(synthetic):
    check_gaussian_ranges(**_fields(synthetic), num_faces=synthetic.body.num_faces)


def _set(name, index, value):
    def mutate(f):
        f[name][index] = value
    return mutate


BAD = {  # field -> (mutation, text the error must carry)
    "log_scales 80": (_set("log_scales", (3, 1), 80.0), "log_scales = 80 at Gaussian 3, "
                      "column 1 is outside the allowed range [-50, 6]"),
    "log_scales -80": (_set("log_scales", (0, 0), -80.0), "log_scales = -80"),
    "local mean far": (_set("local_means", (5, 2), 1e6), "local_means (norm) = 1e+06 at "
                       "Gaussian 5"),
    "opacity logit": (_set("opacity_logits", 7, -1e4), "opacity_logits = -10000"),
    "sh": (_set("sh", (2, 0, 1), 1e30), "sh = 1e+30 at Gaussian 2, column 1"),
    "quat tiny": (_set("quats", 4, torch.tensor([1e-9, 0.0, 0.0, 0.0])),
                  "quats (norm) = 1e-09 at Gaussian 4"),
    "quat huge": (_set("quats", 4, torch.tensor([1e20, 0.0, 0.0, 0.0])), "quats (norm) = 1e+20"),
    "parent": (_set("parents", 1, 10**9), "parents = 1e+09 at Gaussian 1"),
    "negative parent": (_set("parents", 1, -1), "parents = -1"),
    "nan": (_set("log_scales", (6, 0), float("nan")), "log_scales = nan at Gaussian 6"),
    "inf": (_set("sh", (0, 0, 0), float("inf")), "sh = inf"),
}


@pytest.mark.parametrize("case", BAD)
def test_each_field_out_of_range_is_named(synthetic, case):
    mutate, text = BAD[case]
    fields = _fields(synthetic)
    mutate(fields)
    with pytest.raises(RangeError) as err:
        check_gaussian_ranges(**fields, num_faces=synthetic.body.num_faces)
    assert text in str(err.value)
    assert "allowed range" in str(err.value)


def test_zero_quaternion_and_limits_are_settings(synthetic):
    fields = _fields(synthetic)
    fields["quats"][0] = 0.0  # the identity by convention: allowed
    check_gaussian_ranges(**fields)
    n = fields["parents"].shape[0]
    with pytest.raises(RangeError, match=f"{n} Gaussians, more than the allowed 10"):
        check_gaussian_ranges(**fields, ranges=GaussianRanges(max_gaussians=10))
    fields["log_scales"][:] = 7.0
    check_gaussian_ranges(**fields, ranges=GaussianRanges(log_scale_max=7.5))
    with pytest.raises(RangeError, match="log_scales"):
        check_gaussian_ranges(**fields)


def _absurd_package(synthetic, tmp_path, **values):
    fields = _fields(synthetic)
    for name, value in values.items():
        fields[name][:] = value
    package = type(synthetic)(**{**synthetic.__dict__,
                                 "avatar": type(synthetic.avatar)(**fields)})
    return save_package(package, tmp_path / "absurd.zip")


@pytest.mark.parametrize(("field", "value"), [("log_scales", 80.0), ("local_means", 1e30),
                                              ("sh", -1e6), ("opacity_logits", 1e30)])
def test_loader_refuses_absurd_packages(synthetic, tmp_path, field, value):
    path = _absurd_package(synthetic, tmp_path, **{field: value})
    with pytest.raises(PackageError, match=field):
        load_package(path)


def test_loader_refuses_values_beyond_float32(synthetic, tmp_path):
    """float64 arrays beyond float32's range become Inf when loaded: refused too."""
    path = save_package(synthetic, tmp_path / "pkg.zip")
    with zipfile.ZipFile(path) as z:
        manifest = z.read("avatar.json")
        arrays = dict(np.load(io.BytesIO(z.read("gaussians.npz"))))
    arrays["local_means"] = arrays["local_means"].astype(np.float64)
    arrays["local_means"][0, 0] = 1e300
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("avatar.json", manifest)
        z.writestr("gaussians.npz", buf.getvalue())
    with pytest.raises(PackageError, match="local_means"):
        load_package(path)


def test_server_refuses_the_log_scale_80_package_and_keeps_serving(server, synthetic,
                                                                   tmp_path):
    body = _absurd_package(synthetic, tmp_path, log_scales=math.log(1e34)).read_bytes()
    root = server.settings.data_dir / "avatars"
    before = {p.name for p in root.iterdir()}
    headers = {"Authorization": f"Bearer {server.token}"}
    with httpx.Client(base_url=server.url, headers=headers, timeout=30) as c:
        r = c.post("/v1/avatars", content=body, headers={"content-type": "application/zip"})
        assert r.status_code == 422, r.text
        assert "log_scales" in r.json()["detail"] and "allowed range" in r.json()["detail"]
        assert {p.name for p in root.iterdir()} == before  # nothing stored
        assert c.get("/v1/health").json()["status"] == "ok"

    async def one_frame():
        async with stream(server) as ws:
            return await recv_until(ws, is_type("frame"))
    assert asyncio.run(one_frame()).type == "frame"


def test_ranges_are_a_server_setting(synthetic, tmp_path):
    # A [gaussian_ranges] table in the settings file, a field overridden from the environment.
    config = tmp_path / "server.toml"
    config.write_text("[gaussian_ranges]\nmax_gaussians = 10\n")
    settings = load_settings(config, data_dir=tmp_path / "data",
                             environ={"TELESPLAT_GAUSSIAN_RANGES": '{"log_scale_max": 5.0}'})
    assert settings.gaussian_ranges == GaussianRanges(max_gaussians=10, log_scale_max=5.0)
    registry = AvatarRegistry.from_settings(settings)
    path = _absurd_package(synthetic, tmp_path)  # nothing changed: valid by default
    with pytest.raises(PackageError, match="more than the allowed 10"):
        registry.add_package(path, owner="alice")
    assert registry.list() == []
    relaxed = AvatarRegistry(tmp_path / "relaxed")
    assert relaxed.add_package(path, owner="alice").num_gaussians == synthetic.avatar.num
