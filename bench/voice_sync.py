"""Lip sync of a room's voice at aiortc viewers: click onset vs mouth opening (issue 30).

Starts its own server (bench/stream.py's start_server). A performer (aiortc, WHEP with
role=perform and a microphone track) opens the jaw at each event and, in the same instant, puts
a 5 ms click in its next 20 ms audio frame; 300 ms later the jaw closes; ``--drive-hz`` drives
the current jaw between (a webcam tracker's rate; 0: drives at the jaw's edges only), an edge
being one of them (``--edge-drive tick``) or a drive between them (``extra``: JawDrives).
``--viewers`` aiortc WHEP viewers (one recvonly audio line each, video released at its RTP
marker as a browser does), spread over ``--processes`` worker processes (0: in the performer's
process), record for every event, on time.monotonic() (one clock for every process):

- the mouth opening: the arrival of the last RTP packet of the first frame in which more than
  ``--open-pixels`` pixels differ from the closed-mouth frame by more than 25 grey levels;
- the click onset: the arrival of the RTP packet whose decoded frame holds the click
  (``--mouth-clock decode``: both at their decode instead; aiortc's audio jitter buffer holds
  a click ~90 ms that a browser's would not);
- offset = click - mouth (ms): positive when the voice is late. Targets (ITU-R BT.1359):
  |median| <= 20 ms, every event within -45 / +125 ms; also the offset of the same two RTP
  timestamps mapped through each track's last RTCP sender report (what a receiver syncing by
  the reports plays);
- the longest gap between audio packets each viewer received over the events' span (target
  <= 60 ms at 16 viewers), beside the performer's own: between the packets its peer sent
  (after aiortc's encoder, which runs in a thread) and at its source (the microphone's
  handover);
- the server's voice drops (overflow of listener buffers), its CPU and each viewer's.

``--video-decode first``: in each viewer process only the first viewer decodes its video (and
is scored for lip sync); the others receive every packet of both tracks but drop their video
frames undecoded (`skip_video_decode`), so that on a small machine the 16 viewers' decoding
does not take the cores the server needs. Their audio gaps are still measured.

Each line of the table is one run: (viewers, processes, clock, drives/s, voice) under a cap,
the server's ``webrtc_max_bitrate`` (TELESPLAT_WEBRTC_MAX_BITRATE), on the video encoder;
servers side by side for each ``--pacing``, ``--sender-clock`` (``webrtc_sender_clock``) and
``--max-delay-s`` (``voice_max_delay_s``; "default": unset).

    nice -n 10 .venv/bin/python bench/voice_sync.py [--events 50] [--viewers 1,16]
        [--caps 0,500000] [--processes 4] [--drive-hz 0,30] [--mouth-clock arrival,decode]
        [--pacing even,frames] [--sender-clock capture,send] [--max-delay-s default,0]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import fractions
import itertools
import math
import multiprocessing
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from aiortc.mediastreams import MediaStreamError

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from stream import start_server, stop_server  # noqa: E402
from webrtc import cpu_seconds  # noqa: E402

from client.webrtc import WhepViewer  # noqa: E402
from protocol import Drive  # noqa: E402
from protocol.rtp_receiver import frame_rtp_timestamp  # noqa: E402
from server.loop_watch import GcWatch, LoopWatch  # noqa: E402
from server.metrics import ServerMetrics  # noqa: E402

RATE = 48_000
FRAME = 960
EVENT_EVERY_S = 0.7
OPEN_S = 0.3
JAW_OPEN = 0.5
CLICK_LEVEL = 0.3


class JawDrives:
    """A webcam performer's drives: the current jaw, ``drive_hz`` times a second (0: only at
    the jaw's edges). ``edges="tick"``: a jaw edge is one of those drives and the schedule
    goes on from it (the next drive 1 / ``drive_hz`` later), as a tracker's camera frame that
    catches the open mouth is the one at the click; only the interval before an edge is short.
    ``"extra"`` (the benches before 2026-11-27's fifth session): an edge is a drive between
    two ticks, so at 30 drives/s the performer sends 32.9 a second into a 30 fps cap, and an
    edge may lose its frame to the next tick's drive (docs/benchmarks.md, "The frame-rate cap
    as a rate")."""

    def __init__(self, send, drive_hz: float, edges: str = "tick") -> None:
        if edges not in ("tick", "extra"):
            raise ValueError(f"edges {edges!r}: tick or extra")
        self.send, self.drive_hz, self.edges = send, drive_hz, edges
        self.angle = 0.0
        self.seq = iter(range(1, 10**9))
        self.next_tick = 0.0  # time.monotonic() of the next scheduled drive

    def _drive(self) -> None:
        now = time.monotonic()
        self.send(Drive(seq=next(self.seq), smplx={"jaw_pose": [self.angle, 0.0, 0.0]},
                        t_capture=now))
        self.next_tick = now + 1 / self.drive_hz if self.drive_hz else math.inf

    def jaw(self, angle: float) -> None:
        """A jaw edge, driven now."""
        self.angle = angle
        tick = self.next_tick
        self._drive()
        if self.edges == "extra":
            self.next_tick = tick  # the ticks keep their own schedule

    async def run(self, until: float, alive=lambda: True) -> None:
        while self.drive_hz and time.monotonic() < until and alive():
            delay = self.next_tick - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)  # an edge meanwhile moves the tick: re-check
            else:
                self._drive()


