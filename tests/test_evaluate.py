"""Evaluation of avatars (`avatar_core.metrics.evaluate`) on a tiny synthetic capture."""

import json
import math
import shutil

import cv2
import numpy as np
import pytest

from avatar_core.body.model_paths import BodyModelFiles
from avatar_core.cli import main
from avatar_core.dataset import load_dataset
from avatar_core.gaussians.animate import AvatarAnimator, synthetic_package
from avatar_core.gaussians.loading import LoadedAvatar
from avatar_core.gaussians.package import save_package
from avatar_core.metrics.evaluate import (
    blank_excluded,
    estimate_background,
    evaluate,
    evaluation_mask,
)
from avatar_core.metrics.report import (
    ABLATION_COLUMNS,
    METRIC_KEYS,
    ablation_json,
    ablation_table,
    load_result,
    side_by_side,
)
from avatar_core.synth.capture import CaptureSpec, capture

FRAMES, CAMERAS = 3, 5
IMAGE_METRICS = ("l1", "psnr", "ssim")
AKD = ("akd_face", "akd_hands", "akd_torso")


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory, synthetic_files):
    out = tmp_path_factory.mktemp("eval") / "ds"
    spec = CaptureSpec(sequences=(("smile",), ("nod",)), num_cameras=CAMERAS, resolution=48,
                       max_frames=FRAMES, supersample=1, cross_identity=1)
    return capture(out, spec, model_dir=synthetic_files.root)


def _loaded(files, identity=0):
    package, model = synthetic_package(files.root, identity)
    animator = AvatarAnimator(model, package.avatar, betas=np.asarray(package.body.betas))
    return LoadedAvatar(package, animator, BodyModelFiles(files.root))


@pytest.fixture(scope="module")
def avatar(synthetic_files):
    return _loaded(synthetic_files)


