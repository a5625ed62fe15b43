"""WebRTC peers (issue 16): WHEP viewers and WHIP performers as room participants.

A peer is the stream's own :class:`~server.stream.session.Session` composed with a
``transport`` (:class:`~.transport.WebRTCTransport`) whose frames go to an aiortc video track
and whose messages travel over a data channel labelled ``telesplat``; everything else
(latest-wins render loop, pacing, seats, presence) is the session's. ``registry`` holds the
peers and their limits; ``negotiate`` the SDP side; ``track`` the outgoing video; ``channel``
the data channel; ``encoders`` the bit-rate clamp; ``ingest`` a WHIP webcam into server-side
tracking; ``sctp`` the data channel's byte and message budgets before aiortc reassembles
anything. aiortc is imported only where a peer is
made, so importing the server stays cheap.
"""
