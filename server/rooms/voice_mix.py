"""One mixed voice for a room's viewers who ask for it, instead of each seat's own track.

A room forwards every seat's Opus undecoded (server/rooms/voice.py); a viewer may ask for one
track instead (WHEP ``?voice=mix``, ``hello.voice_mix``). The room then runs one
:class:`RoomMix`, shared by everyone who asked: a listener per seat (so the voices still
wait for the picture: the mix viewers' transports feed them frames, :meth:`followers`), each
seat's packets decoded, summed every 20 ms, encoded once (:class:`MixCodec`, on the mix's own
thread, off the event loop) and handed to each subscriber. It starts with the first
subscriber and stops with the last; while no seat sends anything it sleeps.

Bounds: at most ``voice_mix_max_seats`` seats mixed at once (the first ones to speak; a
packet of another seat is dropped and counted ``unmixed`` until one falls silent for
``HOLD_S``), each seat's decoded backlog at most ``voice_buffer_packets`` frames, each
subscriber's queue the same. Each mixed packet carries its loudest seat's capture instant; a
WebSocket subscriber gets it as ``t_capture`` on the clock its frames carry
(:func:`picture_stamp`).
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import fractions
import time
from typing import Any

import av
import numpy as np

from protocol import Voice
from protocol.messages import MAX_CAPTURE_TIME

from .voice import CLOCK_RATE, Listener, VoicePacket, seat_voice

FRAME = 960            # one 20 ms frame at 48 kHz: the mix's step
FRAME_S = FRAME / CLOCK_RATE
PREBUFFER_FRAMES = 2   # a seat plays once this much is decoded (its packets leave in bursts
#                        with their frames: a 40 ms cushion keeps a burst's gaps out)
IDLE_FRAMES = 5        # after this many frames with nothing to mix the mixer sleeps
HOLD_S = 1.0           # a seat keeps its place among the mixed this long after its last packet


class SeatDecoder:
    """One seat's Opus decoded into a bounded backlog of samples (float32, full scale 1), each
    packet's capture instant kept beside its samples."""

    def __init__(self, max_samples: int) -> None:
        self.codec = av.CodecContext.create("libopus", "r")
        self.codec.sample_rate, self.codec.layout = CLOCK_RATE, "mono"
        self.samples = np.zeros(0, np.float32)
        self.max_samples = max_samples
        self.playing = False
        self.dropped = 0  # samples dropped past max_samples (the seat ran ahead of the mix)
        # [samples left, capture instant of its first sample, samples] per decoded frame, in
        # backlog order: each packet keeps its own instant (a run's first one would keep the
        # transit estimate of its time, which the seat's own stamps move on from)
        self._segments: collections.deque[list] = collections.deque()

    @property
    def captured_at(self) -> float | None:
        """The capture instant of the backlog's first sample (None: unknown or empty)."""
        if not self._segments or self._segments[0][1] is None:
            return None
        left, at, length = self._segments[0]
        return at + (length - left) / CLOCK_RATE

    def add(self, payload: bytes, captured_at: float | None = None) -> None:
        """Decode ``payload``, captured at ``captured_at`` (its first sample's instant)."""
        try:
            frames = self.codec.decode(av.Packet(payload))
        except av.FFmpegError:
            return  # checked Opus that libopus still refuses: skipped, the seat goes on
        offset = 0
        for frame in frames:
            pcm = frame.to_ndarray().reshape(-1)
            scale = 32768.0 if pcm.dtype == np.int16 else 1.0
            at = None if captured_at is None else captured_at + offset / CLOCK_RATE
            self._segments.append([len(pcm), at, len(pcm)])
            offset += len(pcm)
            self.samples = np.concatenate([self.samples, pcm.astype(np.float32) / scale])
        excess = len(self.samples) - self.max_samples
        if excess > 0:
            self.samples = self.samples[excess:]
            self.dropped += excess
            self._consume(excess)

    def _consume(self, samples: int) -> None:
        while samples > 0 and self._segments:
            head = self._segments[0]
            used = min(samples, head[0])
            head[0] -= used
            samples -= used
            if head[0] == 0:
                self._segments.popleft()

    def take(self) -> tuple[np.ndarray, float | None] | None:
        """The next 20 ms (zero-padded) and its first sample's capture instant, or None while
        it has too little to play."""
        if not self.playing and len(self.samples) >= PREBUFFER_FRAMES * FRAME:
            self.playing = True
        if not self.playing:
            return None
        at = self.captured_at
        out, self.samples = self.samples[:FRAME], self.samples[FRAME:]
        self._consume(len(out))
        if len(self.samples) == 0:
            self.playing = False  # ran dry: cushion again before the next word
        return np.pad(out, (0, FRAME - len(out))), at


