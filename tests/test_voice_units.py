"""The voice's parts without peers: the Opus packet check against libopus' own packets
(PyAV's encoder) and hand-made malformed ones; a seat's voice: bounds, counting, the delay,
the continuous timeline, listeners' buffers."""

from __future__ import annotations

import asyncio
import fractions
import time

import av
import numpy as np
import pytest

from protocol.opus import OpusPacketError, packet_duration_ms
from server.config import Settings
from server.rooms.voice import CLOCK_RATE, SeatVoice


def libopus_packets(frame_ms: float, bit_rate: int, count: int = 20) -> list[bytes]:
    """Real Opus packets of noise from libopus (PyAV), ``frame_ms`` each."""
    codec = av.CodecContext.create("libopus", "w")
    codec.sample_rate, codec.layout, codec.format = 48000, "mono", "s16"
    codec.bit_rate = bit_rate
    codec.options = {"frame_duration": str(frame_ms)}
    samples = int(48000 * frame_ms / 1000)
    rng = np.random.default_rng(0)
    packets = []
    for i in range(count):
        frame = av.AudioFrame.from_ndarray(
            rng.integers(-8000, 8000, (1, samples), dtype=np.int16), format="s16",
            layout="mono")
        frame.sample_rate, frame.pts = 48000, i * samples
        frame.time_base = fractions.Fraction(1, 48000)
        packets += [bytes(p) for p in codec.encode(frame)]
    return packets


@pytest.mark.parametrize("frame_ms, bit_rate", [(2.5, 64000), (10, 24000), (20, 64000),
                                                (60, 32000), (120, 96000)])
def test_libopus_packets_pass_with_their_duration(frame_ms, bit_rate):
    packets = libopus_packets(frame_ms, bit_rate)
    assert packets
    for packet in packets:
        assert packet_duration_ms(packet) == pytest.approx(frame_ms)


@pytest.mark.parametrize("packet, rule", [
    (b"", "R1"),
    (b"\xf8" + bytes(1276), "R2"),
    (b"\xf9" + bytes(3), "R3"),
    (b"\xfa", "ends inside"),
    (b"\xfa\x09" + bytes(4), "R4"),
    (b"\xfb", "R6"),
    (b"\xfb\x00", "R5"),
    (b"\x1b\x03", "R5"),          # three 60 ms frames: 180 ms
    (b"\xfb\x41\xff\xff", "padding"),
    (b"\xfb\x02" + bytes(5), "R6"),  # CBR, two frames in 5 bytes: unequal
    (b"\xfb\x82\xfc\xff" + bytes(8), "R7"),
])
def test_malformed_packets_are_refused_by_rule(packet, rule):
    with pytest.raises(OpusPacketError, match=rule):
        packet_duration_ms(packet)


def voice(**overrides) -> SeatVoice:
    return SeatVoice(Settings(**overrides))


def test_bounds_drop_and_count_and_only_valid_packets_reach_listeners():
    seat = voice(voice_max_packet_bytes=200, voice_max_bitrate=16_000, voice_buffer_packets=128)
    async def run():
        listener = seat.subscribe()
        now = time.monotonic()
        # 80 B every 20 ms is twice 16 kbit/s: after one second's burst (2000 B) half go.
        outcomes = [seat.publish("p", b"\xf8" + bytes(79), i * 960, now + i * 0.02)
                    for i in range(100)]
        outcomes += [seat.publish("p", b"\xf8" + bytes(300), 0, now + 2.0),
                     seat.publish("p", b"\xfb\x00", 0, now + 2.0)]
        got = []
        while listener._queue:
            got.append(await listener.next())
        return outcomes, got

    outcomes, got = asyncio.run(run())
    assert outcomes[-2:] == ["too_large", "garbage"]
    rate = outcomes[:100].count("rate")
    assert 24 <= rate <= 28, rate  # 2000 + 1.98 s * 2000 B/s allowed: 74 of 100 packets
    assert len(got) == outcomes.count("forwarded") == 100 - rate
    assert seat.counts["rate"] == rate and seat.counts["garbage"] == 1


def test_the_timeline_is_continuous_across_publishers_and_wraps():
    seat = voice()
    now = 100.0
    ts = [seat._timeline("a", 2**32 - 960, now), seat._timeline("a", 0, now + 0.02),
          seat._timeline("a", 960, now + 0.04)]
    assert ts[1] - ts[0] == 960 and ts[2] - ts[1] == 960  # the 32-bit wrap unwrapped
    seat.last_packet_at = now + 0.04
    nxt = seat._timeline("b", 123456, now + 1.04)  # a new performer a second later
    assert nxt - ts[2] == CLOCK_RATE