@pytest.fixture(scope="module")
def self_fused(avatar, dataset_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("self_fused")
    return evaluate(avatar, dataset_dir, "self-reenactment", out_dir=out), out


def _copy(dataset_dir, tmp_path):
    return shutil.copytree(dataset_dir, tmp_path / "copy")


@pytest.mark.parametrize("protocol", ["novel-view", "self-reenactment"])
def test_image_protocols_give_finite_metrics_and_files(avatar, dataset_dir, tmp_path,
                                                       protocol):
    ds = load_dataset(dataset_dir)
    split = ds.splits[protocol.replace("-", "_")]
    r = evaluate(avatar, ds, protocol, out_dir=tmp_path)
    assert r.num_views == len(split.sequences) * FRAMES * len(split.cameras)
    assert r.num_gaussians == avatar.package.avatar.num > 0
    assert r.image_size == [48, 48] and set(r.metrics) == set(METRIC_KEYS)
    for key in (*IMAGE_METRICS, *AKD, "tje"):
        assert math.isfinite(r.metrics[key]), key
    assert 0 < r.metrics["l1"] < 1 and 0 < r.metrics["ssim"] < 1 and r.metrics["psnr"] > 5
    assert r.metrics["csim"] is None and "face-identity" in r.notes["csim"]
    if r.metrics["lpips"] is None:
        assert r.notes["lpips"].startswith("LPIPS off")
    assert list(r.per_camera) == list(split.cameras)
    assert all(row["views"] == FRAMES * len(split.sequences) for row in r.per_camera.values())
    assert all(t > 0 for t in (r.timing["render_ms_median"], r.timing["pose_ms_mean"]))
    assert len(r.views) == r.num_views and r.fused and not r.warnings

    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["metrics"] == pytest.approx(r.to_dict()["metrics"])
    assert load_result(tmp_path).metrics == saved["metrics"]
    md = (tmp_path / "metrics.md").read_text()
    assert "| PSNR (dB) |" in md and "LPIPS" in md and "## Per camera" in md
    # First frame of each sequence x each camera: [GT | render | error], 48 px zoomed to 144.
    assert len(r.images) == len(split.sequences) * len(split.cameras)
    img = cv2.imread(str(tmp_path / r.images[0]))
    assert img.shape == (144, 3 * 144 + 2 * 2, 3)
    assert all(f"]({p})" in md for p in r.images)


def test_cross_identity_scores_keypoints_only(avatar, dataset_dir, tmp_path):
    ds = load_dataset(dataset_dir)
    split = ds.splits["cross_identity"]
    r = evaluate(avatar, ds, "cross-identity", out_dir=tmp_path)
    assert r.num_views == FRAMES * len(split.cameras)
    for key in (*IMAGE_METRICS, "lpips", "tje"):
        assert r.metrics[key] is None and "no ground-truth image" in r.notes[key]
    # The avatar's own (ada's) body moved by bo's motion: keypoints differ from bo's.
    for key in AKD:
        assert math.isfinite(r.metrics[key]) and r.metrics[key] > 0, key
    assert not r.warnings  # the betas differ on purpose: no warning
    img = cv2.imread(str(tmp_path / r.images[0]))
    assert img.shape == (144, 2 * 144 + 2, 3)  # [driver | avatar], no error map
    json.loads((tmp_path / "metrics.json").read_text())  # strict JSON (nulls, no NaN)


def test_no_fusion_drives_with_the_body_tracker_alone(avatar, dataset_dir, self_fused):
    fused, _ = self_fused
    raw = evaluate(avatar, dataset_dir, "self-reenactment", fusion=False)
    # With fusion the avatar is driven by the true parameters: keypoints match exactly.
    assert fused.fused and fused.metrics["akd_face"] == fused.metrics["akd_hands"] == 0.0
    # The body tracker has no expression/jaw, 6-PCA hands and a noisy neck and wrists.
    assert not raw.fused and not raw.fusion
    assert raw.metrics["akd_face"] > 0.01 and raw.metrics["akd_hands"] > 0.01
    assert raw.metrics["l1"] != fused.metrics["l1"]


def test_lower_body_pixels_are_not_scored(avatar, dataset_dir, self_fused, tmp_path):
    fused, _ = self_fused
    ds = load_dataset(_copy(dataset_dir, tmp_path))
    rng = np.random.default_rng(0)
    changed = 0
    for key in ds.views("self_reenactment"):
        view = ds.view(*key)
        lower = ~evaluation_mask(view)
        changed += int(lower.sum())
        rgb = np.where(lower[..., None], rng.integers(0, 256, view.rgb.shape),
                       np.round(view.rgb * 255)).astype(np.uint8)
        path = ds.root / "sequences" / key.sequence / "images" / key.camera / \
            f"{key.frame:05d}.png"
        cv2.imwrite(str(path), rgb[..., ::-1])
    assert changed > 100  # the cameras do see legs and hips
    garbage = evaluate(avatar, ds, "self-reenactment")
    for key in (*IMAGE_METRICS, *AKD, "tje"):
        assert garbage.metrics[key] == pytest.approx(fused.metrics[key], rel=1e-6, abs=1e-9)


def test_blanking_and_background_helpers(dataset_dir):
    ds = load_dataset(dataset_dir)
    view = ds.view(*ds.views("self_reenactment")[0])
    keep = evaluation_mask(view)
    assert keep[view.parts < 0].all() and keep[view.upper_body_mask].all()
    assert not keep.all()
    assert estimate_background(view) == (1.0, 1.0, 1.0)  # the studio's white
    blank = blank_excluded(view.rgb, keep, (0.5, 0.25, 0.0))
    np.testing.assert_array_equal(blank[keep], view.rgb[keep])
    np.testing.assert_array_equal(blank[~keep], np.tile([0.5, 0.25, 0.0], ((~keep).sum(), 1)))
    sbs = side_by_side(view.rgb, view.rgb, keep, min_height=48)
    assert sbs.shape == (48, 3 * 48 + 4, 3) and sbs.dtype == np.uint8


def test_stride_and_view_cap(avatar, dataset_dir):
    r = evaluate(avatar, dataset_dir, "self-reenactment", frame_stride=2, max_views=7)
    assert r.num_views == 7 and r.frame_stride == 2
    assert {v["frame"] for v in r.views} == {0, 2}
    # TJE pairs frames 0 and 2 of the two cameras that have both.
    assert math.isfinite(r.metrics["tje"])
    assert sum(row["tje"] is not None for row in r.per_camera.values()) == 2
    single = evaluate(avatar, dataset_dir, "novel-view", max_views=1)
    assert single.metrics["tje"] is None and "null" in single.notes["tje"]


def test_other_subjects_betas_are_warned_about(synthetic_files, dataset_dir):
    other = _loaded(synthetic_files, identity=1)
    with pytest.warns(UserWarning, match="betas differ"):
        r = evaluate(other, dataset_dir, "novel-view", max_views=1)
    assert any("betas differ" in w for w in r.warnings)


def test_ablation_table_merges_runs(avatar, dataset_dir, self_fused):
    fused, _ = self_fused
    runs = {
        "full": {"self-reenactment": fused,
                 "cross-identity": evaluate(avatar, dataset_dir, "cross-identity",
                                            max_views=2)},
        "no fusion": {"self-reenactment": evaluate(avatar, dataset_dir, "self-reenactment",
                                                   fusion=False, max_views=5)},
    }
    md = ablation_table(runs).strip().splitlines()
    assert len(md) == 2 + 2
    header = [c.strip() for c in md[0].strip("|").split("|")]
    assert header[0] == "model" and len(header) == 1 + 2 * len(ABLATION_COLUMNS)
    assert header[1] == "self-reenactment L1" and header[-1] == "cross-identity AKD hands (px)"
    full = [c.strip() for c in md[2].strip("|").split("|")]
    assert full[0] == "full" and full[1] == f"{fused.metrics['l1']:.4f}"
    assert full[7:10] == ["n/a"] * 3  # cross-identity has no image metrics
    no_fusion = [c.strip() for c in md[3].strip("|").split("|")]
    assert no_fusion[7:] == ["-"] * len(ABLATION_COLUMNS)  # not run
    js = ablation_json(runs)
    json.dumps(js, allow_nan=False)
    assert js["rows"]["no fusion"]["self-reenactment"]["akd_hands"] > 0
    assert js["rows"]["full"]["cross-identity"]["l1"] is None
    with pytest.raises(ValueError, match="no results"):
        ablation_table({})


def test_cli_eval_writes_the_report(synthetic_files, dataset_dir, avatar, tmp_path, capsys):
    pkg = save_package(avatar.package, tmp_path / "avatar")
    out = tmp_path / "eval"
    assert main(["eval", str(pkg), str(dataset_dir), "--protocol", "novel-view", "--out",
                 str(out), "--models", str(synthetic_files.root), "--max-views", "2",
                 "--no-fusion", "--frame-stride", "2"]) == 0
    result = load_result(out)
    assert result.num_views == 2 and not result.fusion and result.frame_stride == 2
    assert (out / "metrics.md").is_file() and (out / result.images[0]).is_file()
    assert "| L1 |" in capsys.readouterr().out


def test_unknown_protocol_and_missing_split_are_clear_errors(avatar, synthetic_files,
                                                             dataset_dir, tmp_path, capsys):
    with pytest.raises(ValueError, match="unknown protocol 'novel_view'"):
        evaluate(avatar, dataset_dir, "novel_view")
    copy = _copy(dataset_dir, tmp_path)
    splits = json.loads((copy / "splits.json").read_text())
    del splits["cross_identity"]
    (copy / "splits.json").write_text(json.dumps(splits))
    with pytest.raises(ValueError, match="no 'cross_identity' split"):
        evaluate(avatar, copy, "cross-identity")
    assert main(["eval", "synthetic", str(copy), "--protocol", "cross-identity", "--models",
                 str(synthetic_files.root)]) == 2
    assert "no 'cross_identity' split" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["eval", "synthetic", str(copy), "--protocol", "bogus"])


def test_a_render_budget_costs_accuracy(avatar, dataset_dir):
    full = evaluate(avatar, dataset_dir, "novel-view", max_views=2)
    few = evaluate(avatar, dataset_dir, "novel-view", max_views=2, budget=0.1)
    assert math.isfinite(few.metrics["psnr"])
    assert few.metrics["psnr"] < full.metrics["psnr"] - 1.0  # a tenth of the splats is visible