def click_microphone(on_click, sent_at: list[float]):
    """An aiortc audio track in real time; ``fire()`` puts a click in the next frame and calls
    ``on_click()`` as that frame is handed to the encoder (one instant for voice and jaw);
    ``sent_at`` gets the time each frame was handed over (the source's own gaps)."""
    import av
    from aiortc import MediaStreamTrack

    class Mic(MediaStreamTrack):
        kind = "audio"

        def __init__(self) -> None:
            super().__init__()
            self.sent, self.start, self.pending = 0, None, False

        def fire(self) -> None:
            self.pending = True

        async def recv(self):
            if self.start is None:
                self.start = time.monotonic()
            due = self.start + self.sent * FRAME / RATE
            await asyncio.sleep(max(0.0, due - time.monotonic()))
            samples = np.zeros((1, FRAME), np.int16)
            if self.pending:
                self.pending = False
                t = np.arange(240) / RATE
                samples[0, :240] = (30000 * np.sin(2 * np.pi * 2000 * t)).astype(np.int16)
                on_click()
            frame = av.AudioFrame.from_ndarray(samples, format="s16", layout="mono")
            frame.sample_rate, frame.pts = RATE, self.sent * FRAME
            frame.time_base = fractions.Fraction(1, RATE)
            self.sent += 1
            sent_at.append(time.monotonic())
            return frame

    return Mic()


def longest_gap_ms(times: list[float]) -> float:
    """The longest step between consecutive instants (s), in ms; NaN for fewer than two."""
    return float(np.diff(times).max() * 1e3) if len(times) > 1 else float("nan")


def set_process_nice(delta: int, base: int | None = None, pid: int | str = "self") -> int:
    """Every thread of process ``pid`` (this one: the performer's loop, aiortc's encoder
    threads) at ``base + delta`` niceness (``base``: its main thread's now); returns ``base``.
    Linux keeps a niceness per thread (new ones take their creator's), so each is set;
    negative needs CAP_SYS_NICE."""
    main = 0 if pid == "self" else int(pid)
    base = os.getpriority(os.PRIO_PROCESS, main) if base is None else base
    if delta or base != os.getpriority(os.PRIO_PROCESS, main):
        for tid in os.listdir(f"/proc/{pid}/task"):
            with contextlib.suppress(ProcessLookupError):
                os.setpriority(os.PRIO_PROCESS, int(tid), base + delta)
    return base


def time_audio_rtp(pc) -> list[float]:
    """The instants (time.monotonic()) the performer's peer hands each audio RTP packet to its
    DTLS transport, after aiortc's encoder (run in a thread): the step between the
    microphone's handover and the socket. The peer sends no other RTP; RTCP is left out."""
    sender = next(s for s in pc.getSenders() if s.track is not None and s.track.kind == "audio")
    transport, out = sender.transport, []
    original = transport._send_rtp

    async def timed(data: bytes) -> None:
        if not 192 <= data[1] <= 223:  # RTCP's packet types (RFC 5761), the rest RTP
            out.append(time.monotonic())
        await original(data)

    transport._send_rtp = timed
    return out


class _DroppedFrames:
    """Stands in for an aiortc video receiver's decoder queue: encoded frames go nowhere;
    the end marker (None) reaches the decoder thread, so the receiver still stops."""

    def __init__(self, original) -> None:
        self.original = original

    def put(self, task) -> None:
        if task is None:
            self.original.put(None)


def skip_video_decode(pc) -> None:
    """Every video frame this peer receives from now on is reassembled and dropped, never
    decoded (RTP, RTCP and the audio track go on as before)."""
    for transceiver in pc.getTransceivers():
        if transceiver.kind == "video":
            receiver = transceiver.receiver
            queue_name = "_RTCRtpReceiver__decoder_queue"  # aiortc 1.x's private queue
            if not hasattr(receiver, queue_name):
                raise RuntimeError("this aiortc has no decoder queue to bypass")
            setattr(receiver, queue_name, _DroppedFrames(getattr(receiver, queue_name)))


