"""A hostile WHEP peer in its own process (so that it floods at full speed, not sharing the
test server's GIL): ``python -m tests.webrtc_flooder URL ROOM TOKEN (--pings N | --big BYTES)``.

It joins like any viewer (client/webrtc.py), prints ``ready {...}`` once its data channel is
open and the welcome came, then waits for a line on stdin. Then it either sends ``N`` pings
through aiortc's data channel (one SCTP packet each, as fast as its SCTP stack lets it) or
one message of ``BYTES`` bytes ignoring the answer's ``a=max-message-size`` (aiortc's sender
refuses larger messages; this client lifts its own check), watches for ``--hold`` seconds
(or until its peer connection closes) and prints ``done {...}``: what came back, what its
SCTP stack still had queued, and when the channel closed. ``--raw K`` sends the pings as raw
SCTP DATA chunks instead, K a packet, with no congestion control and no retransmission (what
a hostile SCTP stack may do).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import time

from client.webrtc import WhepViewer
from protocol import Ping, encode

# -- raw SCTP DATA chunks (what a hostile SCTP stack may send: any flags, order, stream) -------

PPID_BINARY = 53  # WebRTC binary message (RFC 8831)
SCTP_MAX_PACKET = 1189  # aiortc's packet size (fits the minimum IPv6 MTU under DTLS)


def data_chunk(sctp, stream_id: int, data: bytes, *, first: bool = True, last: bool = True,
               stream_seq: int | None = None):
    """The client's next TSN as one DATA chunk (aiortc's DataChunk); ``stream_seq`` None: the
    stream's next ordered sequence number (taken once per message, on its first fragment)."""
    from aiortc.rtcsctptransport import SCTP_DATA_FIRST_FRAG, SCTP_DATA_LAST_FRAG, DataChunk

    chunk = DataChunk(flags=(SCTP_DATA_FIRST_FRAG if first else 0)
                      | (SCTP_DATA_LAST_FRAG if last else 0))
    chunk.tsn = sctp._local_tsn
    sctp._local_tsn = (sctp._local_tsn + 1) % 2**32
    if stream_seq is None:
        stream_seq = sctp._outbound_stream_seq.get(stream_id, 0)
        if last:
            sctp._outbound_stream_seq[stream_id] = (stream_seq + 1) % 2**16
    chunk.stream_id, chunk.stream_seq, chunk.protocol = stream_id, stream_seq, PPID_BINARY
    chunk.user_data = data
    return chunk


def packets(sctp, chunks, per_packet: int | None = None) -> list[bytes]:
    """``chunks`` bundled into as few SCTP packets as fit SCTP_MAX_PACKET (and at most
    ``per_packet`` chunks each), in order."""
    import struct

    from google_crc32c import value as crc32c

    header = struct.pack("!HHL", sctp._local_port, sctp._remote_port,
                         sctp._remote_verification_tag)
    out: list[bytes] = []
    body, count = b"", 0
    for chunk in chunks:
        raw = bytes(chunk)
        if body and (len(header) + 4 + len(body) + len(raw) > SCTP_MAX_PACKET
                     or count == per_packet):
            out.append(header + struct.pack("<L", crc32c(header + bytes(4) + body)) + body)
            body, count = b"", 0
        body += raw
        count += 1
    if body:
        out.append(header + struct.pack("<L", crc32c(header + bytes(4) + body)) + body)
    return out


async def send_raw(sctp, chunks, pause_every: int = 20, per_packet: int | None = None) -> int:
    """Send ``chunks`` straight onto the DTLS transport (no congestion control, no
    retransmission); the number of packets."""
    sent = 0
    for packet in packets(sctp, chunks, per_packet):
        await sctp.transport._send_data(packet)
        sent += 1
        if sent % pause_every == 0:
            await asyncio.sleep(0.001)
    return sent


def _state(v: WhepViewer) -> dict:
    sctp = v.pc.sctp
    return {"channel": v.channel.readyState, "connection": v.pc.connectionState,
            "sctp": sctp.state if sctp is not None else None,
            "queued": (len(sctp._data_channel_queue) + len(sctp._outbound_queue)
                       + len(sctp._sent_queue)) if sctp is not None else None}


def _closed(v: WhepViewer) -> bool:
    return (v.channel.readyState in ("closing", "closed")
            or v.pc.connectionState in ("closed", "failed"))


async def run(args: argparse.Namespace) -> dict:
    v = WhepViewer(args.url, args.room, args.token, width=64, height=64, timeout_s=30.0)
    await v.start()
    try:
        await v.wait_open()
        await v.welcome()
        advertised = v.pc.sctp._remote_max_message_size
        print("ready " + json.dumps({"max_message_size": advertised}), flush=True)
        await asyncio.to_thread(sys.stdin.readline)  # the test's "go"
        started = time.monotonic()
        if args.big:
            v.pc.sctp._remote_max_message_size = 0  # ignore a=max-message-size
            v.channel.send(b"\x00" * args.big)
        elif args.raw:  # no congestion control, no retransmission
            ping = encode(Ping(t=1.0))
            sctp = v.pc.sctp
            await send_raw(sctp, [data_chunk(sctp, v.channel.id, ping)
                                  for _ in range(args.pings)], pause_every=20,
                           per_packet=args.raw)
        else:
            ping = encode(Ping(t=1.0))
            for i in range(args.pings):
                v.channel.send(ping)
                if i % 200 == 199:
                    await asyncio.sleep(0)  # let its SCTP stack transmit
        sent_s = time.monotonic() - started
        closed_after = None
        messages: dict[str, int] = {}
        deadline = started + args.hold
        while time.monotonic() < deadline:
            try:
                msg = await v.message(timeout=0.05)
                key = msg.type if msg.type != "error" else f"error:{msg.code}"
                messages[key] = messages.get(key, 0) + 1
            except TimeoutError:
                pass
            if closed_after is None and _closed(v):
                closed_after = time.monotonic() - started
                if args.big:
                    break
        return {"sent_s": sent_s, "closed_after_s": closed_after, "messages": messages,
                **_state(v)}
    finally:
        v.location = None  # no DELETE: a hostile peer just goes
        await v.pc.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("url")
    parser.add_argument("room")
    parser.add_argument("token")
    parser.add_argument("--pings", type=int, default=0)
    parser.add_argument("--big", type=int, default=0)
    parser.add_argument("--raw", type=int, default=0, metavar="PER_PACKET",
                        help="--pings as raw SCTP chunks, this many a packet, at full speed")
    parser.add_argument("--hold", type=float, default=5.0)
    result = asyncio.run(run(parser.parse_args(argv)))
    print("done " + json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
