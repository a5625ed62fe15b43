"""Metrics: SSIM / PSNR against scikit-image, masks, gradients, LPIPS gating, AKD and TJE."""

import logging
import math
import socket

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from avatar_core.body.models import SMPLXModel
from avatar_core.body.upper_body import UpperBodyModel
from avatar_core.metrics import (
    akd,
    body_akd,
    body_keypoints,
    dssim_loss,
    keypoint_groups,
    keypoint_tje,
    l1,
    lpips_metric,
    perceptual,
    photometric_loss,
    project_keypoints,
    psnr,
    ssim,
    ssim_map,
    tje,
)
from avatar_core.metrics.image import gaussian_kernel
from avatar_core.metrics.keypoints import FINGERTIP_VERTICES
from avatar_core.render.camera import Camera, orbit
from avatar_core.synth.model_writer import SMPLX_SEMANTIC_VERTEX_IDS

try:  # the reference implementation (dev extra); the other tests run without it
    import skimage.metrics as skm
except ImportError:
    skm = None
needs_skimage = pytest.mark.skipif(skm is None, reason="scikit-image is not installed")

SKIMAGE_SSIM = dict(gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                    data_range=1.0, channel_axis=-1)


def _random_pair(seed, shape=(40, 37, 3), noise=0.1):
    rng = np.random.default_rng(seed)
    a = rng.random(shape)
    return a, np.clip(a + rng.normal(0.0, noise, shape), 0.0, 1.0)


