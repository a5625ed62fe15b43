"""Both WHEP tracks on the performer's capture clock (issue 30, ``webrtc_sender_clock``).

Real aiortc peers against a real server in this process (one time.monotonic() for both): the
performer stamps its drives with time.monotonic() and its microphone's clicks are noted as
they are handed to the encoder; the viewer reads each frame's drive seq from its stamp, hears
each click, and maps both RTP timestamps through the last RTCP sender report of their track.
Each must land on the NTP time of its own capture (wall clock = monotonic + the offset between
them), within a few ms: a frame and a packet captured together then map to one NTP time, as
a browser that lip-syncs by the reports needs. Hard cases: no audio track, drives without a
capture time, a performer that leaves and a new one (another clock) that takes the seat.
"""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

from client.webrtc import WhepViewer
from protocol import Drive
from protocol.stamp import read_stamp
from tests.server_fixtures import run_server
from tests.test_server_rooms import create_room, invite
from tests.voice_fixtures import CLICK_LEVEL, click_track, peak

pytest.importorskip("aiortc")

SIZE = 128
TIMEOUT_S = 30.0
WARM_S = 2.5      # two sender reports of each track (every 0.5-1.5 s) before measuring
LISTEN_S = 15.0   # at most: each listener stops once it has ENOUGH (a loaded machine renders
ENOUGH = 12       # a few frames a second)
DRIVE_HZ = 30
CLICK_EVERY = 25  # 20 ms frames: a click every 0.5 s
TOLERANCE_MS = 12.0  # a few ms of transit and scheduling on this shared machine, not a frame
RATES = {"video": 90_000, "audio": 48_000}


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    with run_server(tmp_path_factory.mktemp("sender_clock"), default_width=SIZE,
                    default_height=SIZE, default_max_fps=15,
                    webrtc_sender_clock="capture") as running:
        yield running


def wall_minus_monotonic() -> float:
    return time.time() - time.monotonic()


class Reports:
    """A viewer's received sender reports per track, and its RTP timestamps mapped by them."""

    def __init__(self, viewer: WhepViewer) -> None:
        from aiortc.rtp import RtcpSrPacket

        self.video_pt: dict[str, int] = {}
        self.first: dict[str, int] = {}  # aiortc's decoded pts: RTP timestamp less the first
        self.reports: dict[str, list[tuple[int, float]]] = {"video": [], "audio": []}
        self.video_ts: dict[int, int] = {}  # video RTP sequence number -> timestamp
        for receiver in viewer.pc.getReceivers():
            kind = receiver.track.kind
            rtp, rtcp = receiver._handle_rtp_packet, receiver._handle_rtcp_packet

            async def on_rtp(packet, arrival_time_ms=0, kind=kind, rtp=rtp):
                self.first.setdefault(kind, packet.timestamp)
                if kind == "video" and packet.payload_type == self.video_pt.setdefault(
                        "pt", packet.payload_type):  # not a retransmission (RTX)
                    self.video_ts[packet.sequence_number] = packet.timestamp
                await rtp(packet, arrival_time_ms=arrival_time_ms)

            async def on_rtcp(packet, kind=kind, rtcp=rtcp):
                if isinstance(packet, RtcpSrPacket) and packet.sender_info.packet_count:
                    info = packet.sender_info
                    # NTP (1900) -> Unix seconds, as time.time()
                    self.reports[kind].append((info.rtp_timestamp,
                                               info.ntp_timestamp / 2**32 - 2_208_988_800))
                await rtcp(packet)

            receiver._handle_rtp_packet, receiver._handle_rtcp_packet = on_rtp, on_rtcp

    def wall_time(self, kind: str, pts: int) -> float | None:
        """A decoded frame's ``pts`` on the wall clock by its track's latest report."""
        if not self.reports[kind]:
            return None
        rtp, wall = self.reports[kind][-1]
        ticks = (self.first[kind] + pts - rtp + 2**31) % 2**32 - 2**31
        return wall + ticks / RATES[kind]


