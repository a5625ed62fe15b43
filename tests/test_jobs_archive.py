"""Upload archive checks without a server: where the dataset root is, member limits,
duplicate and special members, bombs, budgets, liars and damage, and nothing left behind
when unpacking fails."""

import io
import os
import struct
import zipfile

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from server.jobs.archive import ArchiveError, UploadLimits, check_archive, extract_archive

from .upload_bombs import corrupt, zip_bomb


def _zip(*members: tuple[str, bytes]) -> io.BytesIO:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for name, data in members:
            z.writestr(name, data)
    buf.seek(0)
    return buf


@pytest.mark.parametrize("names, root", [
    (("dataset.json", "cameras.json", "sequences/a/params.npz"), "."),
    (("take/dataset.json", "take/cameras.json", "take/sequences/a/params.npz"), "take"),
])
def test_the_dataset_root_is_the_top_or_the_one_top_folder(tmp_path, names, root):
    out = extract_archive(_zip(*[(n, b"x") for n in names]), tmp_path / "u", UploadLimits())
    assert out == tmp_path / "u" / root
    assert (out / "dataset.json").read_bytes() == b"x"
    assert (out / "sequences" / "a" / "params.npz").is_file()


@pytest.mark.parametrize("members, limits, status, words", [
    ((("a/dataset.json", b"{}"), ("b/x", b"1")), UploadLimits(), 400, "no dataset.json"),
    ((("dataset.json", b"{}"), ("x", b"1"), ("y", b"2")), UploadLimits(max_files=2), 413,
     "members"),
    ((("dataset.json", b"{}"), ("./dataset.json", b"{}")), UploadLimits(), 400, "twice"),
    ((("dataset.json", b"{}"), ("a\\..\\b", b"1")), UploadLimits(), 400, "bad characters"),
    ((("C:/dataset.json", b"{}"),), UploadLimits(), 400, "absolute"),
    ((), UploadLimits(), 400, "empty"),
])
def test_refused_archives(tmp_path, members, limits, status, words):
    with pytest.raises(ArchiveError, match=words) as err:
        extract_archive(_zip(*members), tmp_path / "u", limits)
    assert err.value.status == status
    assert not (tmp_path / "u").exists()


def test_device_files_and_encrypted_members_are_refused():
    info = zipfile.ZipInfo("dataset.json")
    info.external_attr = 0o020666 << 16  # a character device
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr(info, b"")
    with pytest.raises(ArchiveError, match="only files and folders"):
        check_archive(buf, UploadLimits())
    raw = bytearray(_zip(("dataset.json", b"{}")).getvalue())
    for signature, flags_at in ((b"PK\x03\x04", 6), (b"PK\x01\x02", 8)):  # zipfile
        at = raw.index(signature) + flags_at  # cannot write the encrypted bit itself
        raw[at] |= 0x1
    with pytest.raises(ArchiveError, match="encrypted"):
        check_archive(io.BytesIO(bytes(raw)), UploadLimits())


def _declare_size(data: bytes, size: int) -> bytes:
    """The zip with its (one) member's unpacked size rewritten in both headers: a liar."""
    raw = bytearray(data)
    for signature, at in ((b"PK\x03\x04", 22), (b"PK\x01\x02", 24)):
        start = raw.index(signature) + at
        raw[start:start + 4] = struct.pack("<I", size)
    return bytes(raw)


def test_a_member_that_lies_about_its_size_writes_no_more_than_declared(tmp_path):
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("dataset.json", os.urandom(100_000))
    liar = _declare_size(buf.getvalue(), 1000)
    with pytest.raises(ArchiveError, match="cannot be unpacked") as err:
        extract_archive(io.BytesIO(liar), tmp_path / "u", UploadLimits())
    assert err.value.status == 400 and not (tmp_path / "u").exists()