def test_a_listener_waits_the_median_picture_lag_bounded():
    seat = voice(voice_max_delay_s=0.2, voice_pacing="frames")  # even: the slew test below
    listener = seat.subscribe()
    for drive, lag in enumerate([0.05, 0.06, 0.3, 0.07, 0.08]):
        listener.follow_picture(100.0 + drive, 100.0 + drive + lag)
        listener.follow_picture(100.0 + drive, 200.0)  # later frames of a drive: no lag
    assert listener.delay_s == pytest.approx(0.07)  # one slow render moves nothing
    for drive in range(5, 20):
        listener.follow_picture(100.0 + drive, 101.0 + drive)
    assert listener.delay_s == 0.2  # bounded by voice_max_delay_s

    async def run():
        sent = time.monotonic()
        seat.publish("p", b"\xf8\x00", 0)
        await listener.next()
        return time.monotonic() - sent

    assert asyncio.run(run()) >= 0.2


def test_a_packet_waits_for_the_frame_of_its_drive_and_never_past_the_bound():
    drive = {"arrived": None}
    seat = SeatVoice(Settings(voice_max_delay_s=0.5, voice_pacing="frames"),
                     drive_arrived=lambda: drive["arrived"])
    watching, hearing = seat.subscribe(), seat.subscribe()  # the second follows no picture

    async def run():
        now = time.monotonic()
        watching.follow_picture(now - 1.0, now - 0.95)  # the picture's lag: 50 ms
        drive["arrived"] = time.monotonic()  # a new drive, whose frame is slow
        seat.publish("p", b"\xf8\x00", 0)
        heard = await asyncio.wait_for(hearing.next(), 1)  # no picture to wait for
        got = asyncio.create_task(watching.next())
        await asyncio.sleep(0.2)
        waited = not got.done()  # past the 50 ms median: the frame has not left yet
        watching.follow_picture(drive["arrived"], time.monotonic())  # now it has
        released = (await asyncio.wait_for(got, 1)) is not None
        drive["arrived"] = time.monotonic()  # a drive whose frame never leaves
        seat.publish("p", b"\xf8\x00", 960)
        sent = time.monotonic()
        await asyncio.wait_for(watching.next(), 2)
        return heard, waited, released, time.monotonic() - sent

    heard, waited, released, bounded = asyncio.run(run())
    assert heard is not None and waited and released
    assert bounded >= 0.5 - 0.01  # voice_max_delay_s after its arrival, not forever


def test_even_pacing_releases_a_burst_at_its_own_cadence_behind_the_picture():
    """After a second of packets on time, five that arrive together (a stalled network) leave
    20 ms apart, each at its paced time plus the picture's lag; a lag that jumps moves the
    delay at DELAY_SLEW only."""
    from server.rooms.voice import DELAY_SLEW

    seat = voice(voice_max_delay_s=0.5, voice_pacing="even")
    listener = seat.subscribe()

    async def run():
        t0 = time.monotonic()
        base = t0 - 1.0
        listener.follow_picture(t0 - 2.0, t0 - 1.9)  # the picture lags 100 ms
        for i in range(50):  # on time, in the past: released at once
            seat.publish("p", b"\xf8\x00", i * 960, base + 0.02 * i)
        for _ in range(50):
            await listener.next()
        now = time.monotonic()
        first = round((now - 0.08 - base) / 0.02)  # due 80 ms ago, arriving only now
        for j in range(5):
            seat.publish("p", b"\xf8\x00", (first + j) * 960, now)
        out = []
        for _ in range(5):
            packet = await listener.next()
            out.append(time.monotonic() - (packet.paced + 0.1))
        for k in range(2):  # the lag jumps to 300 ms ...
            listener.follow_picture(t0 - 0.5 + k * 0.1, t0 - 0.2 + k * 0.1)
        delay = listener.delay_s
        await asyncio.sleep(0.5)
        seat.publish("p", b"\xf8\x00", (first + 30) * 960)
        await listener.next()
        return out, delay, listener.paced_delay_s

    out, delay, paced = asyncio.run(run())
    assert all(-0.002 <= late <= 0.03 for late in out), out  # not all five at once
    assert delay == pytest.approx(0.3)  # EVEN_LAG_QUANTILE of 100, 300, 300 ms
    assert 0.1 < paced < 0.1 + DELAY_SLEW * 1.0  # ... is followed slowly (about 0.5 s)