class Ear:
    """One viewer's record: mouth-open edges and click onsets (time.monotonic(), one clock for
    every process of the machine)."""

    def __init__(self, viewer: WhepViewer, open_pixels: int, mouth_clock: str) -> None:
        self.viewer, self.open_pixels, self.mouth_clock = viewer, open_pixels, mouth_clock
        self.closed: np.ndarray | None = None
        self.mouth: list[float] = []
        self.clicks: list[float] = []
        # keyed by RTP timestamp; a decoded frame's own: self.rtp(kind, frame.pts)
        self.receivers: dict[str, Any] = {}
        self.arrivals: dict[int, float] = {}  # audio RTP timestamp -> arrival
        self.video_arrivals: dict[int, float] = {}  # video pts -> its last packet's arrival
        self.packet_times: list[float] = []
        self.packet_seqs: list[int] = []  # RTP sequence numbers: a gap with none missing
        self.frames = 0
        self.decodes = True  # False: its video is dropped undecoded (skip_video_decode)
        self.lost = False  # its peer closed during the run
        self.missed_arrivals = 0  # clicks whose packet's arrival was not seen (then: decode)
        self._open = False
        self.sr: dict[str, list[tuple[int, float]]] = {"audio": [], "video": []}  # (rtp, ntp)
        self.click_ts: list[int] = []   # RTP timestamps of the clicks and mouth edges: what
        self.mouth_ts: list[int] = []   # the sender reports map to one clock, as a browser does

    def hook(self) -> None:
        """Note each RTP packet's arrival before aiortc handles it."""
        for receiver in self.viewer.pc.getReceivers():
            self.receivers.setdefault(receiver.track.kind, receiver)
            original = receiver._handle_rtp_packet
            if receiver.track.kind == "audio":
                async def handle(packet, arrival_time_ms: int = 0, original=original):
                    now = time.monotonic()
                    self.arrivals[packet.timestamp] = now
                    self.packet_times.append(now)
                    self.packet_seqs.append(packet.sequence_number)
                    await original(packet, arrival_time_ms=arrival_time_ms)
            else:
                async def handle(packet, arrival_time_ms: int = 0, original=original):
                    self.video_arrivals[packet.timestamp] = time.monotonic()
                    if len(self.video_arrivals) > 4096:  # bounded: the oldest go
                        self.video_arrivals.pop(next(iter(self.video_arrivals)))
                    await original(packet, arrival_time_ms=arrival_time_ms)
            receiver._handle_rtp_packet = handle
            self._hook_reports(receiver)

    def rtp(self, kind: str, pts: int) -> int | None:
        """The RTP timestamp of a decoded frame (protocol.rtp_receiver)."""
        return frame_rtp_timestamp(self.receivers.get(kind), pts)

    def _hook_reports(self, receiver) -> None:
        from aiortc.rtp import RtcpSrPacket

        original, kind = receiver._handle_rtcp_packet, receiver.track.kind

        async def handle(packet):
            if isinstance(packet, RtcpSrPacket):
                info = packet.sender_info
                self.sr[kind].append((info.rtp_timestamp, info.ntp_timestamp / 2**32))
            await original(packet)

        receiver._handle_rtcp_packet = handle

    def sr_offsets(self) -> list[float]:
        """Click minus mouth (ms) on the sender reports' clock, each click paired with the
        mouth edge before it within an event interval: the offset a browser that syncs the
        tracks by their reports plays them at."""
        mouths = [on_report_clock(ts, self.sr["video"], 90_000) for ts in self.mouth_ts]
        out = []
        for ts in self.click_ts:
            click = on_report_clock(ts, self.sr["audio"], RATE)
            near = [m for m in mouths if m is not None and click is not None
                    and abs(click - m) < EVENT_EVERY_S / 2]
            if near:
                out.append((click - near[0]) * 1e3)
        return out

    async def watch_video(self, end: float) -> None:
        if not self.decodes:
            return
        track = await self.viewer._track  # the raw av.VideoFrame: its pts is the RTP timestamp
        while time.monotonic() < end:
            try:
                frame = await asyncio.wait_for(track.recv(), 2.0)
            except TimeoutError:
                continue
            except MediaStreamError:  # the server closed this peer: it records no more
                self.lost = True
                return
            decoded = time.monotonic()
            self.frames += 1
            grey = frame.to_ndarray(format="rgb24").mean(axis=2)
            if self.closed is None:
                self.closed = grey
                continue
            is_open = int((np.abs(grey - self.closed) > 25).sum()) > self.open_pixels
            if is_open and not self._open:
                ts = self.rtp("video", frame.pts)
                self.mouth.append(decoded if self.mouth_clock == "decode"
                                  else self.video_arrivals.get(ts, decoded))
                if ts is not None:
                    self.mouth_ts.append(ts)
            self._open = is_open

    async def listen(self, end: float) -> None:
        loud = False
        while time.monotonic() < end:
            try:
                frame, at = await self.viewer.next_audio(timeout=2.0)
            except TimeoutError:
                continue
            except MediaStreamError:
                self.lost = True
                return
            peak = np.abs(frame.to_ndarray()).max() / 32768
            if peak > CLICK_LEVEL and not loud:
                ts = self.rtp("audio", frame.pts)
                arrived = self.arrivals.get(ts)
                self.missed_arrivals += arrived is None
                self.clicks.append(at if self.mouth_clock == "decode" or arrived is None
                                   else arrived)
                if ts is not None:
                    self.click_ts.append(ts)
            loud = peak > CLICK_LEVEL


def on_report_clock(rtp_ts: int, reports: list[tuple[int, float]], rate: int) -> float | None:
    """``rtp_ts`` on the sender's report clock (NTP seconds), by the report sent last before
    it, as a receiver maps it to sync tracks (RFC 3550 6.4.1)."""
    if not reports:
        return None
    before = [r for r in reports if (rtp_ts - r[0]) % 2**32 < 2**31] or reports[:1]
    rtp, ntp = before[-1]
    return ntp + (((rtp_ts - rtp + 2**31) % 2**32) - 2**31) / rate


