"""Record what a room's viewer gets: each frame's encoded image as a file, and one JSON line per
frame in ``frames.jsonl`` (seq, frame counter, size, codec, stage timings, arrival time, the
capture time of the drive it shows); with ``voice`` the seats' voices too (client/voice.py)."""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

from protocol import Frame

from .stream import Backoff


def parse_view(text: str) -> dict[str, float]:
    """``--view yaw,pitch,distance`` (degrees, degrees, metres) or a camera preset's name
    (protocol.cameras: front, left, right) as orbit fields."""
    from protocol.cameras import CAMERA_NAMES, CAMERA_PRESETS

    if text in CAMERA_PRESETS:
        return dict(CAMERA_PRESETS[text])
    if "," not in text:
        raise ValueError(f"--view {text!r} is neither yaw,pitch,distance nor a camera preset "
                         f"({', '.join(CAMERA_NAMES)})")
    parts = [p.strip() for p in text.split(",")]
    if len(parts) != 3:
        raise ValueError(f"--view wants yaw,pitch,distance, got {text!r}")
    try:
        yaw, pitch, distance = (float(p) for p in parts)
    except ValueError as exc:
        raise ValueError(f"--view wants three numbers, got {text!r}") from exc
    return {"yaw_deg": yaw, "pitch_deg": pitch, "distance": distance}


async def arrivals(next_frame: Callable[[float], Awaitable[Any]], seconds: float | None,
                   timeout: float) -> AsyncIterator[Any]:
    """What ``next_frame(wait_s)`` returns, as it arrives, until ``seconds`` have passed (None:
    until a wait past ``timeout``, which raises ``TimeoutError``); the caller stops on its own
    count of frames kept."""
    deadline = None if seconds is None else time.monotonic() + seconds
    while True:  # bounded by the deadline, or by the timeout of each wait
        left = timeout if deadline is None else deadline - time.monotonic()
        if left <= 0:
            return
        try:
            frame = await next_frame(min(left, timeout))
        except TimeoutError:
            if deadline is None:
                raise
            return
        yield frame


def frame_record(frame: Frame, index: int, file: str, received_s: float) -> dict[str, Any]:
    """One line of frames.jsonl."""
    return {"index": index, "file": file, "seq": frame.seq, "frame": frame.frame,
            "codec": frame.codec, "width": frame.width, "height": frame.height,
            "bytes": len(frame.data), "received_s": round(received_s, 4),
            "t_capture": frame.t_capture, "timings": frame.timings.model_dump()}


