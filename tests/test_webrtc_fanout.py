"""One video encode per picture for every WebRTC viewer who sees it (server/webrtc/fanout.py):
its streams on their own (real encoders, real decoders, no network), then real aiortc viewers
of a real server, shared against each encoding its own (``webrtc_shared_encode`` off, the
reference twin)."""

from __future__ import annotations

import asyncio
import types

import numpy as np
import pytest

pytest.importorskip("aiortc")

from protocol import Drive, Timings  # noqa: E402
from server.config import Settings  # noqa: E402

SIZE = 64
TIMEOUT_S = 30.0


def frame(versions: tuple[int, ...], value: int, group: object = "front", size: int = SIZE):
    """A raw scene frame: a grey picture with a square whose place follows ``value``."""
    from server.stream.scene import Frame

    rgb = np.full((size, size, 3), 90, np.uint8)
    x = 4 + (value * 7) % (size - 20)
    rgb[20:36, x:x + 16] = (200, 40, 40)
    return Frame(versions[0], "raw", size, size, b"", None, True, Timings(),
                 versions=versions, rgb=rgb, group=group)


def settings(**kw) -> Settings:
    return Settings(webrtc_keyframe_min_interval_s=kw.pop("interval", 0.5), **kw)


def viewer_track(fanout, mime: str = "video/vp8", queue_frames: int = 8, bitrate=None):
    """A viewer's track attached to ``fanout`` with a stand-in sender (its picture-loss
    hook is all the track sets on it) and packer (its bit-rate estimate)."""
    from server.webrtc.fanout import FanoutTrack

    track = FanoutTrack(queue_frames=queue_frames)
    sender = types.SimpleNamespace()
    track.attach(fanout, sender, mime, types.SimpleNamespace(target_bitrate=bitrate)
                 if bitrate is not None else None)
    track.sender = sender
    return track


def decoder(mime: str):
    import av

    return av.CodecContext.create("libvpx" if mime == "video/vp8" else "h264", "r")


def decode(codec, packet) -> np.ndarray | None:
    frames = codec.decode(packet)
    return frames[-1].to_ndarray(format="rgb24") if frames else None


def square_x(rgb: np.ndarray) -> float:
    """The red square's mean column."""
    red = (rgb[..., 0] > 150) & (rgb[..., 2] < 100)
    return float(np.nonzero(red)[1].mean())


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return 10 * np.log10(255.0**2 / max(mse, 1e-9))


async def next_packet(track):
    return await asyncio.wait_for(track.recv(), 5)


@pytest.mark.parametrize("mime", ["video/vp8", "video/h264"])
def test_three_viewers_share_one_encode_and_each_decodes_every_frame(mime):
    from server.webrtc.fanout import VideoFanout

    async def run():
        fanout = VideoFanout(settings())
        tracks = [viewer_track(fanout, mime) for _ in range(3)]
        receivers = [asyncio.ensure_future(t.recv()) for t in tracks]  # transports up
        await asyncio.sleep(0)
        frames = [frame((v,), v) for v in range(1, 7)]
        got = [[] for _ in tracks]
        for i, f in enumerate(frames):
            await asyncio.wait_for(asyncio.gather(*(t.deliver(f) for t in tracks)), 5)
            for k, t in enumerate(tracks):
                packet = await asyncio.wait_for(receivers[k], 5) if i == 0 else \
                    await next_packet(t)
                got[k].append(packet)
        encodes = fanout.encodes
        for t in tracks:
            t.stop()
        return frames, got, encodes, fanout

    frames, got, encodes, fanout = asyncio.run(run())
    assert encodes == len(frames)  # once per frame, not once per viewer
    assert not fanout.streams  # the last viewer left: the stream ended
    for packets in got:
        assert [bytes(p) for p in packets] == [bytes(p) for p in got[0]]  # the same bitstream
        pts = [p.pts for p in packets]
        assert pts == sorted(set(pts))  # each viewer's own timestamps, increasing
        codec = decoder(mime)
        images = [decode(codec, p) for p in packets]
        if mime == "video/h264":  # the decoder may hold one frame back; flush it
            images = [i for i in images if i is not None] + [
                f.to_ndarray(format="rgb24") for f in codec.decode(None)]
        assert len(images) == len(frames)
        for image, f in zip(images, frames, strict=True):
            assert psnr(image, f.rgb) > 25
            assert abs(square_x(image) - square_x(f.rgb)) < 1.5  # this frame's, not another's