def _structured_pair(h=48, w=64):
    """Ramp, checkerboard, a flat block (zero variance) and a disc; target blurred + shifted."""
    y, x = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    checker = ((np.arange(h)[:, None] // 4 + np.arange(w)[None] // 4) % 2).astype(float)
    disc = ((x - 0.7) ** 2 + (y - 0.4) ** 2 < 0.04).astype(float)
    a = np.stack([x, 0.2 + 0.6 * checker, 0.5 * disc + 0.3], axis=-1)
    a[30:, :20] = 0.8  # flat block
    b = np.roll(a, 1, axis=1) * 0.9 + 0.05
    return a, b


def _skimage_ssim(a, b):
    return skm.structural_similarity(a, b, **SKIMAGE_SSIM)


# -- SSIM / PSNR / L1 against references -------------------------------------------------------


@needs_skimage
@pytest.mark.parametrize("pair", [_random_pair(0), _random_pair(1, (11, 11, 3), 0.3),
                                  _structured_pair()], ids=["random", "tiny", "structured"])
def test_ssim_matches_skimage(pair):
    a, b = pair
    ref = _skimage_ssim(a, b)
    assert float(ssim(a, b)) == pytest.approx(ref, abs=1e-4)
    # float32 tensors as a training loop passes them.
    got32 = ssim(torch.as_tensor(a, dtype=torch.float32), torch.as_tensor(b, dtype=torch.float32))
    assert got32.dtype == torch.float32
    assert float(got32) == pytest.approx(ref, abs=1e-4)


@needs_skimage
def test_ssim_map_is_skimage_map_cropped():
    a, b = _structured_pair()
    _, full = skm.structural_similarity(a, b, full=True, **SKIMAGE_SSIM)
    ref = full.mean(axis=-1)[5:-5, 5:-5]  # skimage's map, channel mean, valid region
    got = ssim_map(a, b).numpy()
    assert got.shape == (38, 54)
    np.testing.assert_allclose(got, ref, atol=1e-10)


@needs_skimage
def test_ssim_batch_is_per_image_mean():
    pairs = [_random_pair(s, (24, 20, 3), n) for s, n in ((2, 0.05), (3, 0.2), (4, 0.4))]
    a = np.stack([p[0] for p in pairs])
    b = np.stack([p[1] for p in pairs])
    refs = np.array([_skimage_ssim(x, y) for x, y in pairs])
    np.testing.assert_allclose(ssim(a, b, reduction="none").numpy(), refs, atol=1e-4)
    assert float(ssim(a, b)) == pytest.approx(refs.mean(), abs=1e-4)


@needs_skimage
def test_masked_ssim_full_mask_equals_skimage_and_partial_mask_weights_the_map():
    a, b = _structured_pair()
    ref = _skimage_ssim(a, b)
    h, w = a.shape[:2]
    assert float(ssim(a, b, np.ones((h, w), bool))) == pytest.approx(ref, abs=1e-4)
    assert float(ssim(a, b, torch.full((h, w), 0.3))) == pytest.approx(ref, abs=1e-4)
    # A partial mask: mean of skimage's (cropped) map over the mask's cropped pixels.
    mask = np.zeros((h, w), bool)
    mask[10:40, 8:30] = True
    _, full = skm.structural_similarity(a, b, full=True, **SKIMAGE_SSIM)
    smap, m = full.mean(axis=-1)[5:-5, 5:-5], mask[5:-5, 5:-5]
    assert float(ssim(a, b, mask)) == pytest.approx(smap[m].mean(), abs=1e-4)
    assert float(ssim(a, b, mask)) != pytest.approx(ref, abs=1e-3)


def _ssim_3dgs(img1, img2):
    """3DGS's utils/loss_utils.ssim (zero-padded 2-D window), on [1, C, H, W]."""
    c = img1.shape[1]
    g = gaussian_kernel(dtype=img1.dtype)
    window = (g[:, None] @ g[None, :]).expand(c, 1, 11, 11).contiguous()

    def conv(x):
        return F.conv2d(x, window, padding=5, groups=c)

    mu1, mu2 = conv(img1), conv(img2)
    s1, s2 = conv(img1 * img1) - mu1**2, conv(img2 * img2) - mu2**2
    s12 = conv(img1 * img2) - mu1 * mu2
    c1, c2 = 0.01**2, 0.03**2
    smap = ((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1**2 + mu2**2 + c1) * (s1 + s2 + c2))
    return smap.mean()


def test_same_padding_matches_3dgs_reference():
    a, b = _random_pair(5, (20, 26, 3))
    ta, tb = torch.as_tensor(a), torch.as_tensor(b)
    ref = _ssim_3dgs(ta.permute(2, 0, 1)[None], tb.permute(2, 0, 1)[None])
    assert float(ssim(ta, tb, padding="same")) == pytest.approx(float(ref), abs=1e-10)
    assert ssim_map(ta, tb, padding="same").shape == (20, 26)
    # Zero padding lowers the border windows: the two conventions really differ.
    assert float(ssim(ta, tb, padding="same")) != pytest.approx(float(ssim(ta, tb)), abs=1e-3)


@needs_skimage
@pytest.mark.parametrize("pair", [_random_pair(6), _structured_pair()],
                         ids=["random", "structured"])
def test_psnr_and_l1_match_references(pair):
    a, b = pair
    ref = skm.peak_signal_noise_ratio(a, b, data_range=1.0)
    assert float(psnr(a, b)) == pytest.approx(ref, abs=1e-4)
    assert float(psnr(a.astype(np.float32), b.astype(np.float32))) == pytest.approx(ref, abs=1e-4)
    assert float(l1(a, b)) == pytest.approx(np.abs(a - b).mean(), abs=1e-12)


@needs_skimage
def test_masked_psnr_and_l1_use_only_masked_pixels():
    a, b = _random_pair(7, (16, 18, 3))
    mask = np.zeros((16, 18), bool)
    mask[3:9, 2:15] = True
    b_changed = b.copy()
    b_changed[~mask] = 1.0 - b_changed[~mask]  # outside the mask: must not matter
    ref = skm.peak_signal_noise_ratio(a[mask], b[mask], data_range=1.0)
    for target in (b, b_changed):
        assert float(psnr(a, target, mask)) == pytest.approx(ref, abs=1e-4)
        assert float(l1(a, target, mask)) == pytest.approx(np.abs(a - b)[mask].mean(), abs=1e-12)
    # Float weights: a weighted mean (weight 2 counts a pixel twice).
    w = mask * 1.0
    w[3, 2] = 2.0
    err = np.abs(a - b).mean(axis=-1)
    assert float(l1(a, b, w)) == pytest.approx((err * w).sum() / w.sum(), abs=1e-12)


@needs_skimage
def test_identical_images_psnr_inf_ssim_one():
    a, _ = _random_pair(8, (16, 16, 3))
    assert float(psnr(a, a)) == math.inf
    assert float(ssim(a, a)) == pytest.approx(1.0, abs=1e-12)
    assert float(l1(a, a)) == 0.0
    flat = np.full((16, 16, 3), 0.5)
    assert float(ssim(flat, flat)) == pytest.approx(_skimage_ssim(flat, flat), abs=1e-6)


def test_photometric_loss_is_3dgs_combination():
    a, b = _random_pair(9, (16, 16, 3))
    s, e = float(ssim(a, b)), float(l1(a, b))
    assert float(dssim_loss(a, b)) == pytest.approx((1 - s) / 2, abs=1e-12)
    assert float(photometric_loss(a, b)) == pytest.approx(0.8 * e + 0.2 * (1 - s), abs=1e-12)
    with pytest.raises(ValueError, match="lambda_dssim"):
        photometric_loss(a, b, lambda_dssim=1.5)


# -- gradients and edge cases ------------------------------------------------------------------


def test_ssim_gradcheck_float64():
    gen = torch.Generator().manual_seed(0)
    a = torch.rand(1, 12, 13, 2, dtype=torch.float64, generator=gen, requires_grad=True)
    b = torch.rand(1, 12, 13, 2, dtype=torch.float64, generator=gen)
    mask = torch.rand(12, 13, dtype=torch.float64, generator=gen)
    assert torch.autograd.gradcheck(lambda x: ssim(x, b), (a,))
    assert torch.autograd.gradcheck(lambda x: ssim(x, b, mask, padding="same"), (a,))


def test_gradients_finite_for_constant_images_and_empty_masks():
    const = torch.full((2, 16, 16, 3), 0.25, requires_grad=True)
    target = torch.full((2, 16, 16, 3), 0.25)
    for loss_fn in (ssim, dssim_loss, l1, photometric_loss):
        (grad,) = torch.autograd.grad(loss_fn(const, target), const)
        assert torch.isfinite(grad).all(), loss_fn.__name__

    x = torch.rand(16, 16, 3, requires_grad=True)
    empty = torch.zeros(16, 16)
    for metric in (ssim, l1, psnr):
        value = metric(x, torch.rand(16, 16, 3), empty)
        assert torch.isnan(value)
        (grad,) = torch.autograd.grad(value, x)
        assert torch.equal(grad, torch.zeros_like(grad)), metric.__name__


@needs_skimage
def test_empty_mask_image_is_skipped_in_the_batch_mean():
    a, b = _random_pair(10, (2, 16, 16, 3))
    mask = np.ones((2, 16, 16), bool)
    mask[1] = False
    per = l1(a, b, mask, reduction="none")
    assert torch.isnan(per[1]) and not torch.isnan(per[0])
    assert float(l1(a, b, mask)) == pytest.approx(float(per[0]))
    assert float(ssim(a, b, mask)) == pytest.approx(_skimage_ssim(a[0], b[0]), abs=1e-4)


def test_bad_inputs_raise_naming_the_argument():
    a, b = _random_pair(11, (16, 16, 3))
    bad = a.copy()
    bad[3, 4, 1] = np.nan
    for metric in (l1, psnr, ssim):
        with pytest.raises(ValueError, match="'pred' contains NaN or Inf"):
            metric(bad, b)
        with pytest.raises(ValueError, match="'target' contains NaN or Inf"):
            metric(a, np.where(bad > 0.5, np.inf, b))
        with pytest.raises(ValueError, match="same shape"):
            metric(a, b[:15])
        with pytest.raises(ValueError, match="'mask' must have shape"):
            metric(a, b, np.ones((15, 16)))
    with pytest.raises(ValueError, match="'mask' contains NaN"):
        ssim(a, b, np.full((16, 16), np.nan))
    with pytest.raises(ValueError, match="negative"):
        l1(a, b, -np.ones((16, 16)))
    with pytest.raises(ValueError, match="float image"):
        psnr((a * 255).astype(np.uint8), b)
    with pytest.raises(ValueError, match="at least 11 x 11"):
        ssim(a[:10], b[:10])
    assert ssim(a[:10], b[:10], padding="same").shape == ()


# -- LPIPS -------------------------------------------------------------------------------------


@pytest.fixture
def no_network(monkeypatch, tmp_path):
    """Any connection attempt fails the test; the torch hub cache is an empty directory."""
    def refuse(*args, **kwargs):
        raise AssertionError("network access attempted")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    return tmp_path


def test_lpips_off_here_with_one_log_line(no_network, caplog):
    with caplog.at_level(logging.WARNING, logger=perceptual.__name__):
        assert lpips_metric() is None
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and lines[0].startswith("LPIPS off: ")
    assert lines[0] == f"LPIPS off: {perceptual.lpips_unavailable_reason()}"


def test_lpips_reasons(no_network, monkeypatch, caplog):
    monkeypatch.setattr(perceptual, "_module_available", lambda name: False)
    assert "'lpips' package is not installed" in perceptual.lpips_unavailable_reason()
    # Package and torchvision present, linear heads shipped, backbone not cached.
    heads = no_network / "heads" / "alex.pth"
    heads.parent.mkdir()
    heads.write_bytes(b"")
    monkeypatch.setattr(perceptual, "_module_available", lambda name: True)
    monkeypatch.setattr(perceptual, "_lpips_heads_file", lambda net: heads)
    reason = perceptual.lpips_unavailable_reason("alex")
    assert "alexnet-owt-7be5be79.pth" in reason and "not cached" in reason
    with caplog.at_level(logging.WARNING, logger=perceptual.__name__):
        assert lpips_metric("alex") is None
    assert "LPIPS off: backbone weights" in caplog.text
    with pytest.raises(ValueError, match="net must be one of"):
        perceptual.lpips_unavailable_reason("resnet")


# -- AKD -----------------------------------------------------------------------------------------


def test_akd_hand_computed():
    gt = torch.tensor([[0.0, 0.0], [10.0, 10.0], [5.0, 5.0], [1.0, 1.0]])
    pred = torch.tensor([[3.0, 4.0], [10.0, 10.0], [5.0, 17.0], [np.nan, np.nan]])
    visible = torch.tensor([True, True, True, False])
    assert akd(pred, gt, visible) == pytest.approx((5 + 0 + 12) / 3)
    assert akd(pred[None], gt[None], visible[None]) == pytest.approx(17 / 3)  # batched
    assert akd(pred[:3], gt[:3]) == pytest.approx(17 / 3)  # all visible by default
    assert math.isnan(akd(pred, gt, torch.zeros(4, dtype=torch.bool)))
    with pytest.raises(ValueError, match="'pred_2d' contains NaN"):
        akd(pred, gt)
    with pytest.raises(ValueError, match="same shape"):
        akd(pred[:3], gt)
    with pytest.raises(ValueError, match="'visible' must have shape"):
        akd(pred, gt, visible[:3])


def test_project_keypoints_visibility():
    cam = Camera(K=[[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]], R=np.eye(3), t=[0, 0, 0],
                 width=64, height=48)
    pts = torch.tensor([[[0.0, 0.0, 2.0],      # optical axis -> principal point
                         [0.2, -0.1, 1.0],     # (32 + 20, 24 - 10)
                         [1.0, 0.0, 1.0],      # u = 132: outside the image
                         [0.0, 0.0, -1.0]]])   # behind the camera
    uv, vis = project_keypoints(pts, cam)
    assert uv.shape == (1, 4, 2) and vis.shape == (1, 4)
    torch.testing.assert_close(uv[0, :3], torch.tensor([[32.0, 24.0], [52.0, 14.0],
                                                        [132.0, 24.0]]))
    assert torch.isnan(uv[0, 3]).all()
    assert vis.tolist() == [[True, True, False, False]]
    with pytest.raises(ValueError, match="'points' contains NaN"):
        project_keypoints(torch.full((1, 1, 3), np.nan), cam)


def test_keypoint_groups_membership():
    groups = keypoint_groups()
    assert {k: len(v) for k, v in groups.items()} == {"face": 51, "hands": 32, "torso": 12}
    assert "pelvis" not in groups["torso"] and "left_wrist" in groups["torso"]
    assert groups["hands"][0] == "left_wrist" and groups["hands"][16] == "right_wrist"
    assert len(keypoint_groups(fingertips=True, num_landmarks=68)["hands"]) == 42
    # The fingertip vertices are smplx's (the synthetic files place them there too).
    side = {"left": "l", "right": "r"}
    for name, vid in FINGERTIP_VERTICES.items():
        s, finger, _ = name.split("_")
        assert SMPLX_SEMANTIC_VERTEX_IDS[side[s] + finger] == vid


@pytest.fixture(scope="module")
def smplx_model(smplx_data):
    return SMPLXModel(smplx_data, dtype=torch.float64)


def _front_camera(output):
    target = output.joints[0, 12].numpy()  # the neck
    return orbit(target, 0.0, 0.0, 2.5, width=320, height=320, fov_y_deg=40.0)


def test_body_akd_on_synthetic_body(smplx_model):
    out = smplx_model({"transl": np.zeros((1, 3))})
    kps = body_keypoints(out, fingertips=True)
    groups = keypoint_groups(num_landmarks=out.landmarks.shape[1], fingertips=True)
    assert {g: t.shape for g, t in kps.items()} == {g: (1, len(n), 3) for g, n in groups.items()}
    cam = _front_camera(out)
    for group, pts in kps.items():
        assert project_keypoints(pts, cam)[1].all(), group  # the whole upper body is in view
    assert body_akd(out, out, cam, fingertips=True) == {"face": 0.0, "hands": 0.0, "torso": 0.0}

    # Shift the body 1 cm sideways: each keypoint moves fx * d / depth pixels.
    d = 0.01
    moved = smplx_model({"transl": np.array([[d, 0.0, 0.0]])})
    scores = body_akd(moved, out, cam, fingertips=True)
    for group, pts in kps.items():
        depth = cam.center[2] - pts[0, :, 2].numpy()  # the camera looks down -z
        assert scores[group] == pytest.approx(np.mean(cam.fx * d / depth), rel=1e-6), group
    assert 0.0 < scores["torso"] < 2.0


def test_fingertips_of_a_cut_mesh_need_vertex_ids(smplx_data, segmentation, smplx_model):
    params = {"right_hand_pose": np.full((1, 15, 3), 0.2)}
    full = body_keypoints(smplx_model(params), fingertips=True)
    upper = UpperBodyModel(smplx_data, segmentation, dtype=torch.float64)
    out = upper(params)
    cut = body_keypoints(out, fingertips=True, vertex_ids=upper.vertex_ids)
    torch.testing.assert_close(cut["hands"], full["hands"])
    with pytest.raises(ValueError, match="vertex_ids has"):
        body_keypoints(out, fingertips=True, vertex_ids=upper.vertex_ids[:-1])
    assert "face" in body_keypoints(out) and len(body_keypoints(out)["hands"][0]) == 32


# -- TJE -----------------------------------------------------------------------------------------


def _sequence(t=5, h=12, w=10, seed=0):
    rng = np.random.default_rng(seed)
    return torch.as_tensor(0.1 + 0.8 * rng.random((t, h, w, 3)))  # [T, H, W, 3] in [0.1, 0.9]


def test_tje_offset_cancels_flicker_does_not():
    gt = _sequence()
    assert float(tje(gt, gt)) == 0.0
    assert float(tje(gt + 0.05, gt)) == pytest.approx(0.0, abs=1e-12)  # constant offset
    sign = torch.tensor([1.0, -1.0, 1.0, -1.0, 1.0], dtype=gt.dtype)[:, None, None, None]
    flicker = gt + 0.05 * sign
    assert float(tje(flicker, gt)) == pytest.approx(0.1, abs=1e-12)  # |+-2a| every pair
    # Flicker only inside a region: the masked TJE sees it at full strength.
    region = torch.zeros(12, 10, dtype=torch.bool)
    region[2:6, 3:8] = True
    local = gt + 0.05 * sign * region[None, :, :, None]
    assert float(tje(local, gt, region)) == pytest.approx(0.1, abs=1e-12)
    assert float(tje(local, gt)) == pytest.approx(0.1 * 20 / 120, abs=1e-12)


def test_tje_per_frame_masks_use_the_union_of_each_pair():
    gt = _sequence(t=3)
    pred = gt.clone()
    pred[1, 0, 0] += 0.3  # frame 1, pixel (0, 0): both pairs see a 0.3 jump
    masks = torch.zeros(3, 12, 10, dtype=torch.bool)
    masks[0, 0, 0] = True  # pair (0, 1) covers (0, 0) through frame 0
    masks[2, 0, :2] = True  # pair (1, 2) covers (0, 0) and (0, 1)
    assert float(tje(pred, gt, masks)) == pytest.approx((0.3 + 0.3 / 2) / 2, abs=1e-12)
    empty_pair = torch.zeros(3, 12, 10, dtype=torch.bool)
    empty_pair[2, 0, 0] = True  # only pair (1, 2) is defined
    assert float(tje(pred, gt, empty_pair)) == pytest.approx(0.3, abs=1e-12)
    assert torch.isnan(tje(pred, gt, torch.zeros(12, 10)))


def test_tje_is_differentiable_and_checks_inputs():
    gt = _sequence(t=3)
    pred = gt.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(tje(pred, gt), pred)
    assert torch.isfinite(grad).all()
    with pytest.raises(ValueError, match="at least 2 frames, got T=1"):
        tje(gt[:1], gt[:1])
    with pytest.raises(ValueError, match=r"\[T, H, W, C\]"):
        tje(gt[0], gt[0])
    bad = gt.clone()
    bad[1, 2, 3, 0] = np.inf
    with pytest.raises(ValueError, match="'gt' contains NaN or Inf"):
        tje(gt, bad)
    with pytest.raises(ValueError, match="same shape"):
        tje(gt, gt[:2])


def test_keypoint_tje():
    rng = np.random.default_rng(1)
    gt = torch.as_tensor(rng.normal(100.0, 20.0, (4, 6, 2)))  # [T, K, 2] pixels
    assert keypoint_tje(gt, gt) == 0.0
    assert keypoint_tje(gt + torch.tensor([3.0, -2.0]), gt) == pytest.approx(0.0, abs=1e-12)
    sign = torch.tensor([1.0, -1.0, 1.0, -1.0], dtype=gt.dtype)[:, None, None]
    flicker = gt + 0.5 * sign  # +-0.5 px on both axes: each step jumps (1, 1)
    assert keypoint_tje(flicker, gt) == pytest.approx(math.sqrt(2.0), abs=1e-12)
    # Keypoint 0 hidden in frame 1: pairs (0, 1) and (1, 2) skip it; it may hold NaN there.
    visible = torch.ones(4, 6, dtype=torch.bool)
    visible[1, 0] = False
    pred = gt.clone()
    pred[1, 0] = np.nan
    pred[3, 0] += torch.tensor([3.0, 4.0])  # only pair (2, 3) of keypoint 0 jitters: 5 px
    assert keypoint_tje(pred, gt, visible) == pytest.approx(5.0 / 16)  # 16 counted pairs
    with pytest.raises(ValueError, match="'pred' contains NaN"):
        keypoint_tje(pred, gt)
    with pytest.raises(ValueError, match="at least 2 frames"):
        keypoint_tje(gt[:1], gt[:1])
