"""A WHEP viewer in Python (aiortc): watch a room over WebRTC, drive over its data channel.

    async with WhepViewer("http://127.0.0.1:8000", room_id, token, width=512, height=512) as v:
        print(v.codec, (await v.welcome()).room)
        v.send(Drive(seq=1, flame={"jaw_pose": [0.3, 0, 0]}))
        async for rgb, received_at in v.frames():
            ...  # [H, W, 3] uint8, time.monotonic() at decode

It offers a recvonly video (VP8 and H.264, ``codec`` first when given) and the data channel
``telesplat``; ``voices=n`` adds n recvonly Opus audio m-lines (the room's seats 0..n-1, in
the same MediaStream as the video: :meth:`next_audio`; with ``voice_mix`` the first carries
the room's one mix of them), ``microphone=track`` a sendonly one
the server forwards to the viewers when this peer performs. Each video frame is decoded at its
last packet (the RTP marker bit), as a browser does (protocol/rtp_receiver.py;
``release_at_marker=False`` keeps aiortc's buffer, which waits for the next frame's first
packet: one frame interval later). The answer's ``Location`` is
DELETEd by :meth:`close`. HTTP refusals raise :class:`WhepError` with the status and the
server's ``detail``.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Callable
from typing import Any, Literal
from urllib.parse import urlencode

import httpx
import numpy as np

from protocol import decode_server, encode

CHANNEL_LABEL = "telesplat"
SDP_TYPE = "application/sdp"
MESSAGES = 256  # server messages kept unread; past it the oldest go


class WhepError(RuntimeError):
    def __init__(self, status: int, detail: Any, url: str = "") -> None:
        super().__init__(f"HTTP {status} from {url}: {detail}")
        self.status, self.detail = status, detail


class WhepViewer:
    def __init__(self, base_url: str, room: str, token: str | None, *,
                 width: int | None = None, height: int | None = None,
                 fps: float | None = None, seat: int | None = None,
                 role: Literal["perform", "watch"] | None = None, stamp: bool = False,
                 codec: Literal["vp8", "h264"] | None = None, data_channel: bool = True,
                 voices: int = 0, microphone: Any = None, voice_mix: bool = False,
                 release_at_marker: bool = True, timeout_s: float = 20.0) -> None:
        query = {k: v for k, v in {"width": width, "height": height, "fps": fps, "seat": seat,
                                   "role": role, "stamp": int(stamp) if stamp else None,
                                   "voice": "mix" if voice_mix else None,
                                   }.items() if v is not None}
        self.base_url = base_url.rstrip("/")
        self.url = f"{self.base_url}/v1/rooms/{room}/whep" + (
            f"?{urlencode(query)}" if query else "")
        self.token = token
        self.codec_preference = codec
        self.data_channel = data_channel
        self.voices = voices
        self.microphone = microphone
        self.release_at_marker = release_at_marker
        self._audio: list[asyncio.Future] = []  # the received voices' tracks, seat order
        self.timeout_s = timeout_s
        self.location: str | None = None
        self.codec: str | None = None  # negotiated, e.g. "video/VP8"
        self.pc: Any = None
        self.channel: Any = None
        self._track: asyncio.Future | None = None
        self._messages: asyncio.Queue = asyncio.Queue(MESSAGES)
        self._channel_open: asyncio.Event | None = None

    def _headers(self, content_type: str | None = None) -> dict[str, str]:
        headers = {} if self.token is None else {"Authorization": f"Bearer {self.token}"}
        if content_type:
            headers["Content-Type"] = content_type
        return headers

    async def start(self) -> WhepViewer:
        """Offer, POST, apply the answer; WhepError on a refusal."""
        from aiortc import (
            RTCBundlePolicy,
            RTCConfiguration,
            RTCPeerConnection,
            RTCSessionDescription,
        )
        from aiortc.rtcrtpsender import RTCRtpSender

        from protocol.rtp_receiver import release_on_marker

        loop = asyncio.get_running_loop()
        # max-bundle: with aiortc's default a second voice line stays on a transport that
        # never connects (server/webrtc/negotiate.py's configuration says how)
        self.pc = pc = RTCPeerConnection(RTCConfiguration(
            iceServers=[], bundlePolicy=RTCBundlePolicy.MAX_BUNDLE))
        self._track = loop.create_future()
        self._channel_open = asyncio.Event()
        transceiver = pc.addTransceiver("video", direction="recvonly")
        if self.release_at_marker:  # decoded at its last packet, as a browser does
            release_on_marker(transceiver.receiver)
        voices = [pc.addTransceiver("audio", direction="recvonly") for _ in range(self.voices)]
        self._audio = [loop.create_future() for _ in voices]
        if self.microphone is not None:
            pc.addTransceiver(self.microphone, direction="sendonly")
        if self.codec_preference is not None:
            want = f"video/{self.codec_preference}".lower()
            caps = RTCRtpSender.getCapabilities("video").codecs
            transceiver.setCodecPreferences(sorted(caps, key=lambda c: c.mimeType.lower()
                                                   != want))

        @pc.on("track")
        def _on_track(track: Any) -> None:
            if track.kind == "video" and not self._track.done():
                self._track.set_result(track)
            for transceiver, future in zip(voices, self._audio, strict=True):
                if transceiver.receiver.track is track and not future.done():
                    future.set_result(track)

        if self.data_channel:
            self.channel = pc.createDataChannel(CHANNEL_LABEL, ordered=True)
            self.channel.on("open", self._channel_open.set)
            self.channel.on("message", self._on_message)
        await pc.setLocalDescription(await pc.createOffer())
        try:
            async with httpx.AsyncClient(timeout=self.timeout_s) as http:
                response = await http.post(self.url, content=pc.localDescription.sdp,
                                           headers=self._headers(SDP_TYPE))
            if response.status_code != 201:
                raise WhepError(response.status_code, _detail(response), self.url)
            self.location = response.headers["location"]
            await pc.setRemoteDescription(RTCSessionDescription(response.text, "answer"))
        except BaseException:
            await pc.close()
            raise
        self.codec = answered_codec(response.text)
        return self

    def _on_message(self, data: bytes | str) -> None:
        if isinstance(data, str):
            return
        if self._messages.full():
            self._messages.get_nowait()
        self._messages.put_nowait(decode_server(data))

    # -- messages -------------------------------------------------------------------------------

    def send(self, message: Any) -> None:
        """A protocol message (Drive, View, Request, Ping ...) over the data channel."""
        if self.channel is None or self.channel.readyState != "open":
            raise RuntimeError("the data channel is not open (await wait_open() first)")
        self.channel.send(encode(message))

    async def wait_open(self, timeout: float | None = None) -> None:
        await asyncio.wait_for(self._channel_open.wait(), timeout or self.timeout_s)

    async def message(self, predicate: Callable[[Any], bool] = lambda m: True,
                      timeout: float | None = None) -> Any:
        """The next server message satisfying ``predicate`` (others are skipped)."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + (timeout or self.timeout_s)
        while True:
            msg = await asyncio.wait_for(self._messages.get(), max(0.01, deadline - loop.time()))
            if predicate(msg):
                return msg

    async def welcome(self, timeout: float | None = None) -> Any:
        return await self.message(lambda m: m.type == "welcome", timeout)

    # -- frames ---------------------------------------------------------------------------------

    async def next_frame(self, timeout: float | None = None) -> tuple[np.ndarray, float]:
        """The next decoded frame: ([H, W, 3] uint8 RGB, time.monotonic() at decode)."""
        timeout = timeout or self.timeout_s
        track = await asyncio.wait_for(asyncio.shield(self._track), timeout)
        frame = await asyncio.wait_for(track.recv(), timeout)
        return frame.to_ndarray(format="rgb24"), time.monotonic()

    async def next_video_frame(self, timeout: float | None = None) -> Any:
        """The next decoded frame as aiortc gives it: an av.VideoFrame whose ``pts`` is its
        RTP timestamp less the track's first (90 kHz)."""
        timeout = timeout or self.timeout_s
        track = await asyncio.wait_for(asyncio.shield(self._track), timeout)
        return await asyncio.wait_for(track.recv(), timeout)

    async def next_audio(self, seat: int = 0, timeout: float | None = None
                         ) -> tuple[Any, float]:
        """The next decoded audio frame of seat ``seat``'s voice: (av.AudioFrame,
        time.monotonic() at decode)."""
        timeout = timeout or self.timeout_s
        track = await asyncio.wait_for(asyncio.shield(self._audio[seat]), timeout)
        frame = await asyncio.wait_for(track.recv(), timeout)
        return frame, time.monotonic()

    async def frames(self, timeout: float | None = None
                     ) -> AsyncIterator[tuple[np.ndarray, float]]:
        """Decoded frames until the stream ends (or none for ``timeout`` s: TimeoutError)."""
        from aiortc.mediastreams import MediaStreamError

        while True:
            try:
                yield await self.next_frame(timeout)
            except MediaStreamError:
                return

    async def stats(self) -> dict[str, Any]:
        """aiortc's getStats: the inbound video's counters (bytesReceived, packetsLost ...)."""
        report = await self.pc.getStats()
        return {k: v for k, v in report.items()}

    # -- closing --------------------------------------------------------------------------------

    async def close(self) -> None:
        """DELETE the session (errors ignored: the server may be gone), close the peer."""
        if self.location is not None:
            url, self.location = self.base_url + self.location, None
            try:
                async with httpx.AsyncClient(timeout=self.timeout_s) as http:
                    await http.delete(url, headers=self._headers())
            except httpx.HTTPError:
                pass
        if self.pc is not None:
            await self.pc.close()

    async def __aenter__(self) -> WhepViewer:
        return await self.start()

    async def __aexit__(self, *exc: Any) -> None:
        await self.close()


def _detail(response: httpx.Response) -> Any:
    try:
        return response.json().get("detail")
    except ValueError:
        return response.text


def answered_codec(answer_sdp: str) -> str | None:
    """The video codec an SDP answer chose (its first on the first video m-line)."""
    from aiortc import sdp

    for media in sdp.SessionDescription.parse(answer_sdp).media:
        if media.kind == "video" and media.rtp.codecs:
            return media.rtp.codecs[0].mimeType
    return None
