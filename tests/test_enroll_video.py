"""Enrollment videos (avatar_core/enroll/video.py): real small files written by PyAV in the
test, probed and decoded; every refusal says what to do and comes before the work it
guards."""

from __future__ import annotations

import numpy as np
import pytest

from avatar_core.enroll import EnrollmentRefused
from avatar_core.enroll.video import VideoLimits, output_size, probe_video, read_video

from .enroll_videos import truncate, write_audio_only, write_garbage, write_video

APPLE_FOCAL = "com.apple.quicktime.camera.focal_length.35mm_equivalent"


def refused(reason: str, call, *args, **kwargs) -> EnrollmentRefused:
    with pytest.raises(EnrollmentRefused) as info:
        call(*args, **kwargs)
    assert info.value.reason == reason, info.value.to_dict()
    assert info.value.what_to_do and info.value.message
    return info.value


@pytest.mark.parametrize("suffix", [".mp4", ".webm"])
def test_a_video_decodes_to_its_frames_in_order(tmp_path, suffix):
    path = write_video(tmp_path / f"clip{suffix}", seconds=4, fps=10)
    info = probe_video(path)
    assert (info.width, info.height, info.packets, info.rotation) == (160, 120, 40, 0)
    assert info.duration_s == pytest.approx(4.0, abs=0.11) and info.fps == pytest.approx(10, 0.03)
    video = read_video(path)
    assert video.frames.shape == (40, 120, 160, 3) and video.frames.dtype == np.uint8
    assert video.fps == pytest.approx(10.0, rel=0.01) and video.focal_px is None
    np.testing.assert_allclose(np.diff(video.times_s), 0.1, atol=0.002)
    # The pattern's white quadrant is top-left; its red bar moves 4 px a frame.
    assert video.frames[:, 5, 5].min() > 230 and video.frames[:, 100, 150].max() < 60
    bars = [int(np.argmax(f[-4, :, 0].astype(int) - f[-4, :, 1])) for f in video.frames[:5]]
    assert np.all(np.diff(bars) > 0), bars


def test_large_videos_are_downscaled_and_capped_in_frame_rate(tmp_path):
    path = write_video(tmp_path / "hd.mp4", seconds=3, fps=30, width=1280, height=720)
    video = read_video(path, VideoLimits(max_decode_fps=15), long_side=512)
    assert video.size == (512, 288) == output_size(1280, 720, 512)
    assert len(video.frames) == 45 and video.fps == pytest.approx(15.0, rel=0.01)
    assert output_size(320, 240, 512) == (320, 240)  # never upscaled


def test_a_rotated_phone_video_comes_out_upright(tmp_path):
    plain = read_video(write_video(tmp_path / "plain.mp4", seconds=3)).frames[0]
    turned = read_video(write_video(tmp_path / "turned.mp4", seconds=3, rotation=90))
    assert turned.rotation == 90 and turned.size == (120, 160)
    # The display matrix turns the stored picture 90 degrees counter-clockwise.
    np.testing.assert_array_equal(turned.frames[0], np.rot90(plain))


def test_the_focal_length_comes_from_the_metadata_where_present(tmp_path):
    path = write_video(tmp_path / "phone.mp4", seconds=3, width=320, height=240,
                       metadata={APPLE_FOCAL: "26"})
    video = read_video(path, long_side=160)
    assert probe_video(path).focal_35mm == 26.0
    # 26 mm on a 43.27 mm diagonal, at the decoded 160 x 120 picture's 200 px diagonal
    assert video.focal_px == pytest.approx(26 / np.hypot(36, 24) * 200, rel=1e-6)
    nonsense = write_video(tmp_path / "odd.mp4", seconds=3, metadata={APPLE_FOCAL: "9000"})
    assert read_video(nonsense).focal_px is None


def test_refusals_before_any_work(tmp_path):
    clip = write_video(tmp_path / "clip.mp4", seconds=4)
    refused("corrupt_video", probe_video, write_garbage(tmp_path / "junk.mp4"))
    refused("corrupt_video", probe_video, truncate(clip, tmp_path / "cut.mp4", 0.6))
    (tmp_path / "empty.webm").write_bytes(b"")
    refused("corrupt_video", probe_video, tmp_path / "empty.webm")
    err = refused("no_video_stream", probe_video, write_audio_only(tmp_path / "voice.ogg"))
    assert "audio" in err.message
    refused("too_short", probe_video, write_video(tmp_path / "short.webm", seconds=1.5))
    err = refused("too_long", read_video, clip, VideoLimits(min_duration_s=1, max_duration_s=3))
    assert "3 s" in err.what_to_do
    refused("file_too_large", probe_video, clip, VideoLimits(max_bytes=1000))
    refused("resolution_too_large", probe_video, clip, VideoLimits(max_side_px=128))
    refused("resolution_too_small", probe_video, clip, VideoLimits(min_side_px=200))
    refused("too_many_frames", probe_video, clip, VideoLimits(max_packets=20))


def test_decoded_frames_and_bytes_are_bounded_before_decoding(tmp_path):
    clip = write_video(tmp_path / "clip.webm", seconds=4, fps=10)
    refused("too_many_frames", read_video, clip, VideoLimits(max_frames=39))
    assert len(read_video(clip, VideoLimits(max_frames=40)).frames) == 40
    per_frame = 160 * 120 * 3
    refused("too_many_frames", read_video, clip, VideoLimits(max_decoded_bytes=39 * per_frame))
    # Fewer kept frames a second keep a long video within the same bound.
    video = read_video(clip, VideoLimits(max_frames=20, max_decode_fps=5))  # 0, 0.2 .. 3.8 s
    assert len(video.frames) == 20 and video.fps == pytest.approx(5.0, rel=0.01)


def test_bad_limits_are_an_error():
    with pytest.raises(ValueError, match="inconsistent"):
        VideoLimits(min_duration_s=10, max_duration_s=5)
    with pytest.raises(ValueError, match="long_side"):
        read_video("unused.mp4", long_side=4)


def test_millisecond_timestamps_keep_the_full_frame_rate_cap(tmp_path):
    """WebM stores times in milliseconds (33, 67, 100 ms ...): a 30 fps take capped at 15 fps
    keeps every other frame, not every third (measured: 101 of 300 frames before the slots)."""
    path = write_video(tmp_path / "page.webm", seconds=4, fps=30)
    video = read_video(path, VideoLimits(max_decode_fps=15))
    assert len(video.frames) == 60 and video.fps == pytest.approx(15.0, rel=0.02)


def test_frames_slower_than_the_declared_rate_keep_every_slot(tmp_path):
    """A browser's WebM under load: 30 fps declared, a frame every 200 ms. The frames kept
    at 4 a second are planned from the packets' starts (an estimate from the duration less
    a mean frame fell one short, and the upload was refused as corrupt)."""
    times = [200 * i for i in range(49)]
    path = write_video(tmp_path / "slow.webm", fps=30, times_ms=times)
    assert probe_video(path).starts_span_s == pytest.approx(9.6, abs=1e-3)
    video = read_video(path, VideoLimits(max_decode_fps=4.0))
    assert len(video.frames) == 39  # one per 250 ms slot over 9.6 s
    slots = np.floor(video.times_s * 4.0 + 0.05)
    assert np.all(np.diff(slots) == 1)  # every slot once, in order