def opus_encoder(bitrate: int) -> av.CodecContext:
    """A mono 48 kHz libopus encoder of 20 ms packets."""
    encoder = av.CodecContext.create("libopus", "w")
    encoder.sample_rate, encoder.layout = CLOCK_RATE, "mono"
    encoder.format, encoder.bit_rate = "s16", bitrate
    encoder.options = {"frame_duration": "20"}
    return encoder


def encode_samples(encoder: av.CodecContext, samples: np.ndarray, pts: int) -> list[bytes]:
    """Encode one 20 ms frame of ``samples`` ([FRAME] floats in [-1, 1]) at ``pts``; the
    packets it gives (none while the encoder fills its look-ahead)."""
    frame = av.AudioFrame.from_ndarray((np.clip(samples, -1.0, 1.0) * 32767)
                                       .astype(np.int16)[None], format="s16", layout="mono")
    frame.sample_rate, frame.pts = CLOCK_RATE, pts
    frame.time_base = fractions.Fraction(1, CLOCK_RATE)
    return [bytes(p) for p in encoder.encode(frame)]


def tone_packets(freq: float, count: int, amplitude: float = 0.25) -> list[bytes]:
    """``count`` 20 ms Opus packets of a sine tone (tests and benches speak with it)."""
    encoder, packets = opus_encoder(32000), []
    for i in range(count + 1):  # one more: the encoder's look-ahead
        t = (np.arange(FRAME) + i * FRAME) / CLOCK_RATE
        packets += encode_samples(encoder, amplitude * np.sin(2 * np.pi * freq * t), i * FRAME)
    return packets[:count]


def loudest_capture(parts: list[tuple[np.ndarray, float | None]]) -> float | None:
    """The capture instant a mixed frame is stamped with: its loudest seat's (the voice a
    viewer lip-reads), else any seat's that has one."""
    timed = [(float(np.square(pcm).sum()), at) for pcm, at in parts if at is not None]
    return max(timed, key=lambda t: t[0])[1] if timed else None


class MixCodec:
    """Decode, sum and encode: the mix's work, called from one thread at a time."""

    def __init__(self, bitrate: int, max_frames: int) -> None:
        self.encoder = opus_encoder(bitrate)
        self.max_samples = max_frames * FRAME
        self.seats: dict[int, SeatDecoder] = {}
        self.pts = 0
        # each frame fed to the encoder, its capture instant: the encoder's look-ahead puts out
        # a frame's packet a step later, one packet per 20 ms frame, in order
        self._fed: collections.deque[float | None] = collections.deque(maxlen=max_frames + 4)

    def step(self, packets: list[tuple[int, bytes, float | None]]
             ) -> list[tuple[bytes, float | None]] | None:
        """Decode ``packets`` ((seat, payload, capture instant), in arrival order), mix the
        next 20 ms of every seat that has some, encode it; the packets out, each with the
        capture instant of the frame it holds; None when no seat had anything to play."""
        for seat, payload, captured_at in packets:
            decoder = self.seats.get(seat)
            if decoder is None:
                decoder = self.seats[seat] = SeatDecoder(self.max_samples)
            decoder.add(payload, captured_at)
        parts = [p for p in (d.take() for d in self.seats.values()) if p is not None]
        if not parts:
            return None
        self._fed.append(loudest_capture(parts))
        out = encode_samples(self.encoder, np.sum([pcm for pcm, _ in parts], axis=0),
                             self.pts)
        self.pts += FRAME
        return [(payload, self._fed.popleft() if self._fed else None) for payload in out]


