"""The bounded npz reader: the arrays np.load would read, and for hostile files a clear
NpzError within the stated memory (measured with tracemalloc, which sees numpy's buffers)."""

import contextlib
import io
import tracemalloc
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from avatar_core.bounded_npz import NpzError, NpzLimits, read_npz

from .upload_bombs import impossible_shape_npy, npy_header, npz_bytes

MiB = 1 << 20


@contextlib.contextmanager
def peak_memory():
    """Yields a dict whose "peak" is the most bytes allocated above the start, once done."""
    out = {}
    started = not tracemalloc.is_tracing()
    if started:
        tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    tracemalloc.reset_peak()
    try:
        yield out
    finally:
        out["peak"] = tracemalloc.get_traced_memory()[1] - base
        if started:
            tracemalloc.stop()


def _valid_npz() -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, a=np.arange(60, dtype=np.float32).reshape(3, 4, 5),
                        f=np.asfortranarray(np.arange(6).reshape(2, 3)), s=np.float64(2.5),
                        e=np.zeros((0, 3)), big_endian=np.arange(4, dtype=">i4"),
                        flags=np.array([True, False]), c=np.array([1 + 2j]))
    return buf.getvalue()


def test_reads_what_np_load_reads():
    data = _valid_npz()
    ours = read_npz(data)
    with np.load(io.BytesIO(data)) as npz:
        assert sorted(ours) == sorted(npz.files)
        for key in npz.files:
            assert ours[key].dtype == npz[key].dtype and ours[key].shape == npz[key].shape
            np.testing.assert_array_equal(ours[key], npz[key])
    assert ours["f"].flags.f_contiguous


def test_a_deflated_bomb_is_refused_before_anything_is_unpacked():
    bomb = npz_bytes({"x": np.ones(3)}, bomb=("sh", 1 << 30))  # 1 GiB of zeros
    assert len(bomb) < 2 * MiB
    with peak_memory() as mem, pytest.raises(NpzError, match="decompression bomb") as err:
        read_npz(bomb)
    assert err.value.over_limit and "sh.npy" in str(err.value)
    assert mem["peak"] < 8 * MiB, mem


def test_declared_shapes_are_checked_before_allocating():
    for shape in ((10**13,), (2**40, 2**40), (10**6, 10**6, 10**6)):
        data = npz_bytes({}, raw={"p": impossible_shape_npy(shape)})
        with peak_memory() as mem, pytest.raises(NpzError, match="declares shape") as err:
            read_npz(data)
        assert err.value.over_limit and "'p.npy'" in str(err.value)
        assert mem["peak"] < 4 * MiB, mem
    # within the ratio limit but past the per-array budget: refused from the header alone
    data = npz_bytes({}, bomb=("big", 256 * MiB))
    with peak_memory() as mem, pytest.raises(NpzError, match="per array"):
        read_npz(data, NpzLimits(max_ratio=1e9, max_array_bytes=64 * MiB))
    assert mem["peak"] < 8 * MiB, mem


def test_reading_costs_the_arrays_and_a_chunk():
    data = npz_bytes({}, bomb=("z", 32 * MiB))
    with peak_memory() as mem:
        arrays = read_npz(data, NpzLimits(max_ratio=1e9))
    assert arrays["z"].nbytes == 32 * MiB and not arrays["z"].any()
    assert mem["peak"] < 32 * MiB + 8 * MiB, mem
    # the total budget counts every array
    with pytest.raises(NpzError, match="in all"):
        read_npz(npz_bytes({"a": np.zeros(300), "b": np.zeros(300)}),
                 NpzLimits(max_total_bytes=4000))


@pytest.mark.parametrize("make, words", [
    (lambda: npz_bytes({}, raw={"o": npy_header((3,), "|O") + b"\0" * 24}), "not a plain"),
    (lambda: npz_bytes({"r": np.zeros(2, dtype=[("a", "<f4"), ("b", "<i4")])}), "not a plain"),
    (lambda: npz_bytes({}, raw={"t": npy_header((100,)) + b"\0" * 40}), "bytes of data"),
    (lambda: npz_bytes({}, raw={"u": npy_header((10,)) + b"\0" * 20}), "truncated"),
    (lambda: b"PK\x03\x04" + b"\0" * 100, "not a zip"),
    (lambda: b"", "not a zip"),
    (lambda: _valid_npz()[: len(_valid_npz()) // 2], "not a zip"),
    (lambda: _with_member("notes.txt", b"hi"), "not an .npy"),
])
def test_malformed_files_are_one_clear_error(make, words):
    with pytest.raises(NpzError, match=words):
        read_npz(make())


def _with_member(name: str, data: bytes) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr(name, data)
    return buf.getvalue()


def test_member_count_is_checked_on_the_end_record():
    data = npz_bytes({f"k{i}": np.zeros(1) for i in range(10)})
    with pytest.raises(NpzError, match="more than the 4 allowed") as err:
        read_npz(data, NpzLimits(max_members=4))
    assert err.value.over_limit


FUZZ_LIMITS = NpzLimits(max_array_bytes=MiB, max_total_bytes=2 * MiB, max_ratio=50,
                        ratio_floor_bytes=64 * 1024)
VALID = _valid_npz()


def _assert_bounded(data: bytes) -> None:
    with peak_memory() as mem:
        try:
            arrays = read_npz(data, FUZZ_LIMITS)
        except NpzError:
            arrays = {}
    assert sum(a.nbytes for a in arrays.values()) <= FUZZ_LIMITS.max_total_bytes
    # the arrays, a read chunk and zipfile's buffers, whatever the input
    assert mem["peak"] < FUZZ_LIMITS.max_total_bytes + 4 * MiB + 4 * len(data), mem


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=4096))
def test_fuzz_random_bytes(data):
    _assert_bounded(data)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(st.integers(0, len(VALID) - 1), st.integers(0, 255)), max_size=8),
       st.integers(0, len(VALID)))
def test_fuzz_mutated_valid_npz(flips, keep):
    data = bytearray(VALID)
    for at, value in flips:
        data[at] = value
    _assert_bounded(bytes(data[:keep]))