class Performer:
    """Drives at DRIVE_HZ, each stamped ``clock()`` (None: no t_capture), seq -> capture."""

    def __init__(self, viewer: WhepViewer, clock, seq0: int = 1) -> None:
        self.viewer, self.clock = viewer, clock
        self.seq = seq0
        self.captured: dict[int, float] = {}  # seq -> its capture (time.monotonic())
        self.running = True

    async def drive(self) -> None:
        while self.running and self.viewer.channel.readyState == "open":
            now = time.monotonic()
            t = self.clock(now)
            self.viewer.send(Drive(seq=self.seq, smplx={"jaw_pose": [0.3 * (self.seq % 2),
                                                                     0.0, 0.0]}, t_capture=t))
            self.captured[self.seq] = now
            self.seq += 1
            await asyncio.sleep(1 / DRIVE_HZ)


async def video_errors(viewer: WhepViewer, reports: Reports, performers: list[Performer],
                       until: float) -> list[float]:
    """For the first frame showing each drive: its wall time by the reports less its drive's
    capture on the wall clock (ms)."""
    errors, last = [], None
    while time.monotonic() < until and len(errors) < ENOUGH:
        frame = await viewer.next_video_frame()
        seq = read_stamp(frame.to_ndarray(format="rgb24"))
        wall = reports.wall_time("video", frame.pts)
        captured = next((p.captured[seq] for p in performers if seq in p.captured), None)
        if seq != last and wall is not None and captured is not None:
            errors.append((wall - captured - wall_minus_monotonic()) * 1e3)
        last = seq
    return errors


async def audio_errors(viewer: WhepViewer, reports: Reports, mics: list, until: float,
                       since: float = 0.0) -> list[float]:
    """For each click heard (captured after ``since``, monotonic): its wall time by the
    reports less the nearest click's media time (its capture instant: a stalled event loop
    hands a click over late, but its samples keep their time), on the wall clock (ms)."""
    errors, quiet = [], True
    while time.monotonic() < until and len(errors) < ENOUGH:
        frame, _ = await viewer.next_audio()
        loud = peak(frame) > CLICK_LEVEL
        wall = reports.wall_time("audio", frame.pts)
        clicks = [c for mic in mics for c in mic.click_media]
        at = None if wall is None else wall - wall_minus_monotonic()
        if loud and quiet and at is not None and at > since and clicks:
            errors.append(min((at - c for c in clicks), key=abs) * 1e3)
        quiet = not loud
    return errors


def assert_on_capture(errors: list[float], what: str, least: int,
                      tolerance_ms: float = TOLERANCE_MS) -> None:
    assert len(errors) >= least, (what, errors)
    median = float(np.median(errors))
    assert abs(median) <= tolerance_ms, (what, median, errors)
    # each one too (a stalled render or packet moves its arrival, never its capture stamp);
    # most of them: a drive sent late by a stalled loop is stamped when sent
    close = [abs(e) <= tolerance_ms for e in errors]
    assert sum(close) >= 0.8 * len(errors), (what, errors)


# -- units -------------------------------------------------------------------------------------


def test_arrival_clock_takes_the_quickest_recent_transit_and_restarts_on_a_jump():
    from server.stream.capture_clock import ArrivalClock

    clock = ArrivalClock(window_s=10.0, jump_s=1.0)
    assert clock.stamp_of(5.0) is None  # nothing seen: no inverse
    # stamps 100 s behind this clock, transits 30, 5 (the quickest), 80 ms
    assert clock.observe(0.0, 100.030) == pytest.approx(100.030)
    assert clock.observe(1.0, 101.005) == pytest.approx(101.005)
    assert clock.observe(2.0, 102.080) == pytest.approx(102.005)  # a late one moves nothing
    assert clock.stamp_of(102.005) == pytest.approx(2.0)  # back to the sender's clock
    # the quickest leaves the window: the quickest of the rest
    assert clock.observe(11.5, 111.590) == pytest.approx(111.580)
    # the sender's clock jumps back 500 s (a restarted page): a new window at once
    assert clock.observe(12.0 - 500, 112.010) == pytest.approx(112.010)
    assert clock.resets == 1
    with pytest.raises(ValueError, match="window_s"):
        ArrivalClock(window_s=0)
    # stamp + (arrived - stamp) rounds 3.6e-12 s past arrived here: never later than arrived
    stamp, arrived = 76377.4618976614, 12550.690257394217
    assert stamp + (arrived - stamp) > arrived
    assert ArrivalClock().observe(stamp, arrived) == arrived


