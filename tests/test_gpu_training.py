"""The training iteration without host round trips (avatar_core/train/device_step.py): run
on CPU with ``device_resident=True`` it must train like the host path, skip a non-finite
step on the device, and read nothing back per iteration; 500 iterations on CUDA are marked
``gpu``."""

import contextlib
import dataclasses
import math
import traceback

import pytest
import torch

from avatar_core.dataset import load_dataset
from avatar_core.synth.capture import CaptureSpec, capture
from avatar_core.train import photometric
from avatar_core.train.config import preset
from avatar_core.train.optim import GAUSSIAN_KEYS
from avatar_core.train.trainer import Trainer


@pytest.fixture(scope="module")
def dataset(synthetic_files, tmp_path_factory):
    out = tmp_path_factory.mktemp("gputrain") / "capture"
    spec = CaptureSpec(sequences=(("smile",),), num_cameras=4, resolution=48, max_frames=2,
                       supersample=1, cross_identity=None)
    return load_dataset(capture(out, spec, model_dir=synthetic_files.root))


def _config(**changes):
    base = preset("test")
    densify = dataclasses.replace(base.densify, from_iter=4, interval=6, until_iter=20)
    return dataclasses.replace(base, iterations=24, checkpoint_interval=1000,
                               progress_interval=8, densify=densify, **changes)


def _trainer(dataset, out, synthetic_files, **kw) -> Trainer:
    return Trainer(dataset, _config(), out, body_model=synthetic_files.root, **kw)


def test_device_path_trains_like_the_host_path(dataset, synthetic_files, tmp_path):
    events = {"host": [], "device": []}
    trainers = {}
    for name, resident in (("host", False), ("device", True)):
        tr = _trainer(dataset, tmp_path / name, synthetic_files, device_resident=resident,
                      progress=events[name].append)
        assert (tr.tally is not None) == resident
        tr.train(stop_at=24)
        trainers[name] = tr
    host, dev = trainers["host"], trainers["device"]
    assert host.num_gaussians == dev.num_gaussians  # the same densifications
    for key in GAUSSIAN_KEYS:
        # fused and for-each Adam round differently, and eps = 1e-15 turns a rounding flip
        # of a vanishing gradient into a full-size step of a few elements: agree closely
        diff = (host.state[key] - dev.state[key]).detach().abs()
        assert float(diff.max()) < 0.05 and float(diff.mean()) < 1e-4, key
    progress = {n: [e for e in ev if e["type"] == "progress"] for n, ev in events.items()}
    assert [e["iteration"] for e in progress["host"]] == [8, 16, 24]
    for h, d in zip(progress["host"], progress["device"], strict=True):
        assert d["loss"] == pytest.approx(h["loss"], rel=1e-3)
    assert dev.skipped == host.skipped == 0


def test_a_non_finite_step_is_skipped_on_the_device(dataset, synthetic_files, tmp_path):
    tr = _trainer(dataset, tmp_path, synthetic_files, device_resident=True)
    tr.step()  # one real step, then every view's target poisoned
    for i in range(len(tr.views)):
        tr.views.get(i).target.fill_(math.nan)
    assert tr.views.config.cache_views >= len(tr.views)  # kept: the poisoned ones are used
    before = {k: tr.state[k].detach().clone() for k in GAUSSIAN_KEYS}
    steps = [s["step"].clone() for s in tr.optimizer.state.values()]
    for _ in range(3):
        result = tr.step()
        assert result.loss is None and result.skipped is None  # known only on the device
    for k in GAUSSIAN_KEYS:
        assert torch.equal(before[k], tr.state[k]), k  # no step reached the model
    assert [s["step"] for s in tr.optimizer.state.values()] == steps
    assert tr.skipped == 0
    tr._flush_tally()
    assert tr.skipped == 3


# the cpu backend's own code (numba, numpy): on CUDA gsplat renders instead
CPU_RASTERIZER = tuple(f"avatar_core/render/{m}.py" for m in (
    "rasterize", "rasterize_cpu", "rasterize_torch", "budget", "project_cpu"))


