"""The lip-sync bench's stimulus (bench/voice_sync.py's JawDrives): a webcam performer's drives,
whose jaw edges are one of its drive_hz drives ("tick") or drives between them ("extra")."""

import asyncio
import importlib.util
import sys
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def voice_sync():
    spec = importlib.util.spec_from_file_location("voice_sync", ROOT / "bench" / "voice_sync.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def drive_times(voice_sync, edges: str) -> tuple[list[float], list[float], list[float]]:
    """1 s of 20 drives/s with a jaw edge every 0.3 s at an odd phase: the drives' capture
    stamps, the edges' and the jaw angles sent."""
    sent, angles, edge_at = [], [], []
    drives = voice_sync.JawDrives(lambda d: (sent.append(d.t_capture),
                                             angles.append(d.smplx["jaw_pose"][0])), 20.0, edges)

    async def run():
        until = time.monotonic() + 1.0
        task = asyncio.create_task(drives.run(until))
        for angle in (0.5, 0.0, 0.5):
            await asyncio.sleep(0.3 - 0.013)
            edge_at.append(time.monotonic())
            drives.jaw(angle)
        await asyncio.wait_for(task, 5)

    asyncio.run(run())
    return sent, edge_at, angles


def after_each_edge(sent: list[float], edges: list[float]) -> list[float]:
    """The time from each edge's drive to the next drive (s)."""
    out = []
    for e in edges:
        later = [t for t in sent if t > e + 0.001]
        out.append(later[0] - e if later else np.inf)
    return out


def test_an_edge_on_the_tick_is_one_of_the_drives_and_the_schedule_goes_on_from_it(voice_sync):
    """The edges fall 13, 26 and 39 ms before a tick of the 20 Hz schedule they interrupt."""
    sent, edges, angles = drive_times(voice_sync, "tick")
    assert all(any(abs(t - e) < 0.005 for t in sent) for e in edges)
    assert min(after_each_edge(sent, edges)) > 0.045  # no tick merges into the edge's frame
    assert len(sent) <= 20 + len(edges)
    assert angles[-1] == 0.5  # the ticks send the jaw as the last edge left it


def test_an_extra_edge_is_a_drive_between_the_ticks(voice_sync):
    sent, edges, _ = drive_times(voice_sync, "extra")
    assert min(after_each_edge(sent, edges)) < 0.045  # the ticks keep their own schedule
    assert len(sent) >= 20 + len(edges) - 1


def test_an_unknown_edge_mode_is_refused(voice_sync):
    with pytest.raises(ValueError, match="tick or extra"):
        voice_sync.JawDrives(lambda d: None, 30.0, "sometimes")


def test_a_viewer_that_skips_video_decoding_drops_frames_and_still_stops(voice_sync):
    """`--video-decode first`: a peer's video receiver hands no frame to its decoder thread,
    but its end marker still reaches it (so the receiver stops); audio is left alone."""
    from aiortc import RTCPeerConnection

    async def run():
        pc = RTCPeerConnection()
        try:
            pc.addTransceiver("video", direction="recvonly")
            pc.addTransceiver("audio", direction="recvonly")
            def queues_now():
                return {t.kind: t.receiver._RTCRtpReceiver__decoder_queue
                        for t in pc.getTransceivers()}

            queues = queues_now()
            voice_sync.skip_video_decode(pc)
            now = queues_now()
            assert now["audio"] is queues["audio"]
            assert isinstance(now["video"], voice_sync._DroppedFrames)
            now["video"].put(("vp8", b"frame"))
            assert queues["video"].empty()
            now["video"].put(None)
            assert queues["video"].get_nowait() is None
        finally:
            await pc.close()

    asyncio.run(run())