def pair(events: list[float], later: list[float], window: float = EVENT_EVERY_S
         ) -> list[float | None]:
    """For each event, the first time in ``later`` within ``window`` s after it."""
    out = []
    for t in events:
        hits = [x for x in later if t <= x <= t + window]
        out.append(hits[0] if hits else None)
    return out


async def listen_in_process(url: str, token: str, room: str, count: int, size: int,
                            open_pixels: int, mouth_clock: str, voice: bool, ready, go,
                            video_decode: str = "all") -> list[dict]:
    """``count`` viewers in this process: joined, first frame seen, then ``ready`` gets the
    count; recording until the end time ``go`` gives. The process's longest garbage-collector
    pause while recording is returned too (a pause stalls its receiving). ``video_decode``
    "first": only the first viewer decodes its video."""
    ears = [Ear(WhepViewer(url, room, token, width=size, height=size, role="watch",
                           voices=1, timeout_s=60), open_pixels, mouth_clock)
            for _ in range(count)]
    for ear in ears:
        await ear.viewer.start()
        ear.hook()
    await asyncio.gather(*(e.viewer.next_frame() for e in ears))
    if video_decode == "first":
        for ear in ears[1:]:
            skip_video_decode(ear.viewer.pc)
            ear.decodes = False
    pauses: list[float] = []  # this process's collector pauses while recording (ms)
    gc_watch = GcWatch(lambda generation, ms: pauses.append(ms))
    gc_watch.start()
    ready.put(count)
    end = await asyncio.to_thread(go.get, True, 600)
    cpu0, t0 = time.process_time(), time.monotonic()
    await asyncio.gather(*(t for e in ears
                           for t in (e.watch_video(end), e.listen(end) if voice
                                     else asyncio.sleep(0))))
    cpu = (time.process_time() - cpu0) / (time.monotonic() - t0)  # this process, all threads
    gc_watch.stop()
    gc_max_ms = max(pauses, default=0.0)
    for ear in ears:
        await ear.viewer.close()
    return [{"mouth": e.mouth, "clicks": e.clicks, "packets": e.packet_times,
             "seqs": e.packet_seqs, "frames": e.frames, "cpu": cpu / count,
             "sr_offsets": e.sr_offsets(), "missed_arrivals": e.missed_arrivals,
             "lost": e.lost, "gc_max_ms": gc_max_ms, "decodes": e.decodes} for e in ears]


def viewer_process(args: tuple, ready, go, results, nice: int = 0,
                   video_decode: str = "all") -> None:
    """One viewer process; ``nice``: how much lower its priority than the bench's (viewers
    elsewhere, off the server's and the performer's cores)."""
    os.nice(nice)
    try:
        results.put(asyncio.run(listen_in_process(*args, ready, go, video_decode)))
    except BaseException as exc:  # the parent waits for a result: say what went wrong
        ready.put(0)
        results.put(repr(exc))
        raise


def machine_watch(end: float, out) -> None:
    """A separate, otherwise idle process: each time a 2 ms sleep wakes more than 20 ms late
    (the machine itself held it: a virtual machine's stolen time, or every core busy), its
    (time.monotonic() it slept at, ms late)."""
    late = []
    while (now := time.monotonic()) < end:
        time.sleep(0.002)
        if (held := time.monotonic() - now - 0.002) > 0.020:
            late.append((now, held * 1e3))
    out.put(late)


def steal_ms() -> float:
    """The machine's stolen time so far (/proc/stat, all cores; 0 where not given)."""
    try:
        fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()
        return float(fields[8]) * 1000 / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return 0.0


def stall_text(stalls: list, gaps: list[tuple[float, float]], steal: float) -> str:
    """The machine watch against a viewer's audio gaps longer than 60 ms (start, end)."""
    held = [ms for _, ms in stalls]
    both = sum(any(a - 0.01 <= t <= b for t, _ in stalls) for a, b in gaps)
    return (f"machine watch: {len(held)} wakes later than 20 ms (longest "
            f"{max(held, default=0):.0f} ms), stolen time {steal:.0f} ms; the first viewer's "
            f"audio gaps over 60 ms: {len(gaps)}, {both} of them with the machine held")


def own_text(metrics: ServerMetrics, loop: LoopWatch) -> str:
    """The performer's process over a run: its loop's wakes later than 20 ms and its
    collector's pauses longer than 20 ms (server.loop_watch's probes, ``metrics`` their own)."""
    def count(name: str, labels: dict, le: str) -> float:
        return metrics.registry.get_sample_value(f"{name}_bucket", {**labels, "le": le}) or 0.0
    late = count("telesplat_event_loop_lag_ms", {}, "+Inf") - count(
        "telesplat_event_loop_lag_ms", {}, "20.0")
    gen = [{"generation": str(g)} for g in (0, 1, 2)]
    pauses = sum(count("telesplat_gc_pause_ms", g, "+Inf") - count("telesplat_gc_pause_ms", g,
                                                                     "20.0") for g in gen)
    return (f"loop held over 20 ms {late:.0f} times (longest {loop.worst_ms:.0f} ms), "
            f"collector pauses over 20 ms {pauses:.0f}")