def test_a_late_viewer_starts_at_a_keyframe_asked_within_the_interval():
    from server.webrtc.fanout import VideoFanout

    async def run():
        fanout = VideoFanout(settings(interval=0.3))
        first = viewer_track(fanout)
        pending = asyncio.ensure_future(first.recv())
        await asyncio.sleep(0)
        await first.deliver(frame((1,), 1))
        await asyncio.wait_for(pending, 5)
        await first.deliver(frame((2,), 2))
        await next_packet(first)
        stream = first.stream
        late = viewer_track(fanout)
        late_first = asyncio.ensure_future(late.recv())
        await asyncio.sleep(0)
        keys_before = stream.keyframes
        started = asyncio.get_running_loop().time()
        version = 3
        while not late_first.done() and version < 60:  # bounded
            f = frame((version,), version)
            await asyncio.gather(first.deliver(f), late.deliver(f))
            await next_packet(first)
            await asyncio.sleep(0.02)
            version += 1
        packet = await asyncio.wait_for(late_first, 5)
        waited = asyncio.get_running_loop().time() - started
        late.stop()
        first.stop()
        return stream, keys_before, packet, waited, late

    stream, keys_before, packet, waited, late = asyncio.run(run())
    from server.webrtc.encoders import RawVp8Encoder

    assert RawVp8Encoder.is_keyframe(bytes(packet))  # it could decode from its first packet
    assert stream.keyframes == keys_before + 1  # one keyframe, for the join
    assert waited >= 0.3 - 0.05  # not before the interval since the first keyframe
    assert late.skipped >= 1  # the deltas before it were not sent


def test_picture_loss_requests_are_bounded_by_the_keyframe_interval():
    from server.webrtc.fanout import VideoFanout

    async def run():
        fanout = VideoFanout(settings(interval=0.25))
        tracks = [viewer_track(fanout) for _ in range(2)]
        pending = [asyncio.ensure_future(t.recv()) for t in tracks]
        await asyncio.sleep(0)
        loop = asyncio.get_running_loop()
        started = loop.time()
        for version in range(1, 31):  # 30 frames, 20 ms apart: 0.6 s
            for _ in range(20):  # a hostile viewer: 20 picture-loss requests a frame
                tracks[1].sender._send_keyframe()
            f = frame((version,), version)
            await asyncio.gather(*(t.deliver(f) for t in tracks))
            await asyncio.sleep(0.02)
        elapsed = loop.time() - started
        for p in pending:
            await asyncio.wait_for(p, 5)
        stream = tracks[0].stream
        keyframes, encodes = stream.keyframes, stream.encodes
        for t in tracks:
            t.stop()
        return keyframes, encodes, elapsed

    keyframes, encodes, elapsed = asyncio.run(run())
    # the first frame, then at most one per interval, whatever was asked
    assert 2 <= keyframes <= 1 + elapsed / 0.25 + 1, (keyframes, elapsed)
    assert encodes >= 25  # the pictures still flowed


def test_a_viewer_that_stops_reading_skips_to_a_keyframe_and_the_others_miss_nothing():
    from server.webrtc.fanout import VideoFanout

    async def run():
        fanout = VideoFanout(settings(interval=0.0))
        reader, stalled = viewer_track(fanout), viewer_track(fanout, queue_frames=3)
        first = [asyncio.ensure_future(t.recv()) for t in (reader, stalled)]
        await asyncio.sleep(0)
        read = []
        for version in range(1, 11):
            f = frame((version,), version)
            await asyncio.gather(reader.deliver(f), stalled.deliver(f))
            read.append(await asyncio.wait_for(first[0], 5) if version == 1
                        else await next_packet(reader))
        await asyncio.wait_for(first[1], 5)  # it read one packet, then stalled for 9 frames
        overflows = stalled.overflows
        f = frame((11,), 11)
        await asyncio.gather(reader.deliver(f), stalled.deliver(f))
        read.append(await next_packet(reader))
        resumed = [await next_packet(stalled) for _ in range(len(stalled._queue))]
        for t in (reader, stalled):
            t.stop()
        return read, overflows, resumed, stalled

    read, overflows, resumed, stalled = asyncio.run(run())
    from server.webrtc.encoders import RawVp8Encoder

    codec = decoder("video/vp8")
    assert all(decode(codec, p) is not None for p in read)  # 11 of 11 for the reader
    assert overflows >= 1 and stalled.skipped >= 3
    assert resumed and RawVp8Encoder.is_keyframe(bytes(resumed[0]))  # on from a keyframe
    codec = decoder("video/vp8")
    assert all(decode(codec, p) is not None for p in resumed)