def _zeros_zip(nbytes: int, name: str = "cameras.json") -> io.BytesIO:
    return io.BytesIO(zip_bomb(name, nbytes, {"dataset.json": b"{}"}))


@pytest.mark.parametrize("nbytes, limits, words", [
    (256 << 20, UploadLimits(), "decompression bomb"),
    (8 << 20, UploadLimits(max_ratio=1e9, max_member_bytes=4 << 20), "more than the 4194304"),
    (8 << 20, UploadLimits(max_ratio=1e9, max_unpacked_bytes=4 << 20), "4194304 bytes allowed"),
    (8 << 20, UploadLimits(max_ratio=1e9, quota_bytes=4 << 20), "left of your storage quota"),
    (8 << 20, UploadLimits(max_ratio=1e9, quota_bytes=-5), "the 0 bytes left"),
    (8 << 20, UploadLimits(max_ratio=1e9, max_json_bytes=1 << 20), "bytes of JSON"),
])
def test_bombs_and_budgets_are_413_before_anything_is_written(tmp_path, nbytes, limits, words):
    with pytest.raises(ArchiveError, match=words) as err:
        extract_archive(_zeros_zip(nbytes), tmp_path / "u", limits)
    assert err.value.status == 413 and not (tmp_path / "u").exists()


def test_the_member_count_is_read_from_the_end_record(tmp_path):
    members = [("dataset.json", b"{}")] + [(f"f{i}", b"") for i in range(50)]
    with pytest.raises(ArchiveError, match="declares 51 members") as err:
        check_archive(_zip(*members), UploadLimits(max_files=10))
    assert err.value.status == 413


@pytest.mark.parametrize("damage, words", [
    (lambda d: d[: len(d) // 2], "not a readable zip"),
    (lambda d: d[:-5], "not a readable zip"),
    (lambda d: corrupt(d, at=0.3, span=16), "cannot be unpacked"),
])
def test_damaged_archives_are_400(tmp_path, damage, words):
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("dataset.json", os.urandom(20_000))
        z.writestr("cameras.json", os.urandom(20_000))
    with pytest.raises(ArchiveError, match=words) as err:
        extract_archive(io.BytesIO(damage(buf.getvalue())), tmp_path / "u", UploadLimits())
    assert err.value.status == 400 and not (tmp_path / "u").exists()


def _dataset_like_zip() -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("take/dataset.json", b'{"name": "take"}' * 20)
        z.writestr("take/cameras.json", os.urandom(3000))
        z.writestr("take/sequences/a/params.npz", bytes(5000), zipfile.ZIP_STORED)
        z.writestr("take/sequences/a/images/cam00/00000.png", os.urandom(2000))
    return buf.getvalue()


VALID_ZIP = _dataset_like_zip()
FUZZ_LIMITS = UploadLimits(max_unpacked_bytes=1 << 20, max_member_bytes=1 << 19,
                           max_files=64, max_ratio=50, ratio_floor_bytes=1 << 16)


@settings(max_examples=200, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(flips=st.lists(st.tuples(st.integers(0, len(VALID_ZIP) - 1), st.integers(0, 255)),
                      max_size=8),
       keep=st.integers(0, len(VALID_ZIP)))
def test_fuzz_mutated_archives(tmp_path_factory, flips, keep):
    """A damaged archive is an ArchiveError (and leaves nothing) or unpacks within the limits."""
    data = bytearray(VALID_ZIP)
    for at, value in flips:
        data[at] = value
    dest = tmp_path_factory.mktemp("fuzz") / "u"
    try:
        root = extract_archive(io.BytesIO(bytes(data[:keep])), dest, FUZZ_LIMITS)
    except ArchiveError as exc:
        assert exc.status in (400, 413)
        assert not dest.exists()
    else:
        assert root.is_relative_to(dest)
        written = sum(p.stat().st_size for p in dest.rglob("*") if p.is_file())
        assert written <= FUZZ_LIMITS.max_unpacked_bytes
