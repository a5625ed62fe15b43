"""A seat's voice: the performer's Opus packets fanned out, undecoded, to the seat's listeners.

One :class:`SeatVoice` per seat, made when someone first publishes or listens. Each packet is
checked (protocol/opus.py: RFC 6716's rules, no decoding), bounded (``voice_max_packet_bytes``,
``voice_max_bitrate``) and counted; a valid one goes to every :class:`Listener`, each a bounded
queue (``voice_buffer_packets``, the oldest dropped past it). A listener that follows a picture
(a WebRTC viewer: :meth:`Listener.follow_picture`) holds the voice back so that it leaves with
the frames of its instant: the voice waits for the picture, never the other way round.

How it waits is ``voice_pacing``:

- ``frames`` (the default): a packet waits the median picture lag (from a drive's arrival
  to the frame that first shows it leaving for the encoder), then until the listener's
  picture shows the seat's drive of its instant (the newest drive that arrived before it, or
  up to ``DRIVE_SLACK_S`` after it), so the packets of one drive leave together with its
  frame, in bursts. A webcam image waiting or being tracked counts from its arrival, and a
  packet that came meanwhile skips the median wait: it waits for the frame of the drive
  tracked from that image only (tracking time varies by the image: a median would hold the
  voice of a quickly tracked one too long).
- ``even``: each packet leaves at its own cadence, its *paced* time (when it would typically
  arrive: its media time on the median arrival clock of the last ``ORIGIN_WINDOW_S``) plus
  the listener's picture delay, which follows the ``EVEN_LAG_QUANTILE`` of the recent lags
  at most ``DELAY_SLEW`` seconds per second: consecutive packets leave 20 ms apart (give or
  take 2 ms). Closer in Chromium, farther at aiortc viewers (docs/benchmarks.md, voice).

Either way never past ``voice_max_delay_s`` after its arrival.

Packets carry a media time in 48 kHz ticks: the publisher's RTP timestamps, unwrapped and made
continuous across publishers (a new performer goes on where the last one stopped), so a
listener's outgoing timestamps never jump back. Each also gets its capture instant on this
server's clock (its media time through an :class:`~..stream.capture_clock.ArrivalClock`,
restarted with each new publisher): what a WebRTC sender's timestamps and reports count
(server/webrtc/sender_clock.py). A seat nobody publishes to sends nothing and wakes nobody.

A seat speaks while a packet louder than ``voice_speaking_dbov`` came in the last
``SPEAKING_S`` (the level the sender put in the packet: RTP's RFC 6464 extension, or a
``voice`` message's ``level_dbov``; a packet without one counts as speech). The moment a seat
starts speaking it calls ``on_speaking`` (the room's presence, server/rooms/live.py), which
polls for the end.
"""

from __future__ import annotations

import asyncio
import bisect
import collections
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from protocol import Voice
from protocol.opus import OpusPacketError, packet_duration_ms

from ..stream.capture_clock import ArrivalClock

CLOCK_RATE = 48_000                 # Opus' RTP clock
DISCONTINUITY_TICKS = 5 * CLOCK_RATE  # a timestamp jump past this is a new stream, not a gap
SPEAKING_S = 0.3                    # a seat speaks while its last loud packet is this recent
LAG_SAMPLES = 15                    # picture lags the voice delay is the median of
DRIVE_SLACK_S = 0.02                # a drive this soon after a packet is of its instant (one
#                                     20 ms frame: a drive and its sound leave together)
ORIGIN_WINDOW_S = 2.0               # the paced clock: the median arrival over this long
DELAY_SLEW = 0.1                    # even pacing: delay_s moves at most 0.1 s per second (2 ms
#                                     per 20 ms packet: a stretch a jitter buffer absorbs)
EVEN_LAG_QUANTILE = 0.8             # even pacing follows this quantile of the lags, not the
#                                     median: a drive at a random instant waits for the render
#                                     under way, the freshest drive a render takes does not


@dataclass(frozen=True)
class VoicePacket:
    payload: bytes
    media_ts: int     # 48 kHz ticks on the seat's continuous timeline
    arrived: float    # time.monotonic() when the server got it
    t_capture: float | None = None  # its capture time on the performer's clock, when sent
    drive_arrived: float | None = None  # the seat's newest drive's arrival when it came
    paced: float | None = None  # when it typically arrives (monotonic): its even cadence
    tracking: bool = False  # came while its seat's webcam image was being tracked
    captured_at: float | None = None  # its capture instant on this server's clock (monotonic)
    ticks: int = 0    # its audio's duration (48 kHz ticks; 0: not known)