def spread_text(values: list[float], between: str = " / ") -> str:
    """"median (p5 / p95)" in ms, or "-"."""
    if not values:
        return "-"
    p5, p50, p95 = np.percentile(values, [5, 50, 95])
    return f"{p50:.0f} ({p5:.0f}{between}{p95:.0f})"


def lag_text(lags: list[float]) -> str:
    """"median (p5-p95)" in ms of the times from the events."""
    return spread_text(lags, "-")


def server_voice_counts(url: str, token: str) -> dict[str, float]:
    text = httpx.get(f"{url}/metrics", headers={"Authorization": f"Bearer {token}"},
                     timeout=30).text
    out = {}
    for line in text.splitlines():
        if line.startswith("telesplat_voice_packets_total{"):
            label = line.split('outcome="')[1].split('"')[0]
            out[label] = float(line.rsplit(" ", 1)[1])
        elif line.startswith("telesplat_event_loop_lag_ms_bucket{"):
            le = line.split('le="')[1].split('"')[0]
            out[f"loop lag <= {le}"] = float(line.rsplit(" ", 1)[1])
        elif line.startswith("telesplat_gc_pause_ms_bucket{"):
            gen = line.split('generation="')[1].split('"')[0]
            le = line.split('le="')[1].split('"')[0]
            out[f"gc{gen} <= {le}"] = float(line.rsplit(" ", 1)[1])
        elif line.startswith("telesplat_voice_gap_ms_bucket{"):
            stage = line.split('stage="')[1].split('"')[0]
            le = line.split('le="')[1].split('"')[0]
            out[f"gap {stage} <= {le}"] = float(line.rsplit(" ", 1)[1])
        elif line.startswith("telesplat_gc_pause_ms_sum{"):
            gen = line.split('generation="')[1].split('"')[0]
            out[f"gc{gen} ms"] = float(line.rsplit(" ", 1)[1])
    return out


def delta(before: dict[str, float], after: dict[str, float], key: str) -> float:
    """A /metrics count over a run (server_voice_counts before and after)."""
    return after.get(key, 0) - before.get(key, 0)


def gc_text(before: dict[str, float], after: dict[str, float]) -> str:
    """The server's garbage-collector pauses during a run, per generation: how many, their
    total and how many were longer than 50 ms."""
    def diff(key: str) -> float:
        return delta(before, after, key)
    parts = [f"gen {g}: {diff(f'gc{g} <= +Inf'):.0f} ({diff(f'gc{g} ms'):.0f} ms, "
             f"{diff(f'gc{g} <= +Inf') - diff(f'gc{g} <= 50.0'):.0f} > 50 ms)"
             for g in (0, 1, 2)]
    return "; ".join(parts)


def voice_gap_text(before: dict[str, float], after: dict[str, float]) -> str:
    """The server's own voice gaps during a run (voice_gap_ms): as the seat got the packets
    (in) and as the viewers' tracks took them (out), how many were longer than 50 / 75 / 100
    ms, and the bucket the longest fell in."""
    def diff(key: str) -> float:
        return delta(before, after, key)
    parts = []
    for stage in ("in", "out"):
        edges = sorted({float(k.rsplit(" ", 1)[1]) for k in after
                        if k.startswith(f"gap {stage} <= ") and not k.endswith("+Inf")})
        total = diff(f"gap {stage} <= +Inf")
        longer = {le: total - diff(f"gap {stage} <= {le}") for le in (50.0, 75.0, 100.0)}
        top = next((le for le in edges if diff(f"gap {stage} <= {le}") == total), None)
        parts.append(f"{stage}: {total:.0f} gaps, longer than 50 / 75 / 100 ms: "
                     f"{longer[50.0]:.0f} / {longer[75.0]:.0f} / {longer[100.0]:.0f}, the "
                     f"longest <= {top if top is not None else '+Inf'} ms")
    return "; ".join(parts)


LOOP_LATE_MS = (10, 20, 35, 50, 100, 250)  # edges of the server's loop-lag histogram


def loop_lag_text(before: dict[str, float], after: dict[str, float]) -> str:
    """How often the server's event loop woke later than each of `LOOP_LATE_MS` during a run
    (a voice packet that arrives while the loop is held waits as long)."""
    wakes = delta(before, after, "loop lag <= +Inf")
    late = [wakes - delta(before, after, f"loop lag <= {float(le)}") for le in LOOP_LATE_MS]
    return (f"{wakes:.0f} wakes, later than {' / '.join(map(str, LOOP_LATE_MS))} ms: "
            + " / ".join(f"{n:.0f}" for n in late))