class MixSubscriber:
    """One viewer's queue of the mix's packets: a :class:`~.voice.Listener` to its track."""

    def __init__(self, mix: RoomMix, capacity: int) -> None:
        self.mix = mix
        self._queue: collections.deque[VoicePacket] = collections.deque(maxlen=capacity)
        self._ready = asyncio.Event()
        self.closed = False

    def put(self, packet: VoicePacket) -> None:
        self._queue.append(packet)  # past capacity the oldest goes
        self._ready.set()

    async def next(self) -> VoicePacket | None:
        while not self.closed:
            if self._queue:
                return self._queue.popleft()
            self._ready.clear()
            await self._ready.wait()
        return None

    def follow_picture(self, arrived: float | None, now: float) -> None:
        """Nothing: the mix's seats follow the pictures (:meth:`RoomMix.followers`)."""

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._ready.set()
            self.mix.unsubscribe(self)


class RoomMix:
    def __init__(self, live: Any, settings: Any, metrics: Any = None) -> None:
        self.live, self.settings, self.metrics = live, settings, metrics
        self.max_seats = settings.voice_mix_max_seats
        self.subscribers: set[MixSubscriber] = set()
        self.counts: collections.Counter[str] = collections.Counter()
        self._sources: list[tuple[int, Listener]] = []  # (seat position, its listener)
        self._inbox: list[tuple[int, bytes, float]] = []  # (seat, payload, captured at)
        self._arrived = asyncio.Event()
        self._heard: dict[int, float] = {}  # seat position -> its last packet (mixed seats)
        self._task: asyncio.Task | None = None
        self._media_ts = 0
        self._last_at: float | None = None
        self._last_captured: float | None = None  # the last mixed packet's capture instant

    # -- subscribers ------------------------------------------------------------------------------

    def subscribe(self) -> MixSubscriber:
        subscriber = MixSubscriber(self, self.settings.voice_buffer_packets)
        self.subscribers.add(subscriber)
        if self._task is None:
            self._sources = [(i, seat_voice(seat, self.settings, self.metrics).subscribe())
                             for i, seat in enumerate(self.live.seats)]
            self._task = asyncio.get_running_loop().create_task(self._run(), name="voice mix")
        return subscriber

    def unsubscribe(self, subscriber: MixSubscriber) -> None:
        self.subscribers.discard(subscriber)
        if not self.subscribers and self._task is not None:
            self._task.cancel()
            self._task = None
            for _, listener in self._sources:
                listener.close()
            self._sources = []

    def followers(self) -> list[tuple[int, Listener]]:
        """(seat position, listener) pairs a mix viewer's transport feeds its frames to, so
        each seat's voice waits for the picture before it is mixed."""
        return list(self._sources)

    @property
    def running(self) -> bool:
        return self._task is not None

    # -- mixing -----------------------------------------------------------------------------------

    def _admit(self, position: int, now: float) -> bool:
        """Is ``position`` among the seats mixed (at most voice_mix_max_seats, the first to
        speak; one silent for HOLD_S gives its place up)?"""
        for seat, last in list(self._heard.items()):
            if now - last > HOLD_S:
                del self._heard[seat]
        if position not in self._heard and len(self._heard) >= self.max_seats:
            return False
        self._heard[position] = now
        return True

    async def _pump(self, position: int, listener: Listener) -> None:
        while (packet := await listener.next()) is not None:
            if not self._admit(position, time.monotonic()):
                self.counts["unmixed"] += 1
                if self.metrics is not None:
                    self.metrics.voice_packets.labels("unmixed").inc()
                continue
            at = packet.arrived if packet.captured_at is None else packet.captured_at
            self._inbox.append((position, packet.payload, at))
            self._arrived.set()

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        codec = MixCodec(self.settings.voice_mix_bitrate, self.settings.voice_buffer_packets)
        pumps = [loop.create_task(self._pump(i, lis)) for i, lis in self._sources]
        thread = concurrent.futures.ThreadPoolExecutor(1, "voice-mix")
        try:
            while True:
                self._arrived.clear()
                await self._arrived.wait()  # asleep while nobody speaks
                await self._mix_while_heard(loop, thread, codec)
        finally:
            for pump in pumps:
                pump.cancel()
            thread.shutdown(wait=False)  # a step under way ends on its own

    async def _mix_while_heard(self, loop: asyncio.AbstractEventLoop, thread: Any,
                               codec: MixCodec) -> None:
        """A mixed frame every 20 ms until IDLE_FRAMES in a row had nothing to mix."""
        start, ticks, idle = time.monotonic(), 0, 0
        while idle < IDLE_FRAMES:
            packets, self._inbox = self._inbox, []
            out = await loop.run_in_executor(thread, codec.step, packets)
            idle = 0 if out is not None else idle + 1
            for payload, captured_at in out or ():
                self._send(payload, captured_at)
            ticks += 1
            await asyncio.sleep(max(0.0, start + ticks * FRAME_S - time.monotonic()))

    def _send(self, payload: bytes, captured_at: float | None = None) -> None:
        now = time.monotonic()
        # The timeline follows the sound's capture instants where they are known (its RTP
        # timestamps then agree with the sender reports' stamps), else the wall clock across
        # pauses; never back, never stalls.
        if captured_at is not None and self._last_captured is not None:
            gap = captured_at - self._last_captured
            contiguous = abs(gap - FRAME_S) < FRAME_S / 2
        else:
            gap = 0.0 if self._last_at is None else now - self._last_at
            contiguous = gap < 3 * FRAME_S
        self._media_ts += FRAME if contiguous else max(FRAME, round(gap * CLOCK_RATE))
        self._last_at = now
        if captured_at is not None:
            self._last_captured = captured_at
        self.counts["mixed"] += 1
        # stamped with its sound's capture instant: the sender reports of a capture-clock
        # peer (webrtc_sender_clock) then count the mix's own latency out
        packet = VoicePacket(payload, self._media_ts, now, captured_at=captured_at)
        for subscriber in list(self.subscribers):
            subscriber.put(packet)