def test_a_viewer_alone_takes_its_stream_along_and_parting_viewers_part_streams():
    from server.webrtc.fanout import VideoFanout

    async def run():
        fanout = VideoFanout(settings(interval=0.0))
        a, b = viewer_track(fanout), viewer_track(fanout)
        pending = [asyncio.ensure_future(t.recv()) for t in (a, b)]
        await asyncio.sleep(0)
        await a.deliver(frame((1,), 1, group="front"))
        await asyncio.wait_for(pending[0], 5)
        alone = a.stream
        for step in range(3):  # its view moves: a new picture each frame, the drive still
            await a.deliver(frame((1,), step, group=("orbit", step)))
            await next_packet(a)
        moved = (a.stream is alone, alone.keyframes, len(fanout.streams))
        # b sees a's picture: it joins a's stream
        f = frame((2,), 9, group=("orbit", 2))
        await asyncio.gather(a.deliver(f), b.deliver(f))
        await asyncio.wait_for(pending[1], 5)
        joined = (b.stream is a.stream, len(fanout.streams))
        # a moves on: it parts from b, in a stream of its own
        await a.deliver(frame((3,), 10, group=("orbit", 3)))
        parted = (a.stream is not b.stream, len(fanout.streams), a.awaiting_key)
        for t in (a, b):
            t.stop()
        return moved, joined, parted, fanout

    moved, joined, parted, fanout = asyncio.run(run())
    assert moved == (True, 1, 1)  # the same stream, no keyframe past the first
    assert joined == (True, 1)
    assert parted == (True, 2, True)
    assert not fanout.streams


def test_stale_frames_and_repeats():
    """A frame older than the one taken is not encoded; a still picture repeats, marked as
    no new drive; equal offers of one picture share one encode."""
    from server.webrtc.fanout import SharedVideo, VideoFanout, supersedes

    assert supersedes(frame((2, 1), 0), frame((1, 1), 0))
    assert not supersedes(frame((1, 1), 0), frame((2, 1), 0))
    assert not supersedes(frame((2, 1), 0), frame((2, 1), 0))
    assert supersedes(frame((1,), 0, group="b"), frame((2,), 0, group="a"))
    assert supersedes(frame((1, 0), 0), frame((2,), 0))  # a seat joined

    async def run():
        fanout = VideoFanout(settings())
        t = viewer_track(fanout)
        pending = asyncio.ensure_future(t.recv())
        await asyncio.sleep(0)
        await t.deliver(frame((5,), 5))
        await asyncio.wait_for(pending, 5)
        stream: SharedVideo = t.stream
        stream.repeat_after_s = 0.05
        await asyncio.wait_for(t.deliver(frame((4,), 4)), 1)  # stale: at once
        await next_packet(t)  # nothing new: the last picture again
        counts = (stream.encodes, t.sent, t.repeated)
        t.stop()
        return counts

    encodes, sent, repeated = asyncio.run(run())
    assert (sent, repeated) == (1, 1) and encodes == 2  # the stale frame was not encoded


def test_bit_rate_is_the_lowest_viewers_estimate_within_the_bounds():
    from server.webrtc.fanout import VideoFanout

    async def run():
        fanout = VideoFanout(settings(webrtc_min_bitrate=100_000, webrtc_max_bitrate=900_000))
        fast = viewer_track(fanout, bitrate=800_000)
        slow = viewer_track(fanout, bitrate=300_000)
        pending = [asyncio.ensure_future(t.recv()) for t in (fast, slow)]
        await asyncio.sleep(0)
        f = frame((1,), 1)
        await asyncio.gather(fast.deliver(f), slow.deliver(f))
        await asyncio.gather(*pending)
        first = fast.stream.encoder.target_bitrate
        slow._sender_encoder.target_bitrate = 20_000  # below the floor
        f = frame((2,), 2)
        await asyncio.gather(fast.deliver(f), slow.deliver(f))
        await next_packet(fast)
        second = fast.stream.encoder.target_bitrate
        for t in (fast, slow):
            t.stop()
        return first, second

    assert asyncio.run(run()) == (300_000, 100_000)


