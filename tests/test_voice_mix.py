"""The room's mixed voice on request (issue 30) on a real uvicorn with real aiortc peers: two
performers speak two tones in a two-seat room; a WHEP viewer that asks ``?voice=mix`` hears
both in its one audio track, a WebSocket viewer (``hello.voice_mix``) in its ``voice``
messages; the mix runs once for both, only while someone asked, and never for a performer."""

from __future__ import annotations

import asyncio
import fractions
import time

import av
import numpy as np
import pytest

from protocol import Voice, encode
from server.rooms.voice_mix import FRAME, PREBUFFER_FRAMES, MixCodec, SeatDecoder, tone_packets
from tests.server_fixtures import is_type, recv_until, run_server, wait_until
from tests.test_server_rooms import create_room, invite, join, live, rest
from tests.voice_fixtures import RATE

pytest.importorskip("aiortc")

SIZE = 64
TONES = (440.0, 1000.0)  # seat 0's and seat 1's
LISTEN_S = 2.0
TIMEOUT_S = 30.0


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    with run_server(tmp_path_factory.mktemp("voice_mix"), default_width=SIZE,
                    default_height=SIZE, default_max_fps=10) as running:
        yield running


def tone_track(freq: float):
    """A microphone that says one sine tone, 20 ms frames in real time."""
    from aiortc import MediaStreamTrack

    class Tone(MediaStreamTrack):
        kind = "audio"

        def __init__(self) -> None:
            super().__init__()
            self.sent, self._start = 0, None

        async def recv(self):
            if self._start is None:
                self._start = time.monotonic()
            due = self._start + self.sent * FRAME / RATE
            await asyncio.sleep(max(0.0, due - time.monotonic()))
            t = (np.arange(FRAME) + self.sent * FRAME) / RATE
            samples = (np.sin(2 * np.pi * freq * t) * 8000).astype(np.int16)[None]
            frame = av.AudioFrame.from_ndarray(samples, format="s16", layout="mono")
            frame.sample_rate, frame.pts = RATE, self.sent * FRAME
            frame.time_base = fractions.Fraction(1, RATE)
            self.sent += 1
            return frame

    return Tone()


def tone_levels(samples: np.ndarray, rate: int = RATE) -> dict[float, float]:
    """Each tone's share of the signal's spectral magnitude (a Hann-windowed FFT)."""
    spectrum = np.abs(np.fft.rfft(samples * np.hanning(len(samples))))
    freqs = np.fft.rfftfreq(len(samples), 1 / rate)
    total = spectrum.sum() or 1.0
    return {f: float(spectrum[np.abs(freqs - f) < 15].sum() / total) for f in TONES}


def mono(frame) -> np.ndarray:
    """A decoded frame's samples as float mono (aiortc gives packed s16, stereo or mono)."""
    pcm = frame.to_ndarray().astype(np.float32).reshape(-1)
    channels = len(frame.layout.channels)
    return pcm.reshape(-1, channels).mean(axis=1) / 32768.0


def two_seat_room(srv):
    room = create_room(srv, seats=[{"avatar": "demo"}, {"avatar": "demo"}])
    performers = [invite(srv, room["id"], "perform", seat=i) for i in (0, 1)]
    return room, performers, invite(srv, room["id"], "watch")


