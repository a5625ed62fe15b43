"""One WebRTC peer: an aiortc peer connection around a room's session.

The session is the stream's own (server/stream/session.py: latest-wins render loop, pacing,
fair share, seat and presence) composed with a :class:`~.transport.WebRTCTransport`: its
frames go to a :class:`~.fanout.FanoutTrack` (the room's one encode of each picture, shared by
its viewers; ``webrtc_shared_encode``) or, stamped or with sharing off, as raw RGB arrays to a
:class:`~.track.LatestFrameTrack` that aiortc encodes for this peer; its messages use the data
channel. Encoders run in threads; rendering stays where the scene's frames are made. A peer
ends on DELETE, when its room closes, when its transport fails or never connects
(``webrtc_connect_timeout_s``), when its data channel carries a message past
``webrtc_max_message_bytes`` (its :class:`~.sctp.SctpGuard`), and at server shutdown; each
path goes through :meth:`WebRTCPeer.close`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from typing import Any

from aiortc import RTCPeerConnection
from aiortc.mediastreams import VIDEO_CLOCK_RATE

from protocol import Request, encode
from protocol.rtp_receiver import release_on_marker

from ..context import ServerContext
from ..rooms.join import seat_participant, serve
from ..rooms.registry import Room
from ..rooms.voice import CLOCK_RATE, seat_voice
from ..rooms.voice_mix import room_mix
from ..stream.admission import Admitted
from ..stream.session import Session, error_message
from .audio import VoiceTrack, opus_payload_type, publish_voice, refuse_voice
from .channel import DataChannel
from .encoders import install_encoder
from .fanout import FanoutTrack, room_fanout
from .ingest import ingest
from .negotiate import Kind, Offer, answer, configuration
from .publisher_clock import PublisherClock
from .sctp import GuardLimits, SctpGuard
from .sender_clock import CaptureEpoch, report_capture_clock
from .track import LatestFrameTrack
from .transport import WebRTCTransport

log = logging.getLogger(__name__)

CLOSE_WAIT_S = 5.0  # teardown waits this long for the session's tasks


class WebRTCPeer:
    def __init__(self, ctx: ServerContext, kind: Kind, resource: str, room: Room,
                 token_digest: str, admitted: Admitted) -> None:
        self.ctx, self.kind, self.resource, self.room = ctx, kind, resource, room
        self.admitted = admitted  # its session slot, given back at teardown
        self.token_digest = token_digest  # DELETE must show the same token (or the owner's)
        self.pc = RTCPeerConnection(configuration(ctx.settings))
        self.channel = DataChannel(on_close=self._close_soon, metrics=ctx.metrics)
        # Data-channel bytes budgeted before aiortc reassembles them (server/webrtc/sctp.py).
        self.guard = SctpGuard(GuardLimits.from_settings(ctx.settings), self._too_large,
                               metrics=ctx.metrics, name=resource)
        self.track: LatestFrameTrack | FanoutTrack | None = None
        self.epoch: CaptureEpoch | None = None  # webrtc_sender_clock = capture: both tracks'
        self.publisher_clock = PublisherClock()  # what it publishes, on its reports' clock
        self.participant: Session | None = None
        self.codec: str | None = None      # negotiated video codec (MIME type), watching
        self.encoder: Any = None           # our clamped encoder, once installed
        self.voices: dict[str, VoiceTrack] = {}  # audio mid -> the seat voice sent on it
        self.voice_counts: dict[str, int] = {}   # audio this peer may not publish, dropped
        self._connected = asyncio.Event()
        self._tasks: set[asyncio.Task] = set()
        self._run: asyncio.Task | None = None
        self._closing: asyncio.Task | None = None

    # -- opening --------------------------------------------------------------------------------

    async def start(self, offer: Offer, role: str, seat: int, request: Request | None,
                    stamp: bool, name: str | None = None, voice_mix: bool = False) -> str:
        """Seat the participant, answer the offer, start everything; the answer SDP. Raises
        Refusal (seating) or OfferRefused (the SDP); the peer is closed then."""
        s = self.ctx.settings
        # capture clock: both tracks' timestamps and sender reports count from this epoch
        self.epoch = CaptureEpoch.now() if s.webrtc_sender_clock == "capture" else None
        if offer.watch_mid is not None and s.webrtc_shared_encode and not stamp:
            self.track = FanoutTrack(epoch=self.epoch, max_lag_s=s.webrtc_max_sync_lag_s)
        elif offer.watch_mid is not None:  # a stamped frame is this peer's own picture
            self.track = LatestFrameTrack(epoch=self.epoch,
                                          max_lag_s=s.webrtc_max_sync_lag_s)
        self.pc.on("datachannel", self.channel.attach)
        if not offer.data_channel:
            self.channel.absent()
        self.pc.on("track", self._on_track)
        self.pc.on("connectionstatechange", self._on_state)
        try:
            transport = WebRTCTransport(self.channel, self.track, stamp)
            if isinstance(self.track, FanoutTrack):
                self.track.captured_at_of = transport.captured_at
            self.participant, welcome = await seat_participant(
                self.ctx, self.room, role, seat, name, transport, request=request)
            self.channel.welcome = encode(welcome)
            self._run = self._spawn(self._serve(), "serve")
            if voice_mix:
                self.voices, transport.voices = self._mix(offer)
            else:
                self.voices = self._voices(offer, role, seat)
                transport.voices = [(t.position, t.listener) for t in self.voices.values()]
            # the browser syncs the video with one voice of its stream: the first seat heard
            # (a mix, or none: the participant's own seat)
            transport.clock_position = min((t.position for t in self.voices.values()
                                            if t.position >= 0),
                                           default=self.participant.position)
            speaks = role == "perform" and offer.microphone_mid is not None
            sdp, self.codec = await answer(self.pc, offer, self.track, self.guard,
                                           self.voices, speaks)
            self._hear(offer, sdp, speaks, seat)
        except BaseException:
            await self.close("the offer was refused")
            raise
        if self.codec is not None:
            sender = next(t.sender for t in self.pc.getTransceivers()
                          if t.mid == offer.watch_mid)
            self.encoder = install_encoder(sender, self.codec, s.webrtc_min_bitrate,
                                           s.webrtc_max_bitrate)
            if isinstance(self.track, FanoutTrack):  # the encoder only packs, the room's encodes
                self.track.attach(room_fanout(self.room.live, s), sender, self.codec,
                                  self.encoder)
        if self.epoch is not None:
            self._report_capture_clock(offer)
        self._spawn(self._connect_deadline(s.webrtc_connect_timeout_s), "deadline")
        return sdp

    def _report_capture_clock(self, offer: Offer) -> None:
        """Each sending track's sender reports on its capture instants (sender_clock.py)."""
        tracks = {**self.voices, offer.watch_mid: self.track}
        for transceiver in self.pc.getTransceivers():
            track = tracks.get(transceiver.mid)
            if track is not None and transceiver.sender.track is track:
                report_capture_clock(transceiver.sender, track, self.epoch)

    def _voices(self, offer: Offer, role: str, seat: int) -> dict[str, VoiceTrack]:
        """The offer's received audio m-lines carry the room's seats in order; a performer
        does not get its own seat's voice back."""
        seats = self.room.live.seats
        return {mid: VoiceTrack(seat_voice(seats[i], self.ctx.settings,
                                           self.ctx.metrics).subscribe(), i, self.epoch)
                for i, mid in enumerate(offer.voice_mids[:len(seats)])
                if not (role == "perform" and seats[i].index == seat)}

    def _mix(self, offer: Offer) -> tuple[dict[str, VoiceTrack], list[tuple[int, Any]]]:
        """The room's one mix on the offer's first received audio m-line, and the seat
        listeners this peer's frames lead (server/rooms/voice_mix.py)."""
        if not offer.voice_mids:
            return {}, []
        mix = room_mix(self.room.live, self.ctx.settings, self.ctx.metrics)
        track = VoiceTrack(mix.subscribe(), -1, self.epoch)  # stamped when mixed
        return {offer.voice_mids[0]: track}, mix.followers()

    def _hear(self, offer: Offer, sdp: str, speaks: bool, seat: int) -> None:
        """The performer's microphone feeds its seat's voice; any other audio a client
        sends is dropped and counted (a viewer never publishes)."""
        for transceiver in self.pc.getTransceivers():
            if transceiver.kind != "audio":
                continue
            pt = opus_payload_type(sdp, transceiver.mid)
            if speaks and transceiver.mid == offer.microphone_mid and pt is not None:
                voice = seat_voice(self.room.live.seat(seat), self.ctx.settings,
                                   self.ctx.metrics)
                # its drives come from its webcam, on its reports' clock: so does its voice
                # (a WHEP performer's drives carry stamps of a clock of its own)
                reports = (None if offer.publish_mid is None
                           else self.publisher_clock.watch(transceiver.receiver, CLOCK_RATE))
                publish_voice(transceiver.receiver, voice, self, pt, reports,
                              self.participant.capture_clock)
            else:
                refuse_voice(transceiver.receiver, self.ctx.metrics, self.voice_counts)

    def _spawn(self, coro, what: str) -> asyncio.Task:
        task = asyncio.get_running_loop().create_task(coro, name=f"peer {self.resource} {what}")
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    async def _serve(self) -> None:
        try:
            await serve(self.ctx, self.participant)  # the welcome: when the channel opens
        finally:
            self._close_soon("the session ended")

    def _on_track(self, track: Any) -> None:
        if self.kind == "whip" and track.kind == "video" and self.participant is not None:
            receiver = next((t.receiver for t in self.pc.getTransceivers()
                             if t.receiver.track is track), None)
            reports = None
            if receiver is not None:  # the webcam's capture times, as its microphone's
                reports = self.publisher_clock.watch(receiver, VIDEO_CLOCK_RATE)
                release_on_marker(receiver)  # each frame tracked at its last packet
            self._spawn(ingest(track, self.participant, reports), "ingest")

    def _on_state(self) -> None:
        state = self.pc.connectionState
        if state == "connected":
            self._connected.set()
        elif state in ("failed", "closed"):
            self._close_soon(f"the connection {state}")

    def _too_large(self, size: int) -> None:
        """A data-channel message grew past webrtc_max_message_bytes (the guard refuses the
        rest): the client is told, and the peer closed."""
        limit = self.ctx.settings.webrtc_max_message_bytes
        self.channel.send_last(encode(error_message(
            "too_large", f"a data-channel message of more than {limit} bytes (the answer's "
                         "a=max-message-size, webrtc_max_message_bytes): the peer is closed")))
        self._close_soon(f"a data-channel message passed {size} bytes "
                         f"(webrtc_max_message_bytes {limit})")

    async def _connect_deadline(self, timeout_s: float) -> None:
        try:
            await asyncio.wait_for(self._connected.wait(), timeout_s)
        except TimeoutError:
            log.info("WebRTC peer %s did not connect within %g s", self.resource, timeout_s)
            self._close_soon("not connected within webrtc_connect_timeout_s")

    # -- closing --------------------------------------------------------------------------------

    @property
    def closed(self) -> bool:
        return self._closing is not None

    def _close_soon(self, reason: str) -> None:
        if self._closing is None:
            self._closing = asyncio.get_running_loop().create_task(self._teardown(reason))

    async def close(self, reason: str) -> None:
        """End the peer (idempotent); returns once it is torn down and its slot free."""
        self._close_soon(reason)
        await asyncio.shield(self._closing)

    async def _teardown(self, reason: str) -> None:
        log.info("WebRTC peer %s (%s) closing: %s; data channel: %s", self.resource,
                 self.kind, reason, self.guard.summary())
        try:
            self.guard.stop()  # nothing more reaches the session
            # refused: its too_large was queued last (_too_large); let it out before the abort
            if self.guard.refused and not await self.guard.flush(
                    self.ctx.settings.webrtc_close_flush_s):
                log.info("WebRTC peer %s: its last message was not acknowledged within "
                         "webrtc_close_flush_s", self.resource)
            self.channel.disconnect()  # the participant's receiver returns: run() ends
            if self.track is not None:
                self.track.stop()
            for voice in self.voices.values():
                voice.stop()
            with contextlib.suppress(Exception):
                await self.pc.close()
            pending = [t for t in self._tasks if t is not asyncio.current_task()]
            for task in pending:
                if task is not self._run:
                    task.cancel()
            if pending:
                await asyncio.wait(pending, timeout=CLOSE_WAIT_S)
        finally:
            self.admitted.release()
            self.ctx.webrtc_peers.release(self.resource)