async def watch_room(server: str, token: str | None, room: str, out: Path, *,
                     seconds: float | None = 10.0, max_frames: int | None = None,
                     view: dict[str, float] | None = None, size: int = 512,
                     timeout: float = 30.0, max_stale: int = 8,
                     reconnect: Backoff | None = None,
                     voice: bool | str = False) -> dict[str, Any]:
    """Join ``room`` as a viewer and save its frames in ``out`` until ``seconds`` have passed or
    ``max_frames`` arrived (whichever first; at least one of them must be given).

    Up to ``max_stale`` frames rendered before our request landed (not ``size`` square) are
    skipped; after the first frame of the asked size, or that many, every frame is kept but
    one that repeats the last saved (same drive seq, same bytes): one file per picture.
    ``reconnect``: rejoin the room by itself after a server restart (client/stream.py); the
    recording goes on, and the result lists each reconnection's downtime. ``voice``: also
    record the seats' voices (voice-seat{N}.wav and voice.jsonl); "mix": the room's one mix
    instead (voice-mix.wav)."""
    from .images import save_frame
    from .stream import StreamClient

    if seconds is None and max_frames is None:
        raise ValueError("give seconds or max_frames: a recording must end")
    out.mkdir(parents=True, exist_ok=True)
    saved = stale = repeats = 0
    last: tuple[int, int, bytes] | None = None
    async with await StreamClient.connect(server, token=token, room=room, role="watch",
                                          timeout=timeout, reconnect=reconnect,
                                          client_name="telesplat-client watch",
                                          voice=voice) as client:
        start = time.monotonic()
        recorder = None
        if voice:
            from .voice import VoiceRecorder

            recorder = client.on_voice = VoiceRecorder(out, start)
        await client.request(width=size, height=size, codec="jpeg")
        if view is not None:
            await client.view(view)
        frames = arrivals(client.next_frame, seconds, timeout)
        with (out / "frames.jsonl").open("w") as log:
            async with contextlib.aclosing(frames):
                async for frame in frames:
                    if max_frames is not None and saved >= max_frames:
                        break
                    if frame.codec == "h264":
                        continue
                    asked = (frame.width, frame.height) == (size, size)
                    if saved == 0 and stale < max_stale and not asked:
                        stale += 1
                        continue
                    if last is not None and (frame.seq, frame.width, frame.data) == last:
                        repeats += 1  # the same picture again (the join's frame, re-sent
                        continue      # when our request lands): one file per picture
                    last = (frame.seq, frame.width, frame.data)
                    path = save_frame(frame, out / f"{saved:05d}")
                    log.write(json.dumps(frame_record(frame, saved, path.name,
                                                      time.monotonic() - start)) + "\n")
                    saved += 1
                    if max_frames is not None and saved >= max_frames:
                        break
        presence = client.presence
        heard = recorder.close() if recorder is not None else {}
        reconnections = [{"reason": r.reason, "downtime_s": round(r.downtime_s, 3),
                          "attempts": r.attempts} for r in client.reconnections]
    return {"frames": saved, "stale_skipped": stale, "repeats_skipped": repeats, "room": room,
            "presence": presence.model_dump() if presence is not None else None,
            "reconnections": reconnections, **heard}


async def watch_room_webrtc(server: str, token: str | None, room: str, out: Path, *,
                            seconds: float | None = 10.0, max_frames: int | None = None,
                            view: dict[str, float] | None = None, size: int = 512,
                            timeout: float = 30.0, codec: str | None = None,
                            stamp: bool = False) -> dict[str, Any]:
    """Watch ``room`` over WebRTC (WHEP) and save each decoded frame as a PNG (what a WebRTC
    viewer sees, after VP8 / H.264), with one line per frame in ``frames.jsonl`` (index, file,
    size, arrival time; with ``stamp`` the drive seq read from the frame's stamp)."""
    import cv2

    from protocol import Orbit, View
    from protocol.stamp import read_stamp

    from .webrtc import WhepViewer

    if seconds is None and max_frames is None:
        raise ValueError("give seconds or max_frames: a recording must end")
    out.mkdir(parents=True, exist_ok=True)
    saved = 0
    viewer = WhepViewer(server, room, token, width=size, height=size, role="watch",
                        codec=codec, stamp=stamp, timeout_s=timeout)
    async with viewer:
        if view is not None:
            await viewer.wait_open()
            viewer.send(View(orbit=Orbit(**view)))
        start = time.monotonic()
        frames = arrivals(viewer.next_frame, seconds, timeout)
        with (out / "frames.jsonl").open("w") as log:
            async with contextlib.aclosing(frames):
                async for rgb, received in frames:
                    if max_frames is not None and saved >= max_frames:
                        break
                    name = f"{saved:05d}.png"
                    cv2.imwrite(str(out / name), rgb[:, :, ::-1])  # cv2 writes BGR
                    log.write(json.dumps({
                        "index": saved, "file": name, "codec": viewer.codec,
                        "width": int(rgb.shape[1]), "height": int(rgb.shape[0]),
                        "seq": read_stamp(rgb) if stamp else None,
                        "received_s": round(received - start, 4)}) + "\n")
                    saved += 1
                    if max_frames is not None and saved >= max_frames:
                        break
        codec_used = viewer.codec
    return {"frames": saved, "room": room, "transport": "webrtc", "codec": codec_used}