def test_without_the_mix_a_viewer_hears_each_seat_on_its_own_line(srv):
    """Two seats, two voice lines, each seat's tone on its own: the second line used to stay
    silent (aiortc's balanced bundling left it on a transport that never connected)."""
    from client.webrtc import WhepViewer

    room, performers, watch = two_seat_room(srv)

    def peer(token: str, **kwargs) -> WhepViewer:
        return WhepViewer(srv.url, room["id"], token, width=SIZE, height=SIZE,
                          timeout_s=TIMEOUT_S, **kwargs)

    async def heard(viewer: WhepViewer, seat: int) -> np.ndarray:
        frames = []
        while len(frames) * FRAME < LISTEN_S * RATE:
            frame, _ = await viewer.next_audio(seat)
            frames.append(mono(frame))
        return np.concatenate(frames)

    async def run():
        async with peer(performers[0]["token"], microphone=tone_track(TONES[0])), \
                peer(performers[1]["token"], microphone=tone_track(TONES[1])), \
                peer(watch["token"], voices=2) as viewer:
            await viewer.next_frame()
            return await asyncio.gather(heard(viewer, 0), heard(viewer, 1))

    lines = [tone_levels(samples[len(samples) // 2:]) for samples in asyncio.run(run())]
    for seat, levels in enumerate(lines):  # its own tone, not the other seat's
        assert levels[TONES[seat]] > 0.3 and levels[TONES[1 - seat]] < 0.05, (seat, lines)


def test_a_viewer_asking_for_the_mix_hears_both_seats_in_one_track(srv):
    from client.webrtc import WhepError, WhepViewer

    room, performers, watch = two_seat_room(srv)

    def peer(token: str, **kwargs) -> WhepViewer:
        return WhepViewer(srv.url, room["id"], token, width=SIZE, height=SIZE,
                          timeout_s=TIMEOUT_S, **kwargs)

    async def run():
        async with peer(performers[0]["token"], microphone=tone_track(TONES[0])), \
                peer(performers[1]["token"], microphone=tone_track(TONES[1])), \
                peer(watch["token"], voices=1, voice_mix=True) as mixed, \
                join(srv, room["id"], watch["token"], voice_mix=True) as ws_viewer:
            await mixed.next_frame()
            mix = live(srv, room["id"]).voice_mix
            heard, at = [], time.monotonic()
            while time.monotonic() < at + 1.0:  # the tones reach the mix
                await mixed.next_audio()
            mixed_before = mix.counts["mixed"]
            while len(heard) * FRAME < LISTEN_S * RATE:
                frame, _ = await mixed.next_audio()
                heard.append(mono(frame))
            rate = (mix.counts["mixed"] - mixed_before) / (time.monotonic() - at - 1.0)
            messages = [await recv_until(ws_viewer, is_type("voice")) for _ in range(100)]
            state = len(mix.subscribers), mix.running, dict(mix.counts)
            try:  # a performer may not ask: the one mix would hold its own voice
                async with peer(performers[0]["token"], voices=1, voice_mix=True):
                    refused = None
            except WhepError as exc:
                refused = exc
        return np.concatenate(heard), messages, state, rate, refused, mix

    samples, messages, (subscribers, running, counts), rate, refused, mix = asyncio.run(run())
    levels = tone_levels(samples)
    print(f"WHEP mix tone shares {levels}, mixed frames/s {rate:.1f}")
    assert all(share > 0.15 for share in levels.values()), levels  # both voices in one track
    assert subscribers == 2 and running
    assert 40 <= rate <= 60, rate  # one 20 ms frame at a time for both viewers: mixed once
    assert "unmixed" not in counts
    # the WebSocket viewer's messages: the mix (no seat), both tones in them; stamped on its
    # picture seat's clock once that performer's reports came (WHEP microphones: RTCP)
    assert all(m.seat is None for m in messages)
    stamps = [m.t_capture for m in messages if m.t_capture is not None]
    assert stamps == sorted(stamps), stamps
    decoder = av.CodecContext.create("libopus", "r")
    decoder.sample_rate, decoder.layout = RATE, "mono"
    pcm = np.concatenate([f.to_ndarray().reshape(-1).astype(np.float32) / 32768
                          for m in messages for f in decoder.decode(av.Packet(m.data))])
    ws_levels = tone_levels(pcm[len(pcm) // 4:])
    assert all(share > 0.15 for share in ws_levels.values()), ws_levels
    assert refused is not None and refused.status == 400 and "viewers" in str(refused.detail)
    # everyone gone: nothing runs
    wait_until(lambda: not mix.running and not mix.subscribers, TIMEOUT_S,
               what="the mix stopped with its last viewer")


async def speak_to_the_mix(srv, room, performers, watch, voice_of) -> tuple[list, dict]:
    """Both performers over the WebSocket for 2 s, 20 ms apart: ``voice_of(seat, i)`` is
    packet ``i`` of a seat (None: silent then). The first 60 messages a mix viewer got and the
    mix's counts."""
    async with join(srv, room["id"], performers[0]["token"]) as first, \
            join(srv, room["id"], performers[1]["token"]) as second, \
            join(srv, room["id"], watch["token"], voice_mix=True) as viewer:
        await recv_until(viewer, is_type("frame"))
        start = time.monotonic()
        for i in range(100):
            for seat, ws in enumerate((first, second)):
                voice = voice_of(seat, i)
                if voice is not None:
                    await ws.send(encode(voice))
            await asyncio.sleep(max(0.0, start + (i + 1) / 50 - time.monotonic()))
        messages = [await recv_until(viewer, is_type("voice")) for _ in range(60)]
        return messages, dict(live(srv, room["id"]).voice_mix.counts)


def test_the_mix_sums_at_most_voice_mix_max_seats(srv):
    """A mix bounded to one seat plays the first seat to speak; the other's packets are dropped
    and counted until the first falls silent."""
    room, performers, watch = two_seat_room(srv)
    settings = srv.ctx.settings
    before = settings.voice_mix_max_seats
    settings.voice_mix_max_seats = 1
    opus = [tone_packets(f, 100) for f in TONES]

    def voice_of(seat: int, i: int) -> Voice | None:
        # the second speaks later: the mix is full
        return Voice(seq=i, data=opus[seat][i]) if seat == 0 or i >= 10 else None

    try:
        messages, counts = asyncio.run(speak_to_the_mix(srv, room, performers, watch,
                                                        voice_of))
    finally:
        settings.voice_mix_max_seats = before
    decoder = av.CodecContext.create("libopus", "r")
    decoder.sample_rate, decoder.layout = RATE, "mono"
    pcm = np.concatenate([f.to_ndarray().reshape(-1).astype(np.float32) / 32768
                          for m in messages for f in decoder.decode(av.Packet(m.data))])
    levels = tone_levels(pcm[len(pcm) // 4:])
    assert levels[TONES[0]] > 0.15 and levels[TONES[1]] < 0.02, levels
    assert counts["unmixed"] >= 80, counts
    assert all(m.t_capture is None for m in messages)  # its performers stamp nothing


def test_the_websocket_mix_carries_capture_times_on_its_pictures_clock(srv):
    """The picture seat's performer stamps its voice (its clock at 50 s); the other seat's
    stamps are on a clock of its own (at 9000 s). The mix's messages carry the capture instants
    of what they hold on the picture seat's clock: 20 ms apart, within the stamps sent."""
    room, performers, watch = two_seat_room(srv)
    opus = [tone_packets(f, 100) for f in TONES]

    def voice_of(seat: int, i: int) -> Voice:
        return Voice(seq=i, data=opus[seat][i], t_capture=(50, 9000)[seat] + i / 50)

    messages, _ = asyncio.run(speak_to_the_mix(srv, room, performers, watch, voice_of))
    stamps = [m.t_capture for m in messages]
    assert all(s is not None and 50 - 0.1 <= s <= 52 + 0.1 for s in stamps), stamps
    steps = np.diff(stamps)
    assert abs(float(np.median(steps)) - 0.02) < 0.002 and (steps > 0).all(), steps


def test_a_performer_cannot_ask_the_websocket_for_the_mix(srv):
    room, performers, _ = two_seat_room(srv)

    async def run():
        async with join(srv, room["id"], performers[0]["token"], welcome=False,
                        voice_mix=True) as ws:
            return await recv_until(ws, is_type("error"))

    error = asyncio.run(run())
    assert error.code == "invalid" and "viewers" in error.message
    assert live(srv, room["id"]) is None or live(srv, room["id"]).voice_mix is None


def test_the_mix_codec_sums_seats_cushions_and_bounds_their_backlog():
    codec = MixCodec(48_000, max_frames=8)
    a, b = tone_packets(TONES[0], 40), tone_packets(TONES[1], 40)
    assert codec.step([]) is None  # nothing to mix: nothing encoded
    assert codec.step([(0, a[0], None)]) is None  # one frame decoded: still cushioning
    out = codec.step([(0, a[1], None), (1, b[0], None), (1, b[1], None)])
    assert out is not None and all(isinstance(p, bytes) for p, _ in out)
    for i in range(2, 40):
        codec.step([(0, a[i], None), (1, b[i], None)])
    # a seat far ahead of the mix keeps at most max_frames of backlog
    for packet in a[:20]:
        codec.seats[0].add(packet)
    assert len(codec.seats[0].samples) <= 8 * FRAME and codec.seats[0].dropped > 0
    # garbage libopus refuses is skipped, not raised
    decoder = SeatDecoder(4 * FRAME)
    decoder.add(b"\xff\xff\xff")
    assert decoder.take() is None and PREBUFFER_FRAMES >= 1


def test_each_mixed_packet_carries_its_loudest_seats_capture_instant():
    """The mix is stamped with the capture of the sound it holds (not its own send time), so
    capture-clock sender reports count the mix's latency out: the loud seat's instants, one
    20 ms frame apart, through the cushion and the encoder's one-frame look-ahead."""
    codec = MixCodec(48_000, max_frames=16)
    loud, quiet = tone_packets(TONES[0], 30, 0.5), tone_packets(TONES[1], 30, 0.02)
    t0, skew = 1000.0, 0.3  # the quiet seat's sound was captured 300 ms later
    stamps = []
    for i in range(30):
        out = codec.step([(0, loud[i], t0 + i * 0.02), (1, quiet[i], t0 + skew + i * 0.02)])
        stamps += [at for _, at in out or ()]
    assert len(stamps) >= 25
    # in order, 20 ms apart, from the loud seat's first frame on (none from the quiet seat)
    assert stamps[0] == pytest.approx(t0, abs=1e-6)
    assert np.allclose(np.diff(stamps), 0.02, atol=1e-6)
    # a seat without capture instants leaves the stamp to the one that has them
    codec = MixCodec(48_000, max_frames=16)
    stamps = []
    for i in range(10):
        out = codec.step([(0, loud[i], None), (1, quiet[i], t0 + i * 0.02)])
        stamps += [at for _, at in out or ()]
    assert stamps and stamps[0] == pytest.approx(t0, abs=1e-6)


def test_the_whep_query_names_the_choice(srv):
    room, _, watch = two_seat_room(srv)
    r = rest(srv, "POST", f"/v1/rooms/{room['id']}/whep?voice=loud", watch["token"],
             content="v=0\r\n", headers={"Content-Type": "application/sdp"})
    assert r.status_code == 422 and "voice" in r.text




def test_cli_watch_voice_mix_records_the_mix(srv, tmp_path):
    import json
    import wave

    from client.cli import main as cli_main
    from client.stream import StreamClient

    room, performers, watch = two_seat_room(srv)
    opus = tone_packets(TONES[1], 50)  # one second of seat 1's tone
    out = tmp_path / "heard"
    argv = ["watch", "--room", room["id"], "--out", str(out), "--seconds", "120", "--frames",
            "3", "--size", "64", "--voice-mix", "--server", srv.url, "--token", watch["token"]]
    assert cli_main([*argv, "--voice"]) == 2  # one or the other

    async def run():
        async with await StreamClient.connect(srv.url, token=performers[1]["token"],
                                              room=room["id"]) as performer:
            recorder = asyncio.create_task(asyncio.to_thread(cli_main, argv))
            await performer.wait_presence(lambda p: p.viewers >= 1, timeout=60)
            await asyncio.sleep(0.5)  # its mix subscribed
            for packet in opus:
                await performer.voice(packet)
                await asyncio.sleep(0.02)
            for i in range(400):  # bounded; ends once the recorder has its frames
                if recorder.done():
                    break
                seq = await performer.drive(jaw_pose=[0.1 * (i % 5), 0.0, 0.0])
                await performer.wait_frame(seq, timeout=30)
            return await recorder

    assert asyncio.run(run()) == 0
    lines = [json.loads(x) for x in (out / "voice.jsonl").read_text().splitlines()]
    assert lines and all(x["seat"] is None for x in lines)
    assert not (out / "voice-seat1.wav").exists()
    with wave.open(str(out / "voice-mix.wav")) as wav:
        samples = np.frombuffer(wav.readframes(wav.getnframes()), np.int16)
    left = samples[0::2].astype(np.float32) / 32768
    assert len(left) >= 0.5 * RATE
    assert tone_levels(left)[TONES[1]] > 0.3  # seat 1's tone, through the mix