async def run(url: str, token: str, viewers: int, events: int, size: int,
              open_pixels: int, pid: int, voice: bool = True, processes: int = 4,
              mouth_clock: str = "arrival", drive_hz: float = 30.0,
              edges: str = "tick", viewer_nice: int = 0, performer_nice: int = 0,
              video_decode: str = "all") -> dict:
    async with httpx.AsyncClient(base_url=url, timeout=30) as http:
        room = (await http.post("/v1/rooms", headers={"Authorization": f"Bearer {token}"},
                                json={"seats": [{"avatar": "demo"}]})).json()["id"]
    fired: list[float] = []
    performer: WhepViewer | None = None
    sent_at: list[float] = []
    drives = JawDrives(lambda drive: performer.send(drive), drive_hz, edges)

    def clicked() -> None:
        fired.append(time.monotonic())
        drives.jaw(JAW_OPEN)

    mic = click_microphone(clicked, sent_at)
    performer = WhepViewer(url, room, token, width=size, height=size, role="perform", seat=0,
                           microphone=mic if voice else None, timeout_s=60)
    ctx = multiprocessing.get_context("spawn")
    ready, results = ctx.Queue(), ctx.Queue()
    counts = [viewers // max(1, processes) + (i < viewers % max(1, processes))
              for i in range(max(1, processes))]
    counts = [c for c in counts if c]
    gos = [ctx.Queue() for _ in counts]
    async with performer:
        await performer.wait_open()
        sent_rtp = time_audio_rtp(performer.pc) if voice else []
        if processes == 0:  # the viewers in this process, beside the performer (as before)
            here = asyncio.create_task(listen_in_process(
                url, token, room, viewers, size, open_pixels, mouth_clock, voice, ready,
                gos[0], video_decode))
            here.add_done_callback(lambda t: results.put(t.result()))
            workers = [here]
        else:
            workers = [ctx.Process(target=viewer_process, daemon=True, args=(
                (url, token, room, c, size, open_pixels, mouth_clock, voice), ready, go,
                results, viewer_nice, video_decode)) for c, go in zip(counts, gos, strict=True)]
            for w in workers:
                w.start()
        joined = [await asyncio.to_thread(ready.get, True, 300) for _ in workers]
        if sum(joined) != viewers:
            raise RuntimeError(f"viewers joined {joined} of {counts}: {results.get(True, 5)}")
        before = server_voice_counts(url, token)
        end = time.monotonic() + 2.0 + 3.0 + events * EVENT_EVERY_S
        stalls_out = ctx.Queue()
        watch = ctx.Process(target=machine_watch, args=(end, stalls_out), daemon=True)
        watch.start()
        niceness = set_process_nice(performer_nice)  # the viewers and the watch started
        steal0 = steal_ms()
        for go in gos:
            go.put(end)
        tracker = asyncio.create_task(drives.run(
            end - 3.0, lambda: performer.channel.readyState == "open"))
        # the performer's process (its loop runs the microphone, the drives and aiortc's
        # sender): the server's own probes, into a registry of its own
        own_metrics = ServerMetrics()
        own_loop = LoopWatch(own_metrics, interval_s=0.005, stall_ms=0)
        own_loop.start()
        own_gc = GcWatch.into(own_metrics)
        own_gc.start()
        await asyncio.sleep(2.0)  # the closed-mouth reference settles
        cpu0, t0 = cpu_seconds(pid), time.monotonic()
        sent_from, rtp_from = len(sent_at), len(sent_rtp)
        for _ in range(events):
            if voice:
                mic.fire()
            else:
                clicked()
            await asyncio.sleep(OPEN_S)
            drives.jaw(0.0)
            await asyncio.sleep(EVENT_EVERY_S - OPEN_S)
        cpu = (cpu_seconds(pid) - cpu0) / (time.monotonic() - t0)
        await tracker
        await own_loop.stop()
        own_gc.stop()
        set_process_nice(0, niceness)
        mic_gap, send_gap = longest_gap_ms(sent_at[sent_from:]), longest_gap_ms(sent_rtp[rtp_from:])
        records = []
        for _ in workers:
            got = await asyncio.to_thread(results.get, True, 300)
            if isinstance(got, str):
                raise RuntimeError(got)
            records += got
        for w in workers:
            if processes:
                w.join(30)
        after = server_voice_counts(url, token)
        stalls = await asyncio.to_thread(stalls_out.get, True, 60)
        steal = steal_ms() - steal0
        watch.join(10)
    offsets, missed, gaps, mouth_lags, click_lags = [], 0, [], [], []
    for rec in records:
        at = np.asarray(rec["packets"])  # the events' span: not the joins' and leaves' stalls
        times = np.diff(at[(at >= fired[0] - 0.5) & (at <= fired[-1] + EVENT_EVERY_S)])
        gaps.append(float(times.max() * 1e3) if len(times) else float("nan"))
        if not rec["decodes"]:  # no picture: its audio gaps only
            continue
        for f, mouth, click in zip(fired, pair(fired, rec["mouth"]), pair(fired, rec["clicks"]),
                                   strict=True):
            if mouth is None or click is None:
                missed += 1
            else:
                offsets.append((click - mouth) * 1e3)
                mouth_lags.append((mouth - f) * 1e3)
                click_lags.append((click - f) * 1e3)
    arr = np.asarray(offsets)
    sr = np.asarray([x for rec in records for x in rec["sr_offsets"]])
    first = records[0]
    at, seqs = np.asarray(first["packets"]), np.asarray(first["seqs"])
    worst = np.argsort(np.diff(at))[::-1][:5]  # anywhere in the run, the joins included
    print("# first viewer's longest audio gaps: (s after the first event, ms, packets missing) "
          f"{[(round(at[i] - fired[0], 2), round((at[i + 1] - at[i]) * 1e3), int((seqs[i + 1] - seqs[i] - 1) % 65536)) for i in sorted(worst)]}",  # noqa: E501
          file=sys.stderr, flush=True)
    span = (at >= fired[0] - 0.5) & (at <= fired[-1] + EVENT_EVERY_S)
    long_gaps = [(a, b) for a, b, inside in zip(at[:-1], at[1:], span[:-1], strict=True)
                 if inside and b - a > 0.060]
    print(f"# {stall_text(stalls, long_gaps, steal)}; the server's voice gaps: "
          f"{voice_gap_text(before, after)}; the performer's process: "
          f"{own_text(own_metrics, own_loop)}", file=sys.stderr, flush=True)
    print(f"# {viewers} viewers in {processes} processes, mouth at {mouth_clock}: fired "
          f"{len(fired)}, peers lost {sum(r['lost'] for r in records)}, mouth edges "
          f"{[len(r['mouth']) for r in records]}, clicks {[len(r['clicks']) for r in records]},"
          f" audio packets {[len(r['packets']) for r in records]}, video frames "
          f"{[r['frames'] for r in records]}, viewer CPU s/s each "
          f"{[round(r['cpu'], 3) for r in records]}, viewer processes' longest garbage-"
          f"collector pause ms {sorted({round(r['gc_max_ms']) for r in records})}"
          f", clicks without an arrival "
          f"{sum(r['missed_arrivals'] for r in records)}, server voice packets "
          f"{ {k: after.get(k, 0) - before.get(k, 0) for k in after if k.isidentifier()} }; "
          f"server event loop {loop_lag_text(before, after)}; server garbage collector "
          f"{gc_text(before, after)}; first viewer, ms "
          f"after each event: mouth "
          f"{[round((m - f) * 1e3) for f, m in zip(fired, first['mouth'], strict=False)]}, "
          f"click {[round((c - f) * 1e3) for f, c in zip(fired, first['clicks'], strict=False)]}",
          file=sys.stderr, flush=True)
    return {"viewers": viewers, "events": len(fired), "paired": len(offsets), "missed": missed,
            "median_ms": float(np.median(arr)) if len(arr) else float("nan"),
            "p5_ms": float(np.percentile(arr, 5)) if len(arr) else float("nan"),
            "p95_ms": float(np.percentile(arr, 95)) if len(arr) else float("nan"),
            "min_ms": float(arr.min()) if len(arr) else float("nan"),
            "max_ms": float(arr.max()) if len(arr) else float("nan"),
            "within": float(((arr >= -45) & (arr <= 125)).mean()) if len(arr) else 0.0,
            "sr": (f"{np.median(sr):.0f} ({np.percentile(sr, 5):.0f} / "
                   f"{np.percentile(sr, 95):.0f}), {((sr >= -45) & (sr <= 125)).mean():.0%} of "
                   f"{len(sr)}") if len(sr) else "-",
            "mouth_lag": lag_text(mouth_lags), "click_lag": lag_text(click_lags),
            "max_gap_ms": max(gaps), "mic_gap_ms": mic_gap, "send_gap_ms": send_gap,
            "cpu": cpu,
            "overflow": after.get("overflow", 0) - before.get("overflow", 0)}