class GapWatch:
    """The time between packets that follow each other in media time (one starts where the
    last one's audio ended), into ``voice_gap_ms{stage}``: silences and restarts stay out."""

    def __init__(self, metrics: Any, stage: str) -> None:
        self._histogram = None if metrics is None else metrics.voice_gap_ms.labels(stage)
        self._end: int | None = None  # media time where the last packet's audio ended
        self._at = 0.0

    def saw(self, packet: VoicePacket, now: float) -> None:
        if self._histogram is not None and packet.ticks:
            if packet.media_ts == self._end:
                self._histogram.observe((now - self._at) * 1e3)
            self._end, self._at = packet.media_ts + packet.ticks, now


class Listener:
    """One participant's queue of a seat's packets (latest kept, oldest dropped)."""

    def __init__(self, voice: SeatVoice, capacity: int, max_delay_s: float,
                 pacing: str = "frames") -> None:
        self.voice = voice
        self.max_delay_s = max_delay_s
        self.pacing = pacing
        self.delay_s = 0.0          # the median picture lag (bounded)
        self.paced_delay_s = 0.0    # even pacing: delay_s approached at DELAY_SLEW
        self._paced_at: float | None = None
        self.lags: collections.deque[float] = collections.deque(maxlen=LAG_SAMPLES)
        self._shown_arrival: float | None = None  # None: this listener follows no picture
        self._shown = asyncio.Event()
        self._queue: collections.deque[VoicePacket] = collections.deque()
        self._capacity = capacity
        self._ready = asyncio.Event()
        self.closed = False
        self.overflowed = 0
        self._gaps = GapWatch(voice._metrics, "out")

    def put(self, packet: VoicePacket) -> bool:
        """Queue ``packet``; False when the oldest had to go to make room."""
        kept = len(self._queue) < self._capacity
        if not kept:
            self._queue.popleft()
            self.overflowed += 1
        self._queue.append(packet)
        self._ready.set()
        return kept

    async def next(self) -> VoicePacket | None:
        """The next packet once its release time has come; None once closed."""
        packet = await self._release()
        if packet is not None:
            self._gaps.saw(packet, time.monotonic())
        return packet

    async def _release(self) -> VoicePacket | None:
        while not self.closed:
            if not self._queue:
                self._ready.clear()
                await self._ready.wait()
                continue
            head, now = self._queue[0], time.monotonic()
            deadline = head.arrived + self.max_delay_s
            # a packet spoken with an image being tracked knows its frame: no median wait
            floor = 0.0 if head.tracking else self.delay_s
            if self.pacing == "even" and self._shown_arrival is not None:
                wait = min(self._even_release(head, now), deadline) - now
                if wait > 0:
                    await asyncio.sleep(wait)
                    continue
                return self._queue.popleft()
            wait = min(head.arrived + floor, deadline) - now
            if wait > 0:
                await asyncio.sleep(wait)
                continue
            if now < deadline and self._picture_behind(head):
                self._shown.clear()
                try:
                    await asyncio.wait_for(self._shown.wait(), deadline - now)
                except TimeoutError:
                    pass
                continue
            return self._queue.popleft()
        return None

    def _even_release(self, packet: VoicePacket, now: float) -> float:
        """``packet``'s paced time plus the picture delay, which moves toward ``delay_s`` at
        most ``DELAY_SLEW`` s per second (one render's jitter never bunches packets)."""
        if self._paced_at is not None:
            step = DELAY_SLEW * max(0.0, now - self._paced_at)
            self.paced_delay_s += min(step, max(-step, self.delay_s - self.paced_delay_s))
        self._paced_at = now
        paced = packet.arrived if packet.paced is None else packet.paced
        return paced + self.paced_delay_s

    def _picture_behind(self, packet: VoicePacket) -> bool:
        """Has this listener's picture yet to show the seat's drive of ``packet``'s instant?"""
        if self._shown_arrival is None:
            return False
        latest = self.voice.drive_arrived()
        target = (latest if latest is not None and latest <= packet.arrived + DRIVE_SLACK_S
                  else packet.drive_arrived)
        return target is not None and self._shown_arrival < target

    def follow_picture(self, arrived: float | None, now: float) -> None:
        """A frame showing the seat's drive that arrived at ``arrived`` leaves now: the first
        frame of each drive measures the picture's lag (versions made here, as a seat eases
        to rest, arrived at no time and measure nothing); the voice waits the median of the
        recent ones (jitter in one render moves nothing)."""
        if arrived is None or arrived == self._shown_arrival:
            return
        self._shown_arrival = arrived
        self._shown.set()
        self.lags.append(now - arrived)
        lag = (statistics.median(self.lags) if self.pacing == "frames"
               else sorted(self.lags)[int(EVEN_LAG_QUANTILE * (len(self.lags) - 1))])
        self.delay_s = min(max(0.0, lag), self.max_delay_s)
        if len(self.lags) == 1:
            self.paced_delay_s = self.delay_s  # the first lag: nothing to smooth yet

    def close(self) -> None:
        self.closed = True
        self._ready.set()
        self.voice.unsubscribe(self)