def test_capture_stamps_and_epoch():
    from server.webrtc.sender_clock import CaptureEpoch, CaptureStamps

    stamps = CaptureStamps(kept=3)
    for pts in range(5):
        stamps.note(pts, 10.0 + pts)
    assert stamps.captured_at(1) is None and stamps.captured_at(4) == 14.0
    stamps.note(2**32 + 7, 1.5)  # kept by its value on the wire (mod 2^32)
    assert stamps.captured_at(7) == 1.5
    epoch = CaptureEpoch(monotonic=50.0, ntp=1000 * 2**32)
    assert epoch.ticks(51.5, 90_000) == 135_000
    assert epoch.ntp_of(52.25) == 1002 * 2**32 + 2**30


def test_video_timestamps_follow_captures_and_never_go_back():
    """A frame's timestamp is its drive's capture instant; a repeat (a held frame) or a
    frame of no new drive stands one picture lag before its sending; a capture older than the
    last frame's (a performer restarted, a frame of a drive from before the peer) goes on
    from the last timestamp."""
    from server.webrtc.sender_clock import CaptureEpoch
    from server.webrtc.track import LatestFrameTrack

    rgb = np.zeros((8, 8, 3), np.uint8)

    async def run():
        epoch = CaptureEpoch(time.monotonic() - 10.0, 0)
        track = LatestFrameTrack(repeat_after_s=0.05, epoch=epoch, max_lag_s=60.0)
        out = []
        for captured in (epoch.monotonic - 5.0, epoch.monotonic + 9.0, None,
                         epoch.monotonic + 9.5, epoch.monotonic + 9.2):
            delivered = asyncio.create_task(track.deliver(rgb, captured))
            out.append((await track.recv()).pts)
            await delivered
        out.append((await track.recv()).pts)  # nothing new for 50 ms: the held frame again
        track.stop()
        return epoch, track, out

    epoch, track, pts = asyncio.run(run())
    assert pts[0] == 0                      # before the epoch: from its start
    assert pts[1] == 9 * 90_000             # its drive's capture
    assert pts[2] > pts[1]                  # no capture: after the last, never back
    assert pts[3] == int(9.5 * 90_000)
    # an older capture (no new drive), then the held frame: one picture lag (0.5 s, the
    # last frame's) before their sending, i.e. just after the last capture here
    assert pts[3] < pts[4] < pts[5]
    assert pts[5] / 90_000 == pytest.approx(9.5, abs=0.2)
    assert all(b > a for a, b in zip(pts, pts[1:], strict=False))
    assert track.stamps.captured_at(pts[1]) == pytest.approx(epoch.monotonic + 9.0)


def test_a_picture_lagging_past_the_bound_is_stamped_at_the_bound():
    """A loaded server's picture 5 s behind its drive is stamped max_lag_s before its sending,
    so a browser syncing the voice to it holds the voice at most that long; a frame within the
    bound keeps its drive's capture instant, and frames of no new drive keep the bounded lag."""
    from server.webrtc.sender_clock import CaptureEpoch
    from server.webrtc.track import LatestFrameTrack

    rgb = np.zeros((8, 8, 3), np.uint8)

    async def run():
        epoch = CaptureEpoch(time.monotonic() - 10.0, 0)
        track = LatestFrameTrack(repeat_after_s=0.05, epoch=epoch, max_lag_s=0.5)
        out = []
        for captured in (time.monotonic() - 5.0, None, time.monotonic() - 0.1):
            delivered = asyncio.create_task(track.deliver(rgb, captured))
            sent = time.monotonic()
            out.append(((await track.recv()).pts, sent, captured))
            await delivered
        track.stop()
        return epoch, track, out

    epoch, track, out = asyncio.run(run())
    at = [epoch.monotonic + pts / 90_000 for pts, _, _ in out]
    assert out[0][1] - at[0] == pytest.approx(0.5, abs=0.05)  # 5 s behind: stamped 0.5 s
    assert out[1][1] - at[1] == pytest.approx(0.5, abs=0.05)  # no new drive: the same lag
    assert at[2] == pytest.approx(out[2][2], abs=1e-4)         # within the bound: as captured
    assert track.lag_clamped == 1  # the lagging frame; the next one already keeps the bound


