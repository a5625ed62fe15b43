"""The studio rig: layout, intrinsics, jitter, and that every front camera sees the head."""

import math

import numpy as np
import pytest

from avatar_core.body.models import SMPLXModel
from avatar_core.body.upper_body import load_segmentation
from avatar_core.synth.studio import SENSOR_HEIGHT, StudioConfig, studio_rig


def test_rig_layout_follows_the_paper():
    rig = studio_rig(512)
    assert [c.name for c in rig] == [f"cam{i:02d}" for i in range(17)]
    assert [c.role for c in rig].count("front") == 15
    assert [c.role for c in rig].count("rear") == 2
    front = [c.camera.center for c in rig if c.role == "front"]
    azimuth = [math.degrees(math.atan2(p[0], p[2])) for p in front]
    assert np.all(np.diff(azimuth) > 0)  # ordered from the subject's right to left
    assert azimuth[-1] - azimuth[0] == pytest.approx(150.0, abs=2.0)
    heights = np.array([p[1] for p in front])
    assert heights.max() - heights.min() > 0.2  # head and chest rows
    assert front[7][1] == pytest.approx(StudioConfig().head_height, abs=0.03)  # centre: face
    for cam in (c for c in rig if c.role == "rear"):
        assert cam.camera.center[2] < -1.0  # behind the subject


def test_intrinsics_are_1080p_scaled_to_the_resolution():
    nominal = studio_rig(512, jitter=False)
    for res in (256, 512, 1080):
        rig = studio_rig(res, jitter=False)
        for a, b in zip(nominal, rig, strict=True):
            assert (b.camera.width, b.camera.height) == (res, res)
            assert b.camera.fx == pytest.approx(StudioConfig().focal_px * res / SENSOR_HEIGHT)
            assert b.camera.cx == pytest.approx(res / 2)
            np.testing.assert_allclose(a.camera.R, b.camera.R)
    full = studio_rig(540, StudioConfig(crop="full"), jitter=False)
    assert (full[0].camera.width, full[0].camera.height) == (960, 540)


def test_jitter_is_small_deterministic_and_per_camera():
    nominal, a, b = studio_rig(512, jitter=False), studio_rig(512, seed=3), studio_rig(512, seed=3)
    other = studio_rig(512, seed=4)
    moved = []
    for n, x, y, z in zip(nominal, a, b, other, strict=True):
        assert x.camera == y.camera
        assert not np.allclose(x.camera.R, z.camera.R)
        moved.append(np.linalg.norm(n.camera.center - x.camera.center))
        angle = np.arccos(np.clip((np.trace(n.camera.R @ x.camera.R.T) - 1) / 2, -1, 1))
        assert math.degrees(angle) < 2.0
        assert abs(x.camera.fx / n.camera.fx - 1) < 0.03
    assert 0.0 < np.mean(moved) < 0.03


def test_every_front_camera_sees_the_head(smplx_data, synthetic_files):
    model = SMPLXModel(smplx_data)
    verts = model({}).vertices[0].detach().numpy()
    seg = load_segmentation(synthetic_files.segmentation, smplx_data.num_vertices)
    head = verts[seg["head"]]  # [N, 3]
    for cam in studio_rig(256):
        uv, depth = cam.camera.project(head)
        inside = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < 256) & (uv[:, 1] >= 0) \
            & (uv[:, 1] < 256)
        assert inside.all(), f"{cam.name} cuts the head off"
        # ... and the head is not a speck: at least 1/12 of the frame high.
        assert np.ptp(uv[:, 1]) > 256 / 12


def test_bad_configs_are_refused():
    with pytest.raises(ValueError, match="crop"):
        StudioConfig(crop="wide")
    with pytest.raises(ValueError, match="at least one camera"):
        StudioConfig(num_cameras=0)
    with pytest.raises(ValueError, match="resolution"):
        studio_rig(4)


@pytest.mark.parametrize("n, front, rear", [(1, 1, 0), (3, 3, 0), (5, 4, 1), (17, 15, 2)])
def test_smaller_rigs(n, front, rear):
    rig = studio_rig(64, StudioConfig(num_cameras=n))
    assert [c.role for c in rig].count("front") == front
    assert [c.role for c in rig].count("rear") == rear
