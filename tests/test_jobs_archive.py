"""Upload archive checks without a server: where the dataset root is, member limits,
duplicate and special members, and nothing left behind when unpacking fails."""

import io
import zipfile

import pytest

from server.jobs.archive import ArchiveError, UploadLimits, check_archive, extract_archive


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
