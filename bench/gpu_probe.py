"""What the offline GPU check asks of the environment it built, run inside it (the carried
wheels on PYTHONPATH). Prints one JSON object as its last line.

    python bench/gpu_probe.py imports [--cuda]   # every module the check imports, versions
    python bench/gpu_probe.py gsplat             # compile gsplat's kernels, render once

``imports`` exits 1 when a module the check needs is missing (``--cuda``: also gsplat and what
its JIT build needs: rich, packaging, ninja, nvcc; and a torch that sees the GPU). ``gsplat``
times loading gsplat's extension (the JIT compile, when its cache is cold) and one 256 px
render of the shared test scene.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import json
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# What the server, the gpu tests and bench/gpu_check.py import (module: distribution).
NEEDED = {"torch": "torch", "numpy": "numpy", "numba": "numba", "scipy": "scipy",
          "cv2": None, "msgpack": "msgpack", "prometheus_client": "prometheus-client",
          "tqdm": "tqdm", "fastapi": "fastapi", "starlette": "starlette", "uvicorn": "uvicorn",
          "websockets": "websockets", "pydantic": "pydantic", "python_multipart":
          "python-multipart", "httpx": "httpx", "av": "av", "onnxruntime": "onnxruntime",
          "pytest": "pytest", "server.app": None, "client": None}
# The CUDA rasterizer and its JIT build (gsplat/cuda/_backend.py imports rich and packaging;
# torch runs ninja and nvcc): needed on the GPU, reported where found on a dry run.
CUDA_NEEDED = {"gsplat": "gsplat", "rich": "rich", "packaging": "packaging"}
# Used where present, said where not.
OPTIONAL = {"torchvision": "torchvision", "pytest_timeout": "pytest-timeout"}


def _version(module, dist: str | None) -> str:
    if dist is not None:
        try:
            return importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            pass
    return str(getattr(module, "__version__", "?"))


def _import_all(modules: dict[str, str | None]) -> tuple[dict[str, str], dict[str, str]]:
    found, missing = {}, {}
    for name, dist in modules.items():
        try:
            module = importlib.import_module(name)
        except Exception as exc:  # noqa: BLE001 - any failure to import is the finding
            missing[name] = f"{type(exc).__name__}: {exc}"
        else:
            where = Path(getattr(module, "__file__", "") or "").parent
            found[name] = f"{_version(module, dist)} ({where})"
    return found, missing


def _cuda_home() -> str | None:
    """Where torch's JIT builds take nvcc from (CUDA_HOME, the PATH, /usr/local/cuda): the
    function gsplat's backend asks too."""
    try:
        from torch.utils.cpp_extension import _find_cuda_home
    except ImportError:  # a torch that renamed it: its public constant
        from torch.utils.cpp_extension import CUDA_HOME

        return CUDA_HOME
    return _find_cuda_home()


def imports(cuda: bool) -> int:
    found, missing = _import_all(NEEDED | (CUDA_NEEDED if cuda else {}))
    optional, optional_missing = _import_all(OPTIONAL | ({} if cuda else CUDA_NEEDED))
    import torch

    cuda_home = _cuda_home()
    nvcc = Path(cuda_home, "bin", "nvcc") if cuda_home else None
    tools = {"ninja": shutil.which("ninja"),
             "nvcc": str(nvcc) if nvcc is not None and nvcc.is_file() else None}
    if cuda:
        missing |= {tool: "not found (ninja: PATH; nvcc: CUDA_HOME, PATH or /usr/local/cuda)"
                    for tool, path in tools.items() if path is None}
    report: dict = {"python": sys.version.split()[0], "found": found | optional,
                    "missing": missing, "optional_missing": optional_missing, "tools": tools}

    report["torch"] = {"version": torch.__version__, "cuda": torch.version.cuda,
                       "cuda_available": torch.cuda.is_available()}
    if cuda and not torch.cuda.is_available():
        missing["torch.cuda"] = f"torch {torch.__version__} sees no CUDA device"
    if "onnxruntime" in found:
        import onnxruntime

        report["onnxruntime_providers"] = onnxruntime.get_available_providers()
    for name, why in {**missing, **optional_missing}.items():
        print(f"missing: {name}: {why}")
    print(json.dumps(report))
    return 1 if missing else 0


def gsplat_build() -> int:
    import torch

    t0 = time.perf_counter()
    from gsplat.cuda._backend import _C  # the JIT compile, or loading the cached build

    load_s = time.perf_counter() - t0
    if _C is None:
        print("gsplat found no CUDA toolkit (nvcc): its kernels were not compiled")
        print(json.dumps({"load_s": load_s, "compiled": False}))
        return 1
    from avatar_core.render import rasterize
    from avatar_core.render.scenes import avatar_camera, avatar_like_scene
    from avatar_core.render.types import GaussianSet, RenderRequest

    scene = avatar_like_scene(5_000, 0)
    scene = GaussianSet(*(t.cuda() for t in (scene.means, scene.quats, scene.scales,
                                             scene.opacities, scene.sh)))
    t0 = time.perf_counter()
    out = rasterize(scene, avatar_camera(256), RenderRequest(backend="gsplat"))
    torch.cuda.synchronize()
    render_s = time.perf_counter() - t0
    ok = out.stats["backend"] == "gsplat" and bool(torch.isfinite(out.rgb).all())
    print(json.dumps({"load_s": load_s, "first_render_s": render_s, "compiled": True,
                      "rendered": ok, "module": getattr(_C, "__file__", None),
                      "gsplat": importlib.metadata.version("gsplat")}))
    return 0 if ok else 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="what", required=True)
    sub.add_parser("imports").add_argument("--cuda", action="store_true")
    sub.add_parser("gsplat")
    args = parser.parse_args(argv)
    return imports(args.cuda) if args.what == "imports" else gsplat_build()


if __name__ == "__main__":
    sys.exit(main())
