"""Property-based fuzzing of the avatar package loader: whatever the zip, its manifest or its
arrays hold, ``load_package`` gives a package or a PackageError, within a bounded memory."""

import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from avatar_core.bounded_npz import NpzLimits
from avatar_core.gaussians.loading import load_avatar
from avatar_core.gaussians.package import PackageError, load_package, save_package

from .test_bounded_npz import MiB, peak_memory

LIMITS = NpzLimits(max_array_bytes=2 * MiB, max_total_bytes=4 * MiB, max_ratio=50,
                   ratio_floor_bytes=64 * 1024)
KEYS = ("parents", "local_means", "log_scales", "quats", "opacity_logits", "sh")


@pytest.fixture(scope="module")
def members(tmp_path_factory) -> tuple[dict, dict[str, np.ndarray]]:
    """The manifest and arrays of a small valid package (the synthetic avatar, 64 Gaussians)."""
    package = load_avatar("synthetic").package
    path = save_package(package, tmp_path_factory.mktemp("pkg") / "p.zip")
    with zipfile.ZipFile(path) as z:
        manifest = json.loads(z.read("avatar.json"))
        with np.load(io.BytesIO(z.read("gaussians.npz"))) as npz:
            arrays = {k: npz[k][:64] for k in npz.files}
    manifest["gaussians"]["count"] = 64
    return manifest, arrays


def _zip(manifest: bytes, arrays: dict[str, np.ndarray]) -> bytes:
    npz = io.BytesIO()
    np.savez_compressed(npz, **arrays)
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("avatar.json", manifest)
        z.writestr("gaussians.npz", npz.getvalue())
    return out.getvalue()


def _load_bounded(tmp: Path, data: bytes) -> None:
    path = tmp / "fuzz.zip"
    path.write_bytes(data)
    with peak_memory() as mem:
        try:
            package = load_package(path, max_bytes=8 * MiB, npz_limits=LIMITS)
        except PackageError:
            package = None
    if package is not None:
        assert package.avatar.num == package.avatar.parents.shape[0]
    assert mem["peak"] < 32 * MiB, mem


def test_the_fixture_package_loads(members, tmp_path):
    manifest, arrays = members
    path = tmp_path / "ok.zip"
    path.write_bytes(_zip(json.dumps(manifest).encode(), arrays))
    assert load_package(path, npz_limits=LIMITS).avatar.num == 64


DTYPES = st.sampled_from(["<f4", "<f8", ">f4", "<f2", "<i8", "<i4", "<u2", "|u1", "|b1",
                          "<c8"])
SHAPES = st.lists(st.integers(0, 70), max_size=4).map(tuple)
JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner,
                                                                max_size=3),
    max_leaves=8)


@settings(max_examples=120, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(key=st.sampled_from(KEYS), dtype=DTYPES, shape=st.none() | SHAPES,
       fill=st.sampled_from([0.0, 1.0, -1.0, 1e30, -70000.0, np.nan]))
def test_fuzz_arrays(members, tmp_path, key, dtype, shape, fill):
    manifest, arrays = members
    original = arrays[key]
    with np.errstate(all="ignore"):
        value = np.full(original.shape if shape is None else shape, fill).astype(dtype)
    _load_bounded(tmp_path, _zip(json.dumps(manifest).encode(), {**arrays, key: value}))


@settings(max_examples=120, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(path=st.lists(st.sampled_from(["schema_version", "body_model", "model", "parts",
                                      "num_faces", "faces_sha256", "betas", "metadata",
                                      "name", "gaussians", "training"]),
                     min_size=1, max_size=2),
       value=JSON_VALUES)
def test_fuzz_manifest(members, tmp_path, path, value):
    manifest, arrays = members
    doc = json.loads(json.dumps(manifest))
    node = doc
    for key in path[:-1]:
        if not isinstance(node.get(key), dict):
            break
        node = node[key]
    node[path[-1]] = value
    _load_bounded(tmp_path, _zip(json.dumps(doc).encode(), arrays))


@settings(max_examples=120, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(flips=st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(0, 255)),
                      max_size=6),
       keep=st.floats(0, 1))
def test_fuzz_zip_bytes(members, tmp_path, flips, keep):
    manifest, arrays = members
    data = bytearray(_zip(json.dumps(manifest).encode(), arrays))
    for at, value in flips:
        data[int(at * len(data))] = value
    _load_bounded(tmp_path, bytes(data[:max(1, int(keep * len(data)))]))
