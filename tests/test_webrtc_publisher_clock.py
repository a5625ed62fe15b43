"""A WHIP publisher's capture times (issue 30): its sender reports put its webcam's frames and
its microphone's packets on one clock, so the drive tracked from a frame and the voice spoken
with it carry capture times a WebSocket viewer can sync; the mapping itself, with hostile
reports, on its own."""

from __future__ import annotations

import asyncio
import fractions
import time

import numpy as np
import pytest

from server.webrtc.publisher_clock import (
    NTP_FRACTION,
    ORIGIN_MARGIN_S,
    PublisherClock,
    signed_ticks,
)
from tests.server_fixtures import is_type, run_server
from tests.test_server_rooms import create_room, invite, join
from tests.test_webrtc_whip import face_frames
from tests.track_models import needs_models
from tests.voice_fixtures import CLICK_LEVEL, CLICK_SAMPLES, FRAME_SAMPLES, RATE

NTP_NOW = 3_973_000_000  # NTP seconds in 2025
FRAME_EVERY = 20         # audio packets (20 ms) per webcam frame: 0.4 s, 2.5 fps
TIMEOUT_S = 90.0         # the first image loads the landmark models
ONE_CLOCK_MS = 50.0      # the median frame's stamp lands this close to its instant on the
#                          voice's clock (a wrong clock lands anywhere within +-200 ms)
ONE_CLICK_MS = 25.0      # the median click's, to the first's grid
FRAMES, CLICKS = 8, 5    # drives and clicks a run collects
VOICED = 150             # voice packets a WHEP performer's test hears (3 s)


def ntp(seconds: float) -> int:
    return round(seconds * NTP_FRACTION)


# -- the mapping ----------------------------------------------------------------------------------

def test_rtp_timestamps_map_through_the_last_report_on_one_origin():
    clock = PublisherClock()
    audio, video = clock.track(48_000), clock.track(90_000)
    assert audio.capture_time(1000) is None  # no report yet: no capture time
    audio.note(1000, ntp(NTP_NOW + 0.25))
    video.note(5000, ntp(NTP_NOW + 1.5))
    assert clock.origin == NTP_NOW - ORIGIN_MARGIN_S  # the first report's second, less margin
    assert audio.capture_time(1000) == pytest.approx(ORIGIN_MARGIN_S + 0.25)
    assert audio.capture_time(1000 + 960) == pytest.approx(ORIGIN_MARGIN_S + 0.27)
    assert audio.capture_time(1000 - 960) == pytest.approx(ORIGIN_MARGIN_S + 0.23)  # before
    assert video.capture_time(5000 + 9000) == pytest.approx(ORIGIN_MARGIN_S + 1.6)
    assert video.capture_time(None) is None


def test_timestamps_across_the_32_bit_wrap_keep_their_order():
    clock = PublisherClock()
    track = clock.track(90_000)
    track.note(2**32 - 900, ntp(NTP_NOW))
    assert track.capture_time(900 - 2**32 + 2**32) == pytest.approx(ORIGIN_MARGIN_S + 0.02)
    assert signed_ticks(5, 2**32 - 5) == 10 and signed_ticks(2**32 - 5, 5) == -10


def test_hostile_reports_give_no_time_and_never_raise():
    clock = PublisherClock()
    track = clock.track(48_000)
    track.note(0, 0)  # NTP 0: a sender without a wall clock
    assert track.capture_time(0) is None and clock.refused == 1 and clock.origin is None
    track.note(0, ntp(NTP_NOW))
    # media stamped long before the report: before the origin, so no time (not a negative one)
    assert track.capture_time(2**31 - 1) is not None
    assert track.capture_time((-(ORIGIN_MARGIN_S + 10) * 48_000) % 2**32) is None
    # a report a century later: past the protocol's CaptureTime, so no time
    track.note(0, ntp(NTP_NOW + 100 * 365 * 86400))
    assert track.capture_time(0) is None
    for rtp in (-1, 2**40, 2**32):  # any integer: reduced to 32 bits
        track.note(rtp, ntp(NTP_NOW + 1))
        assert track.capture_time(rtp) == pytest.approx(ORIGIN_MARGIN_S + 1)


# -- a real publisher -----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    with run_server(tmp_path_factory.mktemp("publisher_clock"), default_width=64,
                    default_height=64, default_max_fps=30) as running:
        yield running