class HostReads:
    """Counts reads of tensor values into Python (each a wait for the GPU on CUDA)."""

    METHODS = ("item", "tolist", "numpy", "__bool__", "__float__", "__int__", "__index__")

    def __init__(self, monkeypatch):
        self.count, self.paused, self.where = 0, 0, []
        for name in self.METHODS:
            original = getattr(torch.Tensor, name)
            monkeypatch.setattr(torch.Tensor, name, self._wrap(name, original))

    def _wrap(self, name, original):
        def counted(t, *args, **kwargs):
            stack = traceback.extract_stack()[:-1]
            if not self.paused and not any(f.filename.endswith(CPU_RASTERIZER)
                                           for f in stack):
                self.count += 1
                self.where.append(f"{name} at {stack[-1].filename}:{stack[-1].lineno}")
            return original(t, *args, **kwargs)
        return counted

    @contextlib.contextmanager
    def pause(self):
        self.paused += 1
        try:
            yield
        finally:
            self.paused -= 1


def test_the_device_path_reads_nothing_back_per_iteration(dataset, synthetic_files, tmp_path,
                                                          monkeypatch):
    """Every tensor op of the iteration but the cpu rasterizer's (gsplat on CUDA, masked
    without a budget: test_gpu_render) counted; the photometric loss takes the formulas it
    runs on CUDA. Without fine-tuning: with it, each frame goes through the body model, whose
    input validation (avatar_core/body/params.py) still reads every parameter's isfinite."""
    config = _config()
    config = dataclasses.replace(config, finetune=dataclasses.replace(config.finetune,
                                                                      enabled=False))
    tr = Trainer(dataset, config, tmp_path, body_model=synthetic_files.root,
                 device_resident=True)
    for _ in range(len(tr.views) + 1):
        tr.step()  # every view prepared and every frame posed once (data loading)
    monkeypatch.setattr(photometric, "_on_cpu", lambda t: False)
    reads = HostReads(monkeypatch)
    densify_at = tr.config.densify.interval
    done = 0
    while done < 4:
        if (tr.iteration + 1) % densify_at == 0:  # densification reads its counts: skip it
            with reads.pause():
                tr.step()
            continue
        tr.step()
        done += 1
    assert reads.count == 0, sorted(set(reads.where))


@pytest.mark.gpu
def test_500_iterations_on_cuda(dataset, synthetic_files, tmp_path):  # pragma: no cover
    pytest.importorskip("gsplat", reason="gsplat not installed (the cuda extra)")
    config = dataclasses.replace(preset("test"), iterations=500, device="cuda",
                                 checkpoint_interval=250)
    events = []
    tr = Trainer(dataset, config, tmp_path, body_model=synthetic_files.root,
                 progress=events.append)
    assert tr.tally is not None and tr.device.type == "cuda"
    package = tr.train()
    assert package is not None and tr.iteration == 500
    progress = [e for e in events if e["type"] == "progress"]
    assert progress[-1]["loss"] < progress[0]["loss"]
    assert all(math.isfinite(e["loss"]) for e in progress)
    assert tr.skipped == 0


@pytest.mark.gpu
def test_the_fused_photometric_loss_runs_on_cuda():  # pragma: no cover (needs CUDA)
    """The torch formulas on the device give the numba path's loss and gradient."""
    g = torch.Generator().manual_seed(0)
    pred = torch.rand(40, 56, 3, generator=g)
    target = torch.rand(40, 56, 3, generator=g)
    weight = (torch.rand(40, 56, generator=g) > 0.2).float()
    results = []
    for device in ("cpu", "cuda"):
        p = pred.clone().to(device).requires_grad_(True)
        loss = photometric.photometric_loss_fast(p, target.to(device), weight.to(device), 0.2)
        loss.backward()
        results.append((float(loss), p.grad.cpu()))
    assert results[1][0] == pytest.approx(results[0][0], rel=1e-4)
    assert torch.allclose(results[1][1], results[0][1], atol=1e-6, rtol=1e-3)