def test_a_picture_the_codec_refuses_ends_its_viewers_not_the_loop():
    from aiortc.mediastreams import MediaStreamError

    from server.webrtc.fanout import VideoFanout

    async def run():
        fanout = VideoFanout(settings())
        t = viewer_track(fanout)
        pending = asyncio.ensure_future(t.recv())
        await asyncio.sleep(0)
        bad = frame((1,), 1)
        bad.rgb = np.zeros((SIZE, SIZE), np.float64)  # not an RGB picture
        await t.deliver(bad)
        with pytest.raises(MediaStreamError):  # its sender stops: the peer closes
            await asyncio.wait_for(pending, 5)
        fine = viewer_track(fanout)  # the room's next viewer is served
        waiting = asyncio.ensure_future(fine.recv())
        await asyncio.sleep(0)
        await fine.deliver(frame((2,), 2))
        packet = await asyncio.wait_for(waiting, 5)
        fine.stop()
        return t.readyState, packet

    state, packet = asyncio.run(run())
    assert state == "ended" and len(bytes(packet)) > 0


# -- real aiortc viewers of a real server ------------------------------------------------------


@pytest.mark.parametrize("shared", [True, False])
def test_viewers_of_one_room_share_its_encodes(tmp_path, shared):
    """Three WHEP viewers of a room while its performer drives: each decodes pictures that
    follow the drives; shared, the room encoded each picture once (about a third of the
    frames its viewers got), not shared, nothing went through the room's fan-out."""
    from client.webrtc import WhepViewer
    from tests.server_fixtures import run_server
    from tests.test_server_rooms import create_room, invite

    with run_server(tmp_path, default_width=SIZE, default_height=SIZE, default_max_fps=30,
                    webrtc_shared_encode=shared) as srv:
        room = create_room(srv)
        watch = invite(srv, room["id"], "watch")

        async def run():
            viewers = [WhepViewer(srv.url, room["id"], watch["token"], width=SIZE,
                                  height=SIZE, timeout_s=TIMEOUT_S) for _ in range(3)]
            async with WhepViewer(srv.url, room["id"], srv.token, stamp=True,
                                  timeout_s=TIMEOUT_S) as performer:
                await performer.wait_open()
                for v in viewers:
                    await v.__aenter__()
                try:
                    for v in viewers:
                        await v.next_frame()
                    got = [[] for _ in viewers]
                    for seq in range(1, 9):  # the jaw opens and shuts
                        performer.send(Drive(seq=seq, smplx={
                            "jaw_pose": np.array([0.4 * (seq % 2), 0.0, 0.0])}))
                        await asyncio.sleep(0.15)
                    for k, v in enumerate(viewers):
                        for _ in range(3):
                            rgb, _ = await v.next_frame()
                            got[k].append(rgb)
                    tracks = [p.track for p in srv.ctx.webrtc_peers.peers()
                              if p.track is not None]
                    fanout = srv.ctx.webrtc_peers.peers()[0].room.live.video_fanout
                    encodes = None if fanout is None else fanout.encodes
                    return got, encodes, tracks
                finally:
                    for v in viewers:
                        await v.__aexit__(None, None, None)

        got, encodes, tracks = asyncio.run(run())
    for frames in got:
        for rgb in frames:
            assert rgb.shape == (SIZE, SIZE, 3) and rgb.std() > 10  # the avatar, decoded
    from server.webrtc.fanout import FanoutTrack

    viewing = [t for t in tracks if isinstance(t, FanoutTrack)]
    if shared:  # the three viewers; the performer's stamped picture is its own
        assert len(viewing) == 3 and len(tracks) == 4
        sent = sum(t.sent + t.repeated for t in viewing)
        assert 0 < encodes and encodes * 2 < sent, (encodes, sent)
    else:
        assert not viewing and len(tracks) == 4 and encodes is None
