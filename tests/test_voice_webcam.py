"""A webcam performer's lip sync (issue 30) on a real uvicorn with the real tracker: an
``image`` carries its capture time, the drive tracked from it and the frames that show it
carry the same one (the clock its voice uses), and a WebRTC viewer's voice waits for the
frame of the image it was spoken with, tracking time included."""

from __future__ import annotations

import asyncio
import fractions
import time

import numpy as np
import pytest

from protocol import Image, Voice, encode
from protocol.stamp import read_stamp
from tests.server_fixtures import is_type, recv_until, run_server
from tests.test_server_rooms import create_room, invite, join
from tests.test_track_drive import astronaut_jpeg
from tests.track_models import needs_models
from tests.voice_fixtures import (
    CLICK_LEVEL,
    CLICK_SAMPLES,
    FRAME_SAMPLES,
    RATE,
    note_rtp_arrivals,
    peak,
)

pytest.importorskip("aiortc")

SIZE = 64
EVENTS = 5
IMAGE_EVERY_S = 0.2  # a camera's images (latest wins: the tracker takes what it can)
EVENT_EVERY = 30     # images: every 6 s one goes with a click (more than the voice may
#                      wait, so each click is told from the last)
SAME_FRAME_MS = 250.0  # a click this close to its frame came with it
MAX_DELAY_S = 5.0    # the most voice_max_delay_s allows: tracking takes seconds here


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    # tracking takes seconds on two shared cores: the voice may wait that long here
    with run_server(tmp_path_factory.mktemp("voice_webcam"), default_width=SIZE,
                    default_height=SIZE, default_max_fps=30,
                    voice_max_delay_s=MAX_DELAY_S,
                    voice_buffer_packets=int(MAX_DELAY_S * 50) + 50,
                    # the server's default: a full collection of this test process's heap
                    # (server, viewer and pytest in one) holds every packet in flight
                    gc_freeze=True) as running:
        yield running


class Microphone:
    """20 ms Opus packets of silence, or of a click, from one libopus encoder."""

    def __init__(self) -> None:
        import av

        self.codec = av.CodecContext.create("libopus", "w")
        self.codec.sample_rate, self.codec.layout, self.codec.format = RATE, "mono", "s16"
        self.codec.bit_rate = 32000
        self.codec.options = {"frame_duration": "20"}
        self.sent = 0

    def packet(self, click: bool) -> bytes:
        import av

        samples = np.zeros((1, FRAME_SAMPLES), np.int16)
        if click:
            samples[0, :CLICK_SAMPLES] = 30000
        frame = av.AudioFrame.from_ndarray(samples, format="s16", layout="mono")
        frame.sample_rate, frame.pts = RATE, self.sent * FRAME_SAMPLES
        frame.time_base = fractions.Fraction(1, RATE)
        self.sent += 1
        return b"".join(bytes(p) for p in self.codec.encode(frame))


@needs_models
def test_a_tracked_frame_carries_its_images_capture_time(srv):
    room = create_room(srv)
    perform = invite(srv, room["id"], "perform")
    watch = invite(srv, room["id"], "watch")

    async def run():
        async with join(srv, room["id"], perform["token"]) as performer, \
                join(srv, room["id"], watch["token"], voice=True) as viewer:
            await performer.send(encode(Image(seq=5, data=astronaut_jpeg(), t_capture=70.25)))
            await recv_until(performer, is_type("tracked"), timeout=90)  # the tracker loaded
            await performer.send(encode(Image(seq=6, data=astronaut_jpeg(0.5))))  # none
            frames = [await recv_until(viewer, is_type("frame", seq=seq), timeout=60)
                      for seq in (5, 6)]
            return frames, performer.welcome.minor

    (with_time, without), minor = asyncio.run(run())
    assert minor >= 4
    assert with_time.t_capture == 70.25 and with_time.timings.track > 0
    assert without.t_capture is None  # an image without one: a drive without one


