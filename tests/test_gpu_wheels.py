"""The wheel list of the offline GPU check (requirements-gpu-offline.txt, `make gpu-wheels`):
every line pinned and explained, the pins inside pyproject.toml's ranges, and the downloaded
folder checked for one wheel per pin, nothing pulled implicitly, and its size."""

from __future__ import annotations

import sys
import tomllib
from pathlib import Path

import pytest
from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

import gpu_wheels  # noqa: E402

LIST = ROOT / "requirements-gpu-offline.txt"


def _project_requirements() -> dict[str, Requirement]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    lines = project["dependencies"] + project["optional-dependencies"]["cuda"]
    return {gpu_wheels.normalise(r.name): r for r in map(Requirement, lines)}


def test_the_list_pins_inside_the_projects_ranges():
    pins = gpu_wheels.read_pins(LIST)
    project = _project_requirements()
    names = {p.name for p in pins}
    assert {"fastapi", "uvicorn", "pydantic", "websockets", "av", "gsplat"} <= names
    assert not names & {"torch", "torchvision", "numpy"}  # the machine's CUDA builds stay
    for pin in pins:
        if pin.name in project:
            assert project[pin.name].specifier.contains(pin.version), pin.spec
    assert next(p for p in pins if p.name == "gsplat").version == "1.5.3"


@pytest.mark.parametrize(("text", "problem"), [
    ("fastapi>=0.115  # the app\n", "not 'name==version'"),
    ("fastapi==0.165.0\n", "no reason"),
    ("fastapi==0.165.0  # a\nFastAPI==0.165.0  # b\n", "listed twice"),
])
def test_a_bad_line_is_refused(tmp_path, text, problem):
    path = tmp_path / "list.txt"
    path.write_text("# comment\n\n" + text)
    with pytest.raises(ValueError, match=problem):
        gpu_wheels.read_pins(path)


def _wheel(folder: Path, name: str, size: int = 10) -> None:
    (folder / name).write_bytes(b"x" * size)


def test_the_folder_holds_one_wheel_per_pin(tmp_path):
    pins = [gpu_wheels.Pin("typing-extensions", "4.16.0", "why"),
            gpu_wheels.Pin("av", "18.1.0", "why")]
    _wheel(tmp_path, "typing_extensions-4.16.0-py3-none-any.whl")
    _wheel(tmp_path, "av-18.1.0-cp311-abi3-manylinux_2_28_x86_64.whl")
    sizes = gpu_wheels.check_folder(tmp_path, pins, limit_mib=1)
    assert [name for name, _ in sizes] == ["av-18.1.0-cp311-abi3-manylinux_2_28_x86_64.whl",
                                           "typing_extensions-4.16.0-py3-none-any.whl"]
    _wheel(tmp_path, "av-17.0.0-cp311-abi3-manylinux_2_28_x86_64.whl")
    _wheel(tmp_path, "idna-3.20-py3-none-any.whl")
    with pytest.raises(ValueError) as err:
        gpu_wheels.check_folder(tmp_path, pins, limit_mib=1)
    assert "av: 2 versions" in str(err.value) and "idna is not in the list" in str(err.value)


def test_a_missing_pin_a_wrong_version_and_the_size_limit_are_refused(tmp_path):
    pins = [gpu_wheels.Pin("fastapi", "0.165.0", "why"), gpu_wheels.Pin("gsplat", "1.5.3", "w")]
    _wheel(tmp_path, "fastapi-0.164.0-py3-none-any.whl", size=2 * gpu_wheels.MIB)
    with pytest.raises(ValueError) as err:
        gpu_wheels.check_folder(tmp_path, pins, limit_mib=1)
    text = str(err.value)
    assert "gsplat==1.5.3 is missing" in text and "fastapi: 0.164.0 instead of 0.165.0" in text
    assert "over the 1 MiB limit" in text
