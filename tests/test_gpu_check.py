"""`make gpu-check` and bench/gpu_check.py on a machine without CUDA: both stop at once with
"no CUDA device"; the bench's dry run (CPU, tiny sizes) writes its section of docs/gpu.md,
with the ratio table, and every number as JSON."""

import importlib.util
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
no_cuda = pytest.mark.skipif(torch.cuda.is_available(), reason="checks the no-CUDA refusal")


def _bench():
    spec = importlib.util.spec_from_file_location("gpu_check", ROOT / "bench" / "gpu_check.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


@no_cuda
@pytest.mark.skipif(shutil.which("make") is None, reason="no make here")
def test_make_gpu_check_fails_fast_without_cuda():
    if shutil.which("nvidia-smi"):
        pytest.skip("nvidia-smi present: the check would go on to install")
    done = subprocess.run(["make", "-s", "gpu-check", "GPU_VENV=/nonexistent/gpu-venv"],
                          cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert done.returncode != 0
    assert "no CUDA device" in done.stderr
    assert not Path("/nonexistent/gpu-venv").exists()  # nothing installed


@no_cuda
def test_the_bench_refuses_without_cuda(tmp_path, capsys):
    """Its ``main`` in this process (a subprocess costs seconds of imports; the dry run below
    runs the script as users do)."""
    out = tmp_path / "gpu.md"
    assert _bench().main(["--out", str(out)]) == 2
    assert "no CUDA device" in capsys.readouterr().err
    assert not out.exists()


def test_the_section_is_replaced_and_the_rest_kept(tmp_path):
    bench = _bench()
    doc = tmp_path / "gpu.md"
    doc.write_text(f"# GPU\n\nintro\n\n{bench.BEGIN}\nold table\n{bench.END}\n\nhow to run\n")
    bench.write_section(doc, f"{bench.BEGIN}\nnew table\n{bench.END}")
    text = doc.read_text()
    assert "old table" not in text and "new table" in text
    assert text.startswith("# GPU\n\nintro") and text.rstrip().endswith("how to run")
    fresh = tmp_path / "fresh.md"
    bench.write_section(fresh, f"{bench.BEGIN}\nx\n{bench.END}")
    assert fresh.read_text().count(bench.BEGIN) == 1


def test_the_committed_page_has_the_section_and_says_why_it_is_empty():
    """The measured section names the GPU it came from; an empty one says why it is empty."""
    bench = _bench()
    text = (ROOT / "docs" / "gpu.md").read_text()
    assert text.count(bench.BEGIN) == 1 and text.count(bench.END) == 1
    section = text.split(bench.BEGIN, 1)[1].split(bench.END, 1)[0]
    if "| not measured |" in section:
        assert "No GPU was lent" in text
    else:
        assert "Measured by `make gpu-check` on **" in section


@pytest.mark.slow
def test_the_dry_run_writes_every_figure(tmp_path):
    """The whole script on the CPU at tiny sizes (a server on loopback included)."""
    out, numbers = tmp_path / "gpu.md", tmp_path / "figures.json"
    done = subprocess.run([sys.executable, str(ROOT / "bench" / "gpu_check.py"), "--dry-run",
                           "--out", str(out), "--json", str(numbers), "--seconds", "0.5"],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    text = out.read_text()
    for figure in ("render fps", "drive -> frame p95", "viewers of distinct views",
                   "training it/s"):
        assert figure in text
    assert "CPU (dry run)" in text and "n/a" not in text
    # the ratios: what exists on the CPU measured, nvJPEG said to be missing
    assert "| render 64x48, 500 Gaussians | cpu: " in text and "| torch: " in text
    assert "| one render_views call: " in text
    assert "| device-resident: " in text and "| host-checked: " in text
    assert "not measured: no nvJPEG here" in text and "Dry run: the CPU" in text
    doc = json.loads(numbers.read_text())
    assert doc["dry_run"] and doc["figures"]["render_fps"] > 0
    ratios = {r["what"].split()[0]: r for r in doc["ratios"]}
    assert set(ratios) == {"render", "3", "JPEG", "training"}
    assert ratios["JPEG"]["ratio"] is None and ratios["JPEG"]["slow_rate"] > 0
    assert all(r["ratio"] > 0 for k, r in ratios.items() if k != "JPEG")
