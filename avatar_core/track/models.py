"""The MediaPipe landmark models: fetched from PyPI, converted to ONNX, cached.

The TFLite models (Apache-2.0) ship inside the mediapipe wheel. The wheel is downloaded with
``pip download --no-deps`` (never installed, never imported: mediapipe pins an old protobuf),
only the listed ``.tflite`` files are read out of it with ``zipfile``, their sha256 are checked
against the values pinned here (the files are the same in every platform's wheel) and each is
converted to ONNX by `avatar_core.track.convert`. Everything lives in one cache folder,
``~/.cache/telesplat/mediapipe`` unless ``TELESPLAT_MEDIAPIPE_CACHE`` or an explicit path says
otherwise, with a ``manifest.json`` recording the wheel, every file's sha256, the converter
version and each model's input / output signature.

Layout of the cache::

    wheels/mediapipe-0.10.14-*.whl
    tflite/<name>.tflite
    onnx/<name>.onnx
    manifest.json

A user's own ONNX model can replace a converted one when it has the same inputs and outputs
(names, shapes, float32): see `model_path(..., override=...)`.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import subprocess
import sys
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path

MEDIAPIPE_VERSION = "0.10.14"
CONVERTER_VERSION = 1  # bump when the converter's output changes: cached ONNX is rebuilt
FETCH_COMMAND = "telesplat track fetch-models"  # what the errors tell the user to run

# name -> (path inside the wheel, sha256 of the .tflite)
MODELS: dict[str, tuple[str, str]] = {
    "face_detection_short_range": (
        "mediapipe/modules/face_detection/face_detection_short_range.tflite",
        "bbff11cebd1eb27a1e004cae0b0e63ec8c551cbf34a4451148b4908b8db3eca8"),
    "face_landmark": (
        "mediapipe/modules/face_landmark/face_landmark.tflite",
        "1055cb9d4a9ca8b8c688902a3a5194311138ba256bcc94e336d8373a5f30c814"),
    "palm_detection_lite": (
        "mediapipe/modules/palm_detection/palm_detection_lite.tflite",
        "e9a4aaddf90dda56a87235303cf00e4c2d3fb28725f68fd88772997dac905c18"),
    "palm_detection_full": (
        "mediapipe/modules/palm_detection/palm_detection_full.tflite",
        "1b14e9422c6ad006cde6581a46c8b90dd573c07ab7f3934b5589e7cea3f89a54"),
    "hand_landmark_lite": (
        "mediapipe/modules/hand_landmark/hand_landmark_lite.tflite",
        "048edd3645c9bf7397d19a9f6e3a42957d6e414c9bea6598030a2e9b624156e6"),
    "hand_landmark_full": (
        "mediapipe/modules/hand_landmark/hand_landmark_full.tflite",
        "11c272b891e1a99ab034208e23937a8008388cf11ed2a9d776ed3d01d0ba00e3"),
    "pose_detection": (
        "mediapipe/modules/pose_detection/pose_detection.tflite",
        "9ba9dd3d42efaaba86b4ff0122b06f29c4122e756b329d89dca1e297fd8f866c"),
    "pose_landmark_full": (
        "mediapipe/modules/pose_landmark/pose_landmark_full.tflite",
        "e9a5c5cb17f736fafd4c2ec1da3b3d331d6edbe8a0d32395855aeb2cdfd64b9f"),
    "selfie_segmentation": (
        "mediapipe/modules/selfie_segmentation/selfie_segmentation.tflite",
        "9ee168ec7c8f2a16c56fe8e1cfbc514974cbbb7e434051b455635f1bd1462f5c"),
    "iris_landmark": (
        "mediapipe/modules/iris_landmark/iris_landmark.tflite",
        "d1744d2a09c25f501d39eba4faff47e53ecca8852c5ce19bce8eeac39357521f"),
}

# Where the running interpreter has no mediapipe 0.10.14 wheel (a newer Python, another
# platform), any wheel will do, since the .tflite files are identical: this one is asked for.
_FALLBACK_TARGET = ["--python-version", "3.11", "--platform", "manylinux2014_x86_64"]


class ModelFetchError(RuntimeError):
    """The models are missing and cannot be fetched; the message says what and how to fix."""


def cache_dir(path: str | Path | None = None) -> Path:
    if path is not None:
        return Path(path).expanduser()
    env = os.environ.get("TELESPLAT_MEDIAPIPE_CACHE")
    if env:
        return Path(env).expanduser()
    return Path.home() / ".cache" / "telesplat" / "mediapipe"


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


@contextlib.contextmanager
def _locked(cache: Path) -> Iterator[None]:
    """One fetch at a time per cache (parallel test workers share it)."""
    import fcntl

    cache.mkdir(parents=True, exist_ok=True)
    with open(cache / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def find_wheel(cache: Path) -> Path | None:
    wheels = sorted((cache / "wheels").glob(f"mediapipe-{MEDIAPIPE_VERSION}-*.whl"))
    return wheels[0] if wheels else None


def download_wheel(cache: Path, timeout: float = 900.0) -> Path:
    """`pip download --no-deps --only-binary=:all: mediapipe==VERSION` into cache/wheels."""
    dest = cache / "wheels"
    dest.mkdir(parents=True, exist_ok=True)
    base = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:",
            "--disable-pip-version-check", "-q", f"mediapipe=={MEDIAPIPE_VERSION}",
            "-d", str(dest)]
    errors = []
    for extra in ([], _FALLBACK_TARGET):
        try:
            proc = subprocess.run(base + extra, capture_output=True, text=True, timeout=timeout)
        except (OSError, subprocess.TimeoutExpired) as exc:
            errors.append(str(exc))
            continue
        wheel = find_wheel(cache)
        if proc.returncode == 0 and wheel is not None:
            return wheel
        lines = (proc.stderr or proc.stdout or "").strip().splitlines()
        errors.append(lines[-1] if lines else f"pip exited with {proc.returncode}")
    raise ModelFetchError(
        f"the MediaPipe models are missing: could not download the wheel "
        f"mediapipe=={MEDIAPIPE_VERSION} from PyPI into {dest} ({'; '.join(errors)}). "
        f"Fix: run `{FETCH_COMMAND}` (or `make models`) with network access to PyPI, or put "
        f"a mediapipe-{MEDIAPIPE_VERSION}-*.whl there yourself (`python -m pip download "
        f"--no-deps --only-binary=:all: mediapipe=={MEDIAPIPE_VERSION} -d {dest}`).")


def extract_models(wheel: Path, cache: Path, names: list[str] | None = None) -> dict[str, Path]:
    """Copy the listed .tflite files out of the wheel (zipfile; nothing is installed)."""
    out_dir = cache / "tflite"
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {}
    with zipfile.ZipFile(wheel) as zf:
        for name in names or list(MODELS):
            member, digest = MODELS[name]
            target = out_dir / f"{name}.tflite"
            if not (target.exists() and sha256(target) == digest):
                try:
                    data = zf.read(member)
                except KeyError as exc:
                    raise ModelFetchError(f"{wheel.name} has no {member}") from exc
                if hashlib.sha256(data).hexdigest() != digest:
                    raise ModelFetchError(f"{member} in {wheel.name} does not have the pinned "
                                          f"sha256 {digest}; refusing to use it")
                tmp = target.with_suffix(".tmp")
                tmp.write_bytes(data)
                tmp.replace(target)
            paths[name] = target
    return paths


def _signature(model) -> dict:
    def io(values):
        return [{"name": v.name, "shape": [d.dim_value for d in v.type.tensor_type.shape.dim],
                 "dtype": int(v.type.tensor_type.elem_type)} for v in values]

    return {"inputs": io(model.graph.input), "outputs": io(model.graph.output)}


def read_manifest(cache: Path) -> dict:
    try:
        return json.loads((cache / "manifest.json").read_text())
    except (OSError, ValueError):
        return {}


def fetch_models(cache: str | Path | None = None, *, convert: bool = True,
                 prelu: str = "rewrite", force: bool = False, names: list[str] | None = None,
                 progress: Callable[[str], None] | None = None) -> dict[str, Path]:
    """Make sure the wheel, the .tflite files and (if `convert`) the ONNX models are cached.

    Returns name -> ONNX path (or .tflite path when ``convert=False``). Raises
    `ModelFetchError` (saying what is missing and the command to fix it) when the wheel is not
    cached and cannot be downloaded. Cached ONNX files are reused while the .tflite sha256, the
    converter version and the PReLU mode are unchanged.
    """
    cache = cache_dir(cache)
    say = progress or (lambda _msg: None)
    names = names or list(MODELS)
    with _locked(cache):
        wheel = find_wheel(cache)
        if wheel is None:
            say(f"downloading mediapipe=={MEDIAPIPE_VERSION} (wheel only, not installed)")
            wheel = download_wheel(cache)
        tflite_paths = extract_models(wheel, cache, names)
        manifest = read_manifest(cache)
        manifest.update({"mediapipe": MEDIAPIPE_VERSION, "wheel": wheel.name,
                         "wheel_sha256": manifest.get("wheel_sha256") if manifest.get(
                             "wheel") == wheel.name else sha256(wheel)})
        models = manifest.setdefault("models", {})
        for name in names:
            models.setdefault(name, {}).update(
                {"tflite": f"tflite/{name}.tflite", "tflite_sha256": MODELS[name][1]})
        if not convert:
            _write_manifest(cache, manifest)
            return tflite_paths
        import onnx

        from .convert import convert as convert_model

        onnx_paths = {}
        for name in names:
            entry = models[name]
            target = cache / "onnx" / f"{name}.onnx"
            fresh = (not force and target.exists()
                     and entry.get("converter_version") == CONVERTER_VERSION
                     and entry.get("prelu") == prelu
                     and entry.get("onnx_sha256") == sha256(target))
            if not fresh:
                say(f"converting {name}")
                model = convert_model(tflite_paths[name], target, prelu=prelu, name=name)
                entry.update({"onnx": f"onnx/{name}.onnx", "onnx_sha256": sha256(target),
                              "converter_version": CONVERTER_VERSION, "prelu": prelu,
                              **_signature(model)})
                _write_manifest(cache, manifest)
            elif "inputs" not in entry:
                entry.update(_signature(onnx.load(target)))
            onnx_paths[name] = target
        _write_manifest(cache, manifest)
        return onnx_paths


def _write_manifest(cache: Path, manifest: dict) -> None:
    tmp = cache / "manifest.json.tmp"
    tmp.write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    tmp.replace(cache / "manifest.json")


def check_signature(path: str | Path, name: str, cache: str | Path | None = None) -> None:
    """Raise ValueError unless the ONNX model at `path` has `name`'s inputs and outputs."""
    import onnx

    cache = cache_dir(cache)
    expected = read_manifest(cache).get("models", {}).get(name, {})
    if "inputs" not in expected:
        raise ModelFetchError(f"no recorded signature for {name!r} in {cache}: run "
                              f"`{FETCH_COMMAND}` first")
    got = _signature(onnx.load(str(path), load_external_data=False))
    for kind in ("inputs", "outputs"):
        if got[kind] != expected[kind]:
            raise ValueError(f"{path}: {kind} {got[kind]} differ from {name}'s "
                             f"{expected[kind]}")


def model_path(name: str, cache: str | Path | None = None,
               override: str | Path | None = None) -> Path:
    """The ONNX model to run for `name`: the user's `override` (signature checked) or the
    converted one from the cache. Never downloads; errors name the command that fetches."""
    if name not in MODELS:
        raise ValueError(f"unknown model {name!r}; known: {', '.join(MODELS)}")
    if override is not None:
        check_signature(override, name, cache)
        return Path(override)
    path = cache_dir(cache) / "onnx" / f"{name}.onnx"
    if not path.exists():
        raise ModelFetchError(f"the ONNX model {name!r} is missing ({path}): run "
                              f"`{FETCH_COMMAND}` (or `make models`) to fetch and convert it")
    return path