async def relay_mix(session: Any, live: Any, settings: Any, metrics: Any = None) -> None:
    """Until cancelled: the room's mix to ``session`` as ``voice`` messages without a seat
    (its control queue: dropped when the client is behind). Its frames lead the mix's seats
    (its transport's ``voices``), so the mix leaves with the picture of its instant."""
    subscriber = room_mix(live, settings, metrics).subscribe()
    followers = getattr(session.transport, "voices", None)
    if followers is not None:
        followers.extend(subscriber.mix.followers())
    seq = 0
    try:
        while (packet := await subscriber.next()) is not None:
            session.send_control(Voice(seq=seq, data=packet.payload,
                                       t_capture=picture_stamp(session, live, packet)))
            seq += 1
    finally:
        subscriber.close()


def picture_stamp(session: Any, live: Any, packet: VoicePacket) -> float | None:
    """A mixed packet's capture instant as a stamp of the clock the session's frames carry
    (its seat's performer's ``t_capture``), so a WebSocket viewer syncs the mix to its picture
    as it syncs a seat's own voice; None when that performer stamps nothing."""
    seats = live.seats
    position = getattr(session, "position", None)
    if packet.captured_at is None or position is None or not 0 <= position < len(seats):
        return None
    clock = getattr(getattr(seats[position], "performer", None), "capture_clock", None)
    stamp = None if clock is None else clock.stamp_of(packet.captured_at)
    return stamp if stamp is not None and 0.0 <= stamp <= MAX_CAPTURE_TIME else None


def room_mix(live: Any, settings: Any, metrics: Any = None) -> RoomMix:
    """The room's one mix, made on first use."""
    if getattr(live, "voice_mix", None) is None:
        live.voice_mix = RoomMix(live, settings, metrics)
    return live.voice_mix
