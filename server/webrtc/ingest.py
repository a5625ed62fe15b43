"""WHIP ingest: the performer's webcam track into the server-side tracking of its seat.

Every decoded frame is read (aiortc queues them unboundedly otherwise) and offered to the
participant's tracker, which keeps only the newest waiting (latest wins, never a queue); the
conversion to BGR happens on the tracking thread. A frame's capture time comes from the
publisher's sender reports (publisher_clock.py): the drive tracked from it carries it.
"""

from __future__ import annotations

import logging
import time
from typing import Any

from aiortc.mediastreams import MediaStreamError

from protocol.messages import MAX_SEQ

from ..stream.tracking import DecodedImage
from .publisher_clock import TrackReports

log = logging.getLogger(__name__)


def _bgr(frame: Any):
    return lambda: frame.to_ndarray(format="bgr24")  # [H, W, 3] uint8, on the tracking thread


async def ingest(track: Any, participant: Any, reports: TrackReports | None = None) -> None:
    """Until the track ends: each frame to ``participant.offer_image``, with its capture time
    from its track's sender ``reports`` once one came. When tracking is not available in
    this server the participant is told once and frames are only drained."""
    seq, told = 0, False
    while True:
        try:
            frame = await track.recv()
        except MediaStreamError:
            return
        unavailable = participant.tracking.unavailable
        if unavailable:
            if not told:
                participant.send_error("unsupported", unavailable)
                told = True
            continue
        seq = seq + 1 if seq < MAX_SEQ else 0
        t_capture = None if reports is None else reports.frame_capture_time(frame.pts)
        participant.offer_image(DecodedImage(seq, frame.width, frame.height, _bgr(frame),
                                             t_capture), time.monotonic())
