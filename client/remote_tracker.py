"""The remote tracker: track a webcam or a video here, send the fitted parameters as drives.

Tracking runs on this machine (``avatar_core.track``, imported only when used, so the client
library itself never needs torch or onnxruntime); only parameters cross the network, not
images. Frames that come back are counted, or saved when ``out`` is given.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

from .stream import Backoff


async def drive_from_camera(server: str, token: str | None, avatar: str | None,
                            source: str | int, *, room: str | None = None,
                            seat: int | None = None, max_frames: int | None = None,
                            fov_x_deg: float = 60.0, out: Path | None = None,
                            timeout: float = 30.0, progress: bool = True,
                            body_models: Path | None = None,
                            reconnect: Backoff | None = None) -> dict[str, float]:
    """Track ``source`` (a webcam index or a video path) and drive ``avatar`` with the fit, or
    perform ``seat`` of ``room`` (then viewers of the room see it). Returns counts and the
    mean tracking time. ``body_models``: the body-model folder to fit (the resolver's order:
    this, ``$TELESPLAT_BODY_MODELS``, else the synthetic family); use the server's models, so
    that the fitted parameters mean the same there. ``reconnect``: rejoin the same seat by
    itself after a server restart (client/stream.py); drives sent meanwhile wait for it."""
    from tqdm import tqdm

    from avatar_core.track.fit.video import default_sequence_fit, frames_from, tracked_frames
    from avatar_core.track.tracker import LIVE_PALM_INTERVAL, Tracker

    from .images import save_frame
    from .stream import StreamClient

    tracker = Tracker(palm_interval=LIVE_PALM_INTERVAL, iris=True)
    sequence_fit = default_sequence_fit(fov_x_deg, body_models=body_models)
    # Landmarks of the next frame are found while this one is fitted (two threads).
    tracked = tracked_frames(frames_from(source, max_frames), sequence_fit, tracker)

    sent, received, track_ms = 0, 0, 0.0
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    try:
        role = "perform" if room is not None else None
        async with await StreamClient.connect(server, avatar, token, room=room, role=role,
                                              seat=seat, timeout=timeout,
                                              reconnect=reconnect,
                                              client_name="telesplat-client drive") as client:
            with tqdm(total=max_frames, unit="frame", disable=not progress,
                      desc="driving") as bar:
                while True:
                    item = await asyncio.to_thread(next, tracked, None)  # off the event loop
                    if item is None:
                        break
                    seq = await client.drive(item.params, reset=sent == 0)
                    sent, track_ms = sent + 1, track_ms + item.track_ms + item.fit_ms
                    if out is not None:
                        frame = await client.wait_frame(seq, timeout=timeout)
                        save_frame(frame, out / f"{received:05d}")
                        received += 1
                    bar.update(1)
    finally:  # the fit thread and the ONNX sessions, also when the server goes away
        tracked.close()
        tracker.close()
    return {"sent": sent, "saved": received, "track_ms": track_ms / max(sent, 1)}