def test_frames_pacing_releases_a_drives_packets_with_its_frame():
    drive = {"arrived": None}
    seat = SeatVoice(Settings(voice_max_delay_s=0.5, voice_pacing="frames"),
                     drive_arrived=lambda: drive["arrived"])
    listener = seat.subscribe()

    async def run():
        now = time.monotonic()
        listener.follow_picture(now - 1.0, now - 0.99)
        drive["arrived"] = now
        for i in range(5):
            seat.publish("p", b"\xf8\x00", i * 960, now + 0.02 * i)
        got = [asyncio.create_task(listener.next()) for _ in range(1)]
        await asyncio.sleep(0.2)
        waiting = not got[0].done()
        listener.follow_picture(now, time.monotonic())
        out = [await got[0]] + [await listener.next() for _ in range(4)]
        return waiting, time.monotonic() - now, out

    waiting, took, out = asyncio.run(run())
    assert waiting and len(out) == 5 and took < 0.35  # all five at once, with the frame


def test_a_full_listener_drops_its_oldest_and_counts():
    seat = voice(voice_buffer_packets=4)
    listener = seat.subscribe()
    for i in range(10):
        seat.publish("p", b"\xf8\x00", i * 960)
    assert [p.media_ts for p in listener._queue][-1] - listener._queue[0].media_ts == 3 * 960
    assert seat.counts["overflow"] == 6 and listener.overflowed == 6
    listener.close()
    assert not seat.listeners


def test_speaking_presence_is_sent_at_most_once_per_interval():
    from server.rooms.live import LiveRoom
    from server.rooms.registry import Room, SeatSpec
    from server.rooms.voice import seat_voice

    settings = Settings(voice_presence_interval_s=0.5)
    packet = libopus_packets(20, 32000, 1)[0]

    class Listening:  # a participant as presence sees one: its role and control queue
        role = "watch"

        def __init__(self) -> None:
            self.sent: list[tuple[float, object]] = []

        def send_control(self, message) -> None:
            self.sent.append((time.monotonic(), message))

    async def run() -> list:
        room = Room("r", "r", "owner", [SeatSpec(0, "demo")], time.time())
        live = LiveRoom(room, None, settings)
        who = Listening()
        live.participants.append(who)
        voice = seat_voice(live.seats[0], settings)
        for i in range(8):  # loud, then 0.35 s quiet (past SPEAKING_S): it flips each time
            voice.publish(voice, packet, i * 960 * 20, level_dbov=-10.0)
            await asyncio.sleep(0.35)
        voice.publish(voice, packet, 10**6, level_dbov=-100.0)  # a quiet packet: no flip
        for _ in range(100):  # the end of speech is announced within SPEAKING_S + interval
            if not (live.speaking()[0] or live._announced[0]):
                break
            await asyncio.sleep(0.05)
        return who.sent

    sent = asyncio.run(run())
    times = [t for t, _ in sent]
    assert len(sent) >= 2 and sent[0][1].seats[0].speaking and not sent[-1][1].seats[0].speaking
    assert min(np.diff(times)) >= 0.5  # 16 flips of the voice, no update closer than that
    assert len(sent) < 16


def test_gaps_between_packets_that_follow_each_other_are_counted_at_both_stages():
    """voice_gap_ms{stage}: in as the seat got them, out as a listener took them; a silence
    (the media time jumps) or a packet of no known length is no gap."""
    from server.metrics import ServerMetrics

    metrics = ServerMetrics()
    seat = SeatVoice(Settings(voice_max_delay_s=0.0), metrics)
    listener = seat.subscribe()
    start = time.monotonic()  # each packet is released at its arrival (bounded: 0.4 s)
    at = [start + t for t in (0.0, 0.02, 0.1, 0.12, 0.4)]  # an 80 ms gap, then a silence
    rtp = [0, 960, 1920, 2880, 2880 + 960 * 3]

    async def run():
        for t, ts in zip(at, rtp, strict=True):
            assert seat.publish("p", b"\xf8\x00", ts, t) == "forwarded"
            await listener.next()

    asyncio.run(run())

    def count(stage: str, le: str) -> float:
        return metrics.registry.get_sample_value(
            "telesplat_voice_gap_ms_bucket", {"stage": stage, "le": le})

    assert count("in", "+Inf") == 3  # three packets followed the one before in media time
    assert count("in", "75.0") == 2 and count("in", "100.0") == 3  # 20, 80 and 20 ms
    assert count("out", "+Inf") == 3 and count("out", "75.0") <= 2  # out follows in