@needs_models
def test_a_webrtc_viewer_hears_a_webcam_performer_with_the_frame_of_its_image(srv):
    """The performer sends camera images every IMAGE_EVERY_S and its 20 ms voice; with every
    EVENT_EVERY-th image, in the same instant, a click. The viewer's click arrives with the
    first frame (stamped with its drive's seq) of that image or a later one, though tracking
    delays the frame by seconds here and not the voice."""
    from client.webrtc import WhepViewer

    room = create_room(srv)
    perform = invite(srv, room["id"], "perform")
    watch = invite(srv, room["id"], "watch")
    images = [astronaut_jpeg(), astronaut_jpeg(0.8)]  # two poses' worth of pixels

    async def run():
        async with join(srv, room["id"], perform["token"]) as performer:
            await performer.send(encode(Image(seq=1, data=images[0], t_capture=1.0)))
            await recv_until(performer, is_type("tracked"), timeout=90)  # the tracker loaded
            async with WhepViewer(srv.url, room["id"], watch["token"], width=SIZE,
                                  height=SIZE, stamp=True, voices=1, timeout_s=30) as v:
                arrived = note_rtp_arrivals(v)
                await v.next_frame()
                sent: dict[int, float] = {}  # image seq -> when sent with a click
                shown: dict[int, float] = {}  # stamped seq -> its first frame's arrival
                clicks: list[float] = []
                newest = [1]  # the newest image seq sent so far
                # misread: a stamp of an image not yet sent (codec-blurred 2 px cells that
                # passed the check bits); unreadable: no valid stamp
                counts = {"frames": 0, "misread": 0, "unreadable": 0}

                async def speak():
                    mic, start, seq = Microphone(), time.monotonic(), 1
                    next_image = start
                    while len(sent) < EVENTS:
                        now, click = time.monotonic(), False
                        if now >= next_image:
                            seq += 1
                            newest[0] = seq
                            await performer.send(encode(Image(
                                seq=seq, data=images[seq % 2], t_capture=now)))
                            click = seq % EVENT_EVERY == 0  # the first after warming up
                            if click:
                                sent[seq] = now
                            next_image += IMAGE_EVERY_S
                        await performer.send(encode(Voice(seq=mic.sent, data=mic.packet(click),
                                                          t_capture=now)))
                        due = start + mic.sent * FRAME_SAMPLES / RATE
                        await asyncio.sleep(max(0.0, due - time.monotonic()))
                    await asyncio.sleep(MAX_DELAY_S)  # the last frame and click through

                async def watch_frames():
                    while True:
                        frame = await v.next_video_frame()
                        decoded = time.monotonic()
                        seq = read_stamp(frame.to_ndarray(format="rgb24"))
                        counts["frames"] += 1
                        if seq is None or seq > newest[0]:
                            counts["unreadable" if seq is None else "misread"] += 1
                            continue
                        shown.setdefault(seq, arrived["video"](frame.pts) or decoded)

                async def listen():
                    quiet = True
                    while True:
                        frame, decoded = await v.next_audio()
                        if peak(frame) > CLICK_LEVEL and quiet:
                            clicks.append(arrived["audio"](frame.pts) or decoded)
                        quiet = peak(frame) <= CLICK_LEVEL

                watching = [asyncio.create_task(watch_frames()), asyncio.create_task(listen())]
                await speak()
                for task in watching:
                    task.cancel()
                await asyncio.gather(*watching, return_exceptions=True)
                return sent, shown, clicks, counts

    sent, shown, clicks, counts = asyncio.run(run())
    offsets, tracking = [], []
    for seq, at in sent.items():
        # its frame: the first showing it or a later image (latest wins: it may be skipped)
        frame = min((t for s, t in shown.items() if s is not None and s >= seq), default=None)
        # its click: the first heard after it was spoken, before the next one was
        click = next((c for c in clicks if at <= c < at + EVENT_EVERY * IMAGE_EVERY_S), None)
        if frame is None or click is None or frame - at > MAX_DELAY_S:
            continue  # a frame later than the voice may wait: released at the bound
        offsets.append((click - frame) * 1e3)
        tracking.append((frame - at) * 1e3)
    print(f"click - frame ms: {[round(x) for x in offsets]}; image -> frame ms: "
          f"{[round(x) for x in tracking]}; {len(clicks)} clicks for {len(sent)} images; "
          f"frames read {counts}")
    assert len(offsets) >= EVENTS - 2, (sent, shown, clicks)
    # The frame came seconds after its image (tracking), the voice with it, not ahead by the
    # tracking time (as it was before: docs/benchmarks.md). Within SAME_FRAME_MS, not the
    # -45/+125 ms bounds: the voice leaves as the frame goes to the encoder, and on two loaded
    # cores the VP8 encode and this process's own receiving lag 0-140 ms behind (measured
    # here); bench/voice_sync.py measures the bounds.
    # The voice waited for the frame: a click that had not waited would come about the
    # tracking time ahead of its frame (offset ~ -tracking). How long tracking takes depends
    # on the machine (a quiet one ~170 ms, a loaded one 0.9-2.3 s), so the check is relative.
    assert min(tracking) > 50.0, tracking  # the frame did lag its image
    waited = [x > -0.5 * t for x, t in zip(offsets, tracking, strict=True)]
    assert all(waited), (offsets, tracking)
    assert all(abs(x) <= SAME_FRAME_MS for x in offsets), offsets