def add_server_voice_args(parser: argparse.ArgumentParser) -> None:
    """The server's voice settings a run may set, each a comma list run side by side."""
    parser.add_argument("--pacing", default="frames", help="the server's voice_pacing per "
                        "run, side by side: even, frames or even,frames")
    parser.add_argument("--sender-clock", default="capture,send", help="the server's "
                        "webrtc_sender_clock per run: capture, send or capture,send")
    parser.add_argument("--max-delay-s", default="default", help="the server's "
                        "voice_max_delay_s per run (default: unset), e.g. default,0")


def server_voice_runs(args: argparse.Namespace):
    """Each (pacing, sender clock, max delay) of ``args`` in turn, set in the environment the
    server reads; yields the three."""
    for pacing, clock, delay in itertools.product(args.pacing.split(","),
                                                  args.sender_clock.split(","),
                                                  args.max_delay_s.split(",")):
        os.environ["TELESPLAT_VOICE_PACING"] = pacing
        os.environ["TELESPLAT_WEBRTC_SENDER_CLOCK"] = clock
        os.environ.pop("TELESPLAT_VOICE_MAX_DELAY_S", None)
        if delay != "default":
            os.environ["TELESPLAT_VOICE_MAX_DELAY_S"] = delay
        yield pacing, clock, delay


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--events", type=int, default=50)
    parser.add_argument("--viewers", default="1,16")
    parser.add_argument("--caps", default="0,500000", help="webrtc_max_bitrate per run; 0: "
                                                           "the default")
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--open-pixels", type=int, default=8)
    parser.add_argument("--avatar", default="synthetic")
    parser.add_argument("--voice", default="on", help="on, off or on,off: runs with and "
                                                      "without the performer's microphone "
                                                      "(the server CPU it costs)")
    parser.add_argument("--processes", default="4", help="viewer processes per run, e.g. 0,4 "
                                                         "(0: in the performer's process)")
    parser.add_argument("--drive-hz", default="30", help="drives a second between events "
                        "(a webcam performer's rate; 0: only at the jaw's edges), e.g. 0,30")
    parser.add_argument("--edge-drive", default="tick", help="tick (a jaw edge is one of "
                        "the drive-hz drives) or extra (a drive between them, as before "
                        "2026-11-27's fifth session), e.g. tick,extra")
    parser.add_argument("--performer-nice", type=int, default=0, help="the performer's "
                        "niceness over the bench's while the events run, all its threads "
                        "(negative, as root: a performer that does not wait for the cores the "
                        "server and the viewers share, as a remote one would not)")
    parser.add_argument("--server-nice", type=int, default=0, help="the server's niceness "
                        "over the bench's, all its threads (negative, as root: a server whose "
                        "cores the viewers and the performer do not share)")
    parser.add_argument("--viewer-nice", type=int, default=0, help="the viewer processes' "
                        "niceness over the bench's: on one machine, 16 viewers take the cores "
                        "the performer and the server need (viewers are elsewhere in use)")
    parser.add_argument("--video-decode", default="all", choices=("all", "first"),
                        help="first: in each viewer process only the first viewer decodes "
                        "its video (the others drop it undecoded; their audio gaps count)")
    parser.add_argument("--mouth-clock", default="arrival", help="arrival (the frame's last "
                        "RTP packet, as the click's), decode, or arrival,decode")
    add_server_voice_args(parser)
    args = parser.parse_args()
    print("| pacing | sender clock | voice_max_delay_s | viewers | processes | mouth clock | "
          "drives/s | edge drive | cap bit/s | events | paired | "
          "missed | "
          "median ms | p5 / p95 ms | min / max ms | within -45/+125 | mouth after event ms | "
          "click after event ms | on the sender reports' clock: median (p5 / p95) ms, within | "
          "longest audio gap ms "
          "(viewers / sent / mic) | server overflow drops | voice | server CPU s/s |")
    print("|---" * 23 + "|")
    most = max(int(v) for v in args.viewers.split(","))
    os.environ["TELESPLAT_WEBRTC_MAX_PEERS"] = str(most + 2)  # the viewers and the performer
    caps = [int(c) for c in args.caps.split(",")]
    # lazily: each run's settings are in the environment while its caps run
    for (pacing, sender_clock, delay), cap in ((run, cap) for run in server_voice_runs(args)
                                               for cap in caps):
        os.environ.pop("TELESPLAT_WEBRTC_MAX_BITRATE", None)
        os.environ.pop("TELESPLAT_WEBRTC_MIN_BITRATE", None)
        if cap:
            os.environ["TELESPLAT_WEBRTC_MAX_BITRATE"] = str(cap)
            os.environ["TELESPLAT_WEBRTC_MIN_BITRATE"] = str(min(cap, 250_000))
        with tempfile.TemporaryDirectory() as tmp:
            proc, url, token = start_server(Path(tmp), 1, 64, args.avatar)
            set_process_nice(args.server_nice, pid=proc.pid)
            try:
                for n, procs, clock, hz, edges, voice in itertools.product(
                        [int(v) for v in args.viewers.split(",")],
                        [int(p) for p in args.processes.split(",")],
                        args.mouth_clock.split(","), [float(h) for h in args.drive_hz.split(",")],
                        args.edge_drive.split(","), args.voice.split(",")):
                    r = asyncio.run(run(url, token, n, args.events, args.size,
                                        args.open_pixels, proc.pid, voice == "on", procs,
                                        clock, hz, edges, args.viewer_nice,
                                        args.performer_nice, args.video_decode))
                    print(f"| {pacing} | {sender_clock} | {delay} | {n} | {procs} | {clock} | "
                          f"{hz:g} | {edges} | {cap or 'default'} | "
                          f"{r['events']} | {r['paired']} | {r['missed']} | {r['median_ms']:.0f} | "
                          f"{r['p5_ms']:.0f} / {r['p95_ms']:.0f} | {r['min_ms']:.0f} / "
                          f"{r['max_ms']:.0f} | {r['within']:.0%} | {r['mouth_lag']} | "
                          f"{r['click_lag']} | {r['sr']} | {r['max_gap_ms']:.0f} / "
                          f"{r['send_gap_ms']:.0f} / {r['mic_gap_ms']:.0f} | "
                          f"{r['overflow']:.0f} | {voice} | "
                          f"{r['cpu']:.2f} |", flush=True)
            finally:
                stop_server(proc)
                stalls = [line for line in proc.tail if "event loop held" in line]
                if stalls:  # loop_stall_log_ms: each stall's stack follows its line
                    print(f"# server event loop stalls logged: {len(stalls)}; the log's "
                          "tail:\n" + "".join(proc.tail), file=sys.stderr, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