def test_voice_timestamps_stay_continuous_from_the_first_capture():
    from server.rooms.voice import VoicePacket
    from server.webrtc.audio import VoiceTrack
    from server.webrtc.sender_clock import CaptureEpoch

    class Queue:
        def __init__(self, packets):
            self.packets = list(packets)

        async def next(self):
            return self.packets.pop(0) if self.packets else None

        def close(self):
            pass

    epoch = CaptureEpoch(100.0, 0)
    packets = [VoicePacket(b"\xf8", 480_000 + 960 * i, 101.0 + 0.02 * i,
                           captured_at=100.5 + 0.02 * i + (0.003 if i == 2 else 0.0))
               for i in range(3)]
    track = VoiceTrack(Queue(packets), 0, epoch)

    async def run():
        return [(await track.recv()).pts for _ in packets]

    pts = asyncio.run(run())
    assert pts == [24_000, 24_960, 25_920]  # 0.5 s after the epoch, then 20 ms steps
    # each keeps its own capture instant for the reports (the third's estimate moved 3 ms)
    assert track.stamps.captured_at(pts[2]) == pytest.approx(100.543)


def test_aiortc_sender_still_has_what_the_capture_clock_reads():
    """Fails loudly when aiortc's RTCRtpSender changes the private state sender_clock.py
    reads and replaces (then the reports would silently stay on the send time)."""
    from aiortc import RTCPeerConnection

    from server.webrtc.sender_clock import (
        SENDER_LAST_RTP,
        SENDER_LSR,
        SENDER_NEXT_FRAME,
        SENDER_SEND_RTCP,
        CaptureEpoch,
        CaptureStamps,
        report_capture_clock,
    )

    class Stamped:
        stamps = CaptureStamps()

    async def run():
        pc = RTCPeerConnection()
        sender = pc.addTransceiver("video", direction="sendonly").sender
        names = [hasattr(sender, n) for n in (SENDER_LAST_RTP, SENDER_LSR, SENDER_NEXT_FRAME,
                                               SENDER_SEND_RTCP)]
        installed = report_capture_clock(sender, Stamped(), CaptureEpoch.now())
        replaced = getattr(sender, SENDER_SEND_RTCP).__name__
        await pc.close()
        return names, installed, replaced

    names, installed, replaced = asyncio.run(run())
    assert all(names) and installed and replaced == "send_reports"


# -- real peers ----------------------------------------------------------------------------------


def clicking_performer_errors(srv, video: bool = True, voice_mix: bool = False
                              ) -> tuple[list[float], list[float]]:
    """A performer clicking and driving, a viewer (of its seat's voice, or of the mix): each
    frame's and each click's offset from its capture by the viewer's sender reports (ms);
    ``video`` False: the clicks only."""
    room = create_room(srv)
    perform, watch = invite(srv, room["id"], "perform"), invite(srv, room["id"], "watch")

    async def run():
        mic = click_track(click_every=CLICK_EVERY)
        async with WhepViewer(srv.url, room["id"], perform["token"], microphone=mic,
                              width=SIZE, height=SIZE, timeout_s=TIMEOUT_S) as pv, \
                WhepViewer(srv.url, room["id"], watch["token"], voices=1, stamp=True,
                           voice_mix=voice_mix, width=SIZE, height=SIZE,
                           timeout_s=TIMEOUT_S) as v:
            reports = Reports(v)
            await pv.wait_open()
            performer = Performer(pv, lambda now: now)
            driving = asyncio.create_task(performer.drive())
            await asyncio.sleep(WARM_S)
            until = time.monotonic() + LISTEN_S
            frames = video_errors(v, reports, [performer], until) if video else asyncio.sleep(
                0, result=[])
            errors = await asyncio.gather(frames, audio_errors(v, reports, [mic], until))
            performer.running = False
            await driving
            return errors

    return asyncio.run(run())


def test_a_frame_and_a_packet_captured_together_map_to_one_ntp_time(srv):
    video, audio = clicking_performer_errors(srv)
    assert_on_capture(video, "video", least=ENOUGH)
    assert_on_capture(audio, "audio", least=ENOUGH)
    assert abs(np.median(video) - np.median(audio)) <= TOLERANCE_MS, (video, audio)


