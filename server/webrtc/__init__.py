"""WebRTC peers (issue 16): WHEP viewers and WHIP performers as room participants.

A peer is a :class:`~server.rooms.participant.RoomParticipant` whose frames go to an aiortc
video track instead of a WebSocket and whose messages travel over a data channel labelled
``telesplat``; everything else (latest-wins render loop, pacing, seats, presence) is the room
participant's. ``registry`` holds the peers and their limits; ``negotiate`` the SDP side;
``track`` the outgoing video; ``channel`` the data channel; ``encoders`` the bit-rate clamp;
``ingest`` a WHIP webcam into server-side tracking; ``sctp`` the data channel's byte and
message budgets before aiortc reassembles anything. aiortc is imported only where a peer is
made, so importing the server stays cheap.
"""
