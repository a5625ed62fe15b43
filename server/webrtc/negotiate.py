"""The SDP side of a peer: check an offer before anything is made, then answer it.

An offer is checked with aiortc's own parser first (400 for what it cannot use): a WHEP offer
needs a video m-line the client receives (recvonly or sendrecv); a WHIP offer needs one it
sends (sendonly or sendrecv) and may carry one it receives too. Either needs VP8 or H.264 on
those m-lines. The answer carries every ICE candidate (aiortc gathers them all before
``setLocalDescription`` returns: no trickle). Codecs: aiortc answers with the common codecs
in the offer's order (its ``find_common_codecs`` walks the offer's list), so the offer's
preference between VP8 and H.264 wins. Audio m-lines with Opus are voices
(server/webrtc/audio.py): those the client receives carry the room's seats in order, the
first it sends is its microphone (used only when it performs). m-lines the peer does not use
(extra video, audio without Opus) are answered inactive, so nothing arrives that no one
reads. The SCTP transport aiortc makes
for an offered data channel gets its guard (server/webrtc/sctp.py) before the answer is made,
so the answer advertises its max-message-size and receive window.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

from aiortc import (
    RTCBundlePolicy,
    RTCConfiguration,
    RTCIceServer,
    RTCPeerConnection,
    RTCSessionDescription,
)
from aiortc import sdp as aiortc_sdp

VIDEO_CODECS = ("video/vp8", "video/h264")
AUDIO_CODEC = "audio/opus"
RECEIVING = ("recvonly", "sendrecv")  # the client receives (watches) on this m-line
SENDING = ("sendonly", "sendrecv")    # the client sends (publishes) on it

Kind = Literal["whep", "whip"]


class OfferRefused(ValueError):
    """An offer this server cannot answer (HTTP 400)."""


@dataclass(frozen=True)
class Offer:
    sdp: str
    watch_mid: str | None     # the video m-line our track goes out on
    publish_mid: str | None   # the video m-line the client's webcam comes in on (WHIP)
    data_channel: bool
    voice_mids: tuple[str, ...] = ()  # audio m-lines the client receives: seat 0, 1, ... in order
    microphone_mid: str | None = None  # the first audio m-line the client sends on


def _usable(media: Any) -> bool:
    return any(c.mimeType.lower() in VIDEO_CODECS for c in media.rtp.codecs)


def check_offer(text: str, kind: Kind) -> Offer:
    """The offer's m-lines this peer uses; OfferRefused when it cannot be answered."""
    try:
        description = aiortc_sdp.SessionDescription.parse(text)
    except Exception as exc:  # noqa: BLE001 - any parser failure is the client's SDP
        raise OfferRefused(f"unparseable SDP offer: {type(exc).__name__}: {exc}") from None
    if not description.media:
        raise OfferRefused("the SDP offer has no m-line (is the body an SDP offer?)")
    videos = [m for m in description.media if m.kind == "video"]
    if not videos:
        raise OfferRefused("the SDP offer has no video m-line")
    if any(m.rtp.muxId is None or m.rtp.muxId == "" for m in videos):
        raise OfferRefused("every video m-line needs an a=mid (BUNDLE)")

    def first(directions: tuple[str, ...], but: str | None = None) -> Any:
        return next((m for m in videos if (m.direction or "sendrecv") in directions
                     and m.rtp.muxId != but), None)

    if kind == "whep":
        watch, publish = first(RECEIVING), None
        if watch is None:
            raise OfferRefused("a WHEP offer needs a recvonly (or sendrecv) video m-line")
    else:
        publish = first(SENDING)
        if publish is None:
            raise OfferRefused("a WHIP offer needs a sendonly (or sendrecv) video m-line")
        watch = (publish if (publish.direction or "sendrecv") == "sendrecv"
                 else first(("recvonly",), but=publish.rtp.muxId))
    for media in (watch, publish):
        if media is not None and not _usable(media):
            raise OfferRefused(f"no common video codec on m-line {media.rtp.muxId!r}: this "
                               f"server sends and receives {', '.join(VIDEO_CODECS)}")
    audios = [m for m in description.media if m.kind == "audio" and m.rtp.muxId
              and any(c.mimeType.lower() == AUDIO_CODEC for c in m.rtp.codecs)]
    microphone = next((m for m in audios if (m.direction or "sendrecv") in SENDING), None)
    return Offer(text, None if watch is None else watch.rtp.muxId,
                 None if publish is None else publish.rtp.muxId,
                 any(m.kind == "application" for m in description.media),
                 tuple(m.rtp.muxId for m in audios if (m.direction or "sendrecv") in RECEIVING),
                 None if microphone is None else microphone.rtp.muxId)


def configuration(settings) -> RTCConfiguration:
    """ICE servers from the settings; an empty list (not aiortc's default, a public STUN
    server) when none are set: host candidates only.

    Max-bundle: every m-line on the first one's transport. aiortc's default (balanced) gives
    a second audio m-line the first audio line's own transport and marks it bundled, so the
    offer's BUNDLE moves the first audio line to the shared transport but not the second: a
    viewer's second seat's voice then never left (its sender waited on a transport that
    never connected)."""
    servers = [RTCIceServer(urls=url, username=settings.webrtc_turn_username,
                            credential=settings.webrtc_turn_credential)
               if url.startswith("turn") else RTCIceServer(urls=url)
               for url in settings.webrtc_ice_servers]
    return RTCConfiguration(iceServers=servers, bundlePolicy=RTCBundlePolicy.MAX_BUNDLE)


async def answer(pc: RTCPeerConnection, offer: Offer, track: Any, guard: Any = None,
                 voices: dict[str, Any] | None = None,
                 microphone: bool = False) -> tuple[str, str | None]:
    """Apply ``offer``, attach ``track`` to its watched m-line and ``voices`` (mid -> audio
    track) to its audio m-lines, receive on its microphone m-line when ``microphone``, install
    ``guard`` (a :class:`~.sctp.SctpGuard`) on the data channel's SCTP transport, answer;
    (answer SDP, the negotiated video codec's MIME type on the watched m-line or None)."""
    voices = voices or {}
    try:
        await pc.setRemoteDescription(RTCSessionDescription(offer.sdp, "offer"))
    except Exception as exc:  # noqa: BLE001 - aiortc refuses the client's SDP
        raise OfferRefused(f"cannot apply the SDP offer: {type(exc).__name__}: {exc}") from None
    if guard is not None and pc.sctp is not None:
        guard.install(pc.sctp)  # before the answer (its a=max-message-size) and the INIT
    for transceiver in pc.getTransceivers():
        if transceiver.kind == "audio":
            watched = voices.get(transceiver.mid) is not None
            published = microphone and transceiver.mid == offer.microphone_mid
            if watched:
                transceiver.sender.replaceTrack(voices[transceiver.mid])
        else:
            watched = transceiver.kind == "video" and transceiver.mid == offer.watch_mid
            published = transceiver.kind == "video" and transceiver.mid == offer.publish_mid
            if watched:
                transceiver.sender.replaceTrack(track)
        transceiver.direction = {(True, True): "sendrecv", (True, False): "sendonly",
                                 (False, True): "recvonly"}.get((watched, published),
                                                                "inactive")
    await pc.setLocalDescription(await pc.createAnswer())
    local = pc.localDescription.sdp
    codec = None
    if offer.watch_mid is not None:
        for media in aiortc_sdp.SessionDescription.parse(local).media:
            if media.rtp.muxId == offer.watch_mid and media.rtp.codecs:
                codec = media.rtp.codecs[0].mimeType.lower()
    return local, codec