class SeatVoice:
    def __init__(self, settings: Any, metrics: Any = None,
                 on_speaking: Callable[[], None] | None = None,
                 drive_arrived: Callable[[], float | None] = lambda: None,
                 tracking: Callable[[], bool] = lambda: False) -> None:
        self.max_packet_bytes = settings.voice_max_packet_bytes
        self.drive_arrived = drive_arrived  # the seat's newest drive's arrival (monotonic)
        self.tracking = tracking  # is its webcam image being tracked (its drive to come)?
        self.speaking_dbov = settings.voice_speaking_dbov
        self.on_speaking = on_speaking
        self.loud_at: float | None = None
        self.max_bytes_per_s = settings.voice_max_bitrate / 8
        self.max_delay_s = settings.voice_max_delay_s
        self.buffer_packets = settings.voice_buffer_packets
        self.pacing = getattr(settings, "voice_pacing", "frames")
        # (arrival, arrived - media time) of the last ORIGIN_WINDOW_S, and those sorted: the
        # paced clock's origin is their median
        self._origins: collections.deque[tuple[float, float]] = collections.deque()
        self._sorted_origins: list[float] = []
        self._metrics = metrics
        self.listeners: set[Listener] = set()
        self.counts: collections.Counter[str] = collections.Counter()
        self.last_packet_at: float | None = None
        self._tokens = self.max_bytes_per_s  # burst: one second
        self._tokens_at = time.monotonic()
        self._last_in: int | None = None    # the publisher's last RTP timestamp
        self._last_out = 0                   # its place on the seat's timeline
        self._publisher: object | None = None
        self._capture_clock = ArrivalClock()  # the publisher's media time on our clock
        self._gaps = GapWatch(metrics, "in")

    @property
    def speaking(self) -> bool:
        return self.loud_at is not None and time.monotonic() - self.loud_at < SPEAKING_S

    def _heard(self, level_dbov: float | None, now: float) -> None:
        if level_dbov is not None and level_dbov < self.speaking_dbov:
            return
        was = self.speaking
        self.loud_at = now
        if not was and self.on_speaking is not None:
            self.on_speaking()

    # -- publishing ---------------------------------------------------------------------------

    def publish(self, publisher: object, payload: bytes, rtp_ts: int,
                now: float | None = None, t_capture: float | None = None,
                level_dbov: float | None = None, clock: ArrivalClock | None = None) -> str:
        """Check ``payload`` and fan it out; the outcome (a voice_packets label).
        ``level_dbov``: its audio level as the sender measured it (None: not given);
        ``clock``: the performer's own (its drives' too): a ``t_capture`` goes through it to
        this server's clock, so voice and frames land there by one transit estimate (without
        either: the media time through this voice's own clock)."""
        now = time.monotonic() if now is None else now
        outcome, ticks = self._check(payload, now)
        if outcome == "forwarded":
            media_ts = self._timeline(publisher, rtp_ts, now)
            captured_at = (clock.observe(t_capture, now)
                           if clock is not None and t_capture is not None
                           else self._capture_clock.observe(media_ts / CLOCK_RATE, now))
            packet = VoicePacket(payload, media_ts, now, t_capture, self.drive_arrived(),
                                 self._paced(media_ts, now), self.tracking(), captured_at,
                                 ticks)
            self._gaps.saw(packet, now)
            self.last_packet_at = now
            self._heard(level_dbov, now)
            for listener in list(self.listeners):
                if not listener.put(packet):
                    self._count("overflow")
        self._count(outcome)
        return outcome

    def _check(self, payload: bytes, now: float) -> tuple[str, int]:
        """The outcome, and the packet's duration in 48 kHz ticks (0 unless valid)."""
        if len(payload) > self.max_packet_bytes:
            return "too_large", 0
        try:
            ticks = round(packet_duration_ms(payload) * CLOCK_RATE / 1000)
        except OpusPacketError:
            return "garbage", 0
        self._tokens = min(self.max_bytes_per_s,
                           self._tokens + (now - self._tokens_at) * self.max_bytes_per_s)
        self._tokens_at = now
        if len(payload) > self._tokens:
            return "rate", ticks
        self._tokens -= len(payload)
        return "forwarded", ticks

    def _timeline(self, publisher: object, rtp_ts: int, now: float) -> int:
        if publisher is self._publisher and self._last_in is not None:
            step = (rtp_ts - self._last_in + 2**31) % 2**32 - 2**31  # signed, wrap-safe
        else:
            step = DISCONTINUITY_TICKS + 1
        if abs(step) > DISCONTINUITY_TICKS:  # a new publisher or stream: go on from the wall
            self._capture_clock.reset()  # its transit is its own
            elapsed = 0.0 if self.last_packet_at is None else now - self.last_packet_at
            step = max(1, round(min(elapsed, 5.0) * CLOCK_RATE))
        self._publisher, self._last_in = publisher, rtp_ts
        self._last_out += step
        return self._last_out

    def _paced(self, media_ts: int, now: float) -> float:
        """When a packet of ``media_ts`` typically arrives: its media time on the median
        arrival clock of the last ORIGIN_WINDOW_S (the median, not the earliest: the drives
        the picture lag is measured from come as late as a typical packet does)."""
        origin = now - media_ts / CLOCK_RATE
        self._origins.append((now, origin))
        bisect.insort(self._sorted_origins, origin)
        while self._origins[0][0] < now - ORIGIN_WINDOW_S:
            _, gone = self._origins.popleft()
            del self._sorted_origins[bisect.bisect_left(self._sorted_origins, gone)]
        return self._sorted_origins[len(self._sorted_origins) // 2] + media_ts / CLOCK_RATE

    def _count(self, outcome: str) -> None:
        self.counts[outcome] += 1
        if self._metrics is not None:
            self._metrics.voice_packets.labels(outcome).inc()

    # -- listening ----------------------------------------------------------------------------

    def subscribe(self) -> Listener:
        listener = Listener(self, self.buffer_packets, self.max_delay_s, self.pacing)
        self.listeners.add(listener)
        return listener

    def unsubscribe(self, listener: Listener) -> None:
        self.listeners.discard(listener)


def input_arrived(seat: Any) -> float | None:
    """When the seat's newest input arrived: its performer's (a webcam image still being
    tracked counts: the drive it becomes is of that instant), else its drive's."""
    performer = getattr(seat, "performer", None)
    if performer is not None and hasattr(performer, "input_arrived"):
        return performer.input_arrived
    return seat.drive.arrived


def seat_voice(seat: Any, settings: Any, metrics: Any = None) -> SeatVoice:
    """The seat's voice, made on first use (telling ``seat.on_speaking`` when it speaks; its
    listeners wait for the frames of its newest input: :func:`input_arrived`)."""
    if seat.voice is None:
        seat.voice = SeatVoice(settings, metrics, getattr(seat, "on_speaking", None),
                               lambda: input_arrived(seat),
                               lambda: getattr(seat.performer, "tracking_input", False))
    return seat.voice


def publish_message(seat: Any, performer: Any, message: Voice, settings: Any,
                    metrics: Any = None) -> str:
    """A performer's ``voice`` message (WebSocket, data channel) into its seat's voice; its
    media time comes from its capture time (the performer's clock, put on this server's by
    its ``capture_clock``), else from arrival."""
    now = time.monotonic()
    at = message.t_capture if message.t_capture is not None else now
    return seat_voice(seat, settings, metrics).publish(
        performer, message.data, round(at * CLOCK_RATE) % 2**32, now, message.t_capture,
        message.level_dbov, getattr(performer, "capture_clock", None))


async def relay_voices(session: Any, live: Any, settings: Any, metrics: Any = None) -> None:
    """Until cancelled: every other seat's voice to ``session`` as ``voice`` messages (its
    control queue: dropped, never queued without bound, when the client is behind). The client
    syncs them to the frames by their capture times, so no delay is added here."""
    seats = [s for s in live.seats
             if not (session.role == "perform" and s.index == session.seat_index)]
    listeners = [seat_voice(s, settings, metrics).subscribe() for s in seats]

    async def pump(index: int, listener: Listener) -> None:
        seq = 0
        while (packet := await listener.next()) is not None:
            session.send_control(Voice(seq=seq, data=packet.payload,
                                       t_capture=packet.t_capture, seat=index))
            seq += 1

    try:
        await asyncio.gather(*(pump(s.index, lis) for s, lis in zip(seats, listeners,
                                                                     strict=True)))
    finally:
        for listener in listeners:
            listener.close()