def publisher_tracks():
    """A webcam (the face photo) and a microphone on one clock: frame j is captured at
    ``start + 0.4 j`` and so is audio packet 20 j, which holds a click."""
    from aiortc import MediaStreamTrack

    clock: dict[str, float] = {}

    def due(index: int, every_s: float) -> float:
        start = clock.setdefault("start", time.monotonic())
        return start + index * every_s

    class Webcam(MediaStreamTrack):
        kind = "video"

        def __init__(self) -> None:
            super().__init__()
            self.images, self.sent = face_frames(), 0

        async def recv(self):
            import av

            at = due(self.sent, FRAME_EVERY * FRAME_SAMPLES / RATE)
            await asyncio.sleep(max(0.0, at - time.monotonic()))
            frame = av.VideoFrame.from_ndarray(self.images[self.sent % 2], format="rgb24")
            frame.pts = self.sent * FRAME_EVERY * FRAME_SAMPLES * 90_000 // RATE
            frame.time_base = fractions.Fraction(1, 90_000)
            self.sent += 1
            return frame

    class Microphone(MediaStreamTrack):
        kind = "audio"

        def __init__(self) -> None:
            super().__init__()
            self.sent = 0

        async def recv(self):
            import av

            at = due(self.sent, FRAME_SAMPLES / RATE)
            await asyncio.sleep(max(0.0, at - time.monotonic()))
            samples = np.zeros((1, FRAME_SAMPLES), np.int16)
            if self.sent % FRAME_EVERY == 0:
                samples[0, :CLICK_SAMPLES] = 30000
            frame = av.AudioFrame.from_ndarray(samples, format="s16", layout="mono")
            frame.sample_rate, frame.pts = RATE, self.sent * FRAME_SAMPLES
            frame.time_base = fractions.Fraction(1, RATE)
            self.sent += 1
            return frame

    return Webcam(), Microphone()


def clicked(decoder, payload: bytes) -> bool:
    import av

    samples = [f.to_ndarray() for f in decoder.decode(av.Packet(payload))]
    if not samples:
        return False
    block = np.concatenate([s.reshape(-1) for s in samples])
    scale = 32768.0 if block.dtype == np.int16 else 1.0
    return float(np.abs(block).max()) / scale > CLICK_LEVEL