def test_the_mix_maps_to_its_sounds_capture_not_its_own_latency(srv):
    """A mix viewer's clicks (decoded, summed, encoded again, cushioned 40 ms) map through the
    sender reports to the instants they were captured, as a seat's own track does."""
    _, audio = clicking_performer_errors(srv, video=False, voice_mix=True)
    # The mix decodes and encodes again: its 20 ms frames need not start where the mic's did
    # (the decoders' delays), so a click falls anywhere within one: a frame of tolerance.
    # Stamped at mix time instead, this measured +49.6 ms (its cushion and look-ahead).
    assert_on_capture(audio, "mixed audio", least=ENOUGH, tolerance_ms=20.0)


def test_video_alone_and_drives_without_a_capture_time(srv):
    """No audio track: the video's reports alone are on the capture clock; a drive with no
    t_capture counts its arrival as its capture (its send time here, give or take transit)."""
    room = create_room(srv)
    perform, watch = invite(srv, room["id"], "perform"), invite(srv, room["id"], "watch")

    async def run():
        async with WhepViewer(srv.url, room["id"], perform["token"], width=SIZE, height=SIZE,
                              timeout_s=TIMEOUT_S) as pv, \
                WhepViewer(srv.url, room["id"], watch["token"], stamp=True, width=SIZE,
                           height=SIZE, timeout_s=TIMEOUT_S) as v:
            assert [t.kind for t in v.pc.getTransceivers()] == ["video"]
            reports = Reports(v)
            await pv.wait_open()
            performer = Performer(pv, lambda now: None)
            driving = asyncio.create_task(performer.drive())
            await asyncio.sleep(WARM_S)
            video = await video_errors(v, reports, [performer], time.monotonic() + LISTEN_S)
            performer.running = False
            await driving
            return video, reports

    video, reports = asyncio.run(run())
    assert not reports.reports["audio"]
    assert_on_capture(video, "video without t_capture", least=ENOUGH)


def test_a_new_performer_on_another_clock_takes_the_seat(srv):
    """The first performer leaves; a second (its clock 1000 s behind, as a restarted page's
    performance.now()) takes the seat while the viewer stays: the video's RTP timestamps
    never go back, and both tracks are on the new performer's capture clock again."""
    room = create_room(srv)
    perform, watch = invite(srv, room["id"], "perform"), invite(srv, room["id"], "watch")
    behind = min(1000.0, time.monotonic() / 2)

    async def run():
        first_mic, second_mic = click_track(CLICK_EVERY), click_track(CLICK_EVERY)
        async with WhepViewer(srv.url, room["id"], watch["token"], voices=1, stamp=True,
                              width=SIZE, height=SIZE, timeout_s=TIMEOUT_S) as v:
            reports = Reports(v)
            async with WhepViewer(srv.url, room["id"], perform["token"], microphone=first_mic,
                                  width=SIZE, height=SIZE, timeout_s=TIMEOUT_S) as pv:
                await pv.wait_open()
                first = Performer(pv, lambda now: now)
                driving = asyncio.create_task(first.drive())
                await asyncio.sleep(WARM_S)
                first.running = False
                await driving
            async with WhepViewer(srv.url, room["id"], perform["token"],
                                  microphone=second_mic, width=SIZE, height=SIZE,
                                  timeout_s=TIMEOUT_S) as pv:
                await pv.wait_open()
                joined = time.monotonic()  # the voice queued at the viewer before: the first's
                second = Performer(pv, lambda now: now - behind, seq0=first.seq)
                driving = asyncio.create_task(second.drive())
                await asyncio.sleep(WARM_S)  # the old performer's frames and voice drain
                until = time.monotonic() + LISTEN_S
                video, audio = await asyncio.gather(
                    video_errors(v, reports, [second], until),
                    audio_errors(v, reports, [second_mic], until, since=joined))
                second.running = False
                await driving
            return video, audio, reports.video_ts

    video, audio, video_ts = asyncio.run(run())
    seqs = np.unwrap(np.asarray(list(video_ts)), period=2**16)
    steps = np.diff(np.asarray(list(video_ts.values()), dtype=np.int64)[np.argsort(seqs)])
    steps = (steps + 2**31) % 2**32 - 2**31
    assert (steps >= 0).all(), steps[steps < 0]  # a frame's packets share one; never back
    assert_on_capture(video, "video after the restart", least=ENOUGH)
    assert_on_capture(audio, "audio after the restart", least=ENOUGH)