@needs_models
def test_a_whip_publishers_frames_and_voice_carry_capture_times_on_one_clock(srv):
    """A WebSocket viewer of a WHIP publisher: the frames of its tracked webcam and its voice
    both carry capture times (none came before this), each frame's on the 0.4 s grid of the
    clicks' (the instants the webcam and the microphone shared). Medians: aiortc's reports
    pair a timestamp with the time its packet was *sent* (a browser's, with its capture), so
    a packet sent late by a busy loop moves every stamp until the next report."""
    import av
    import httpx
    from aiortc import RTCConfiguration, RTCPeerConnection, RTCSessionDescription

    room = create_room(srv)
    watch = invite(srv, room["id"], "watch")

    async def run():
        pc = RTCPeerConnection(RTCConfiguration(iceServers=[]))
        webcam, microphone = publisher_tracks()
        pc.addTransceiver(webcam, direction="sendonly")
        pc.addTransceiver(microphone, direction="sendonly")
        frames: dict[int, float] = {}  # drive seq -> its frames' t_capture
        clicks: list[float] = []
        leads: list[float] = []  # the seat's drive: its image's arrival less its capture instant
        voiced = 0
        decoder = av.CodecContext.create("libopus", "r")
        async with join(srv, room["id"], watch["token"], voice=True) as viewer:
            await pc.setLocalDescription(await pc.createOffer())
            async with httpx.AsyncClient(base_url=srv.url, timeout=TIMEOUT_S) as http:
                r = await http.post(f"/v1/rooms/{room['id']}/whip",
                                    content=pc.localDescription.sdp,
                                    headers={**srv.headers(), "Content-Type": "application/sdp"})
                assert r.status_code == 201, r.text
                await pc.setRemoteDescription(RTCSessionDescription(r.text, "answer"))
                deadline = time.monotonic() + TIMEOUT_S
                while ((len(frames) < FRAMES or len(clicks) < CLICKS)
                       and time.monotonic() < deadline):
                    try:
                        from protocol import decode_server

                        msg = decode_server(await asyncio.wait_for(viewer.recv(), 5))
                    except TimeoutError:
                        continue
                    if is_type("voice")(msg) and msg.t_capture is not None:
                        voiced += 1
                        if clicked(decoder, msg.data):
                            clicks.append(msg.t_capture)
                    elif is_type("frame")(msg) and msg.t_capture is not None:
                        frames.setdefault(msg.seq, msg.t_capture)
                        drive = srv.ctx.rooms.get(room["id"]).live.seats[0].drive
                        leads.append((drive.arrived - drive.captured_at) * 1e3)
                await http.delete(r.headers["location"], headers=srv.headers())
        await pc.close()
        return frames, clicks, voiced, leads

    frames, clicks, voiced, leads = asyncio.run(run())
    assert len(frames) >= FRAMES and len(clicks) >= CLICKS, (frames, clicks, voiced)
    period = FRAME_EVERY * FRAME_SAMPLES / RATE
    # the clicks keep their grid: each report maps the timestamps anew, off by how late the
    # publisher sent the packet it names (a few ms; 200 ms seen beside a CI run)
    phase = clicks[0]
    off = sorted(((c - phase + period / 2) % period - period / 2) for c in clicks)
    phase += off[len(off) // 2]  # the median click's
    off = [((c - phase + period / 2) % period - period / 2) * 1e3 for c in clicks]
    assert float(np.median(np.abs(off))) < ONE_CLICK_MS, off
    # each drive's stamp: its webcam frame's instant, on the voice's clock
    stamps = [frames[seq] for seq in sorted(frames)]
    assert stamps == sorted(stamps)  # later drives, later images
    residual = [((t - phase + period / 2) % period - period / 2) * 1e3 for t in stamps]
    print(f"frame stamps against the clicks' grid, ms: {[round(x, 1) for x in residual]}; "
          f"{voiced} stamped voice packets, {len(clicks)} clicks; image arrival less its "
          f"capture instant, ms: {[round(x, 1) for x in leads]}")
    assert float(np.median(np.abs(residual))) <= ONE_CLOCK_MS, residual
    # on this server's clock an image was captured no later than it arrived (decoded): the
    # WebRTC senders stamp its frames with that instant (before: with the arrival)
    assert all(x >= 0 for x in leads), leads
    # and it arrived at its last packet, not a frame interval later (protocol/rtp_receiver.py):
    # a buffer that waits for the next frame holds every frame a period; the suite's load can
    # delay many (a median of 240 ms was seen in a fresh-clone run), never all of them
    assert min(leads) < period / 2 * 1e3, leads


def test_a_whep_performers_voice_stays_off_the_clock_of_its_own_drives(srv):
    """A WHEP performer drives over its data channel, stamped on a clock of its own, and
    speaks over RTP: its voice gets no stamp from the sender reports (a WebSocket viewer would
    then sync it against frames on another clock), and its drives' clock never restarts."""
    from client.webrtc import WhepViewer
    from protocol import Drive, decode_server
    from tests.voice_fixtures import click_track

    room = create_room(srv)
    perform = invite(srv, room["id"], "perform")
    watch = invite(srv, room["id"], "watch")

    async def run():
        performer = WhepViewer(srv.url, room["id"], perform["token"], width=64, height=64,
                               microphone=click_track(), timeout_s=TIMEOUT_S)
        async with performer, join(srv, room["id"], watch["token"], voice=True) as viewer:
            await performer.wait_open()
            stamps, voiced = [], 0
            deadline = time.monotonic() + TIMEOUT_S
            seq = 0
            # 3 s of voice: aiortc's sender reports every 0.5-1.5 s, so several came (with
            # the earlier rule the packets were stamped from the first one on)
            while voiced < VOICED and time.monotonic() < deadline:
                seq += 1
                performer.send(Drive(seq=seq, smplx={"jaw_pose": [0.1 * (seq % 2), 0, 0]},
                                     t_capture=10.0 + time.monotonic() % 1000))
                try:
                    msg = decode_server(await asyncio.wait_for(viewer.recv(), 0.1))
                except TimeoutError:
                    continue
                if is_type("voice")(msg):
                    voiced += 1
                    stamps.append(msg.t_capture)
            session = srv.ctx.rooms.get(room["id"]).live.seats[0].performer
            return stamps, voiced, session.capture_clock.resets

    stamps, voiced, resets = asyncio.run(run())
    assert voiced >= VOICED, voiced
    assert all(s is None for s in stamps), stamps
    assert resets == 0
