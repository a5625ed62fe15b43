"""Record the voices a room's viewer hears (``voice`` messages, Opus): one ``voice-seat{N}.wav``
per seat, or one ``voice-mix.wav`` for the room's mix (messages without a seat), 48 kHz stereo
s16 decoded with PyAV's Opus decoder, and one JSON line per packet in ``voice.jsonl`` (seat,
seq, capture time, arrival, its sample offset in the WAV), so each packet can be matched with
the frames (frames.jsonl: ``t_capture``).

A gap in a seat's seqs (packets lost, or dropped as the viewer fell behind) is written as
silence as long as the packet before it, so the WAV keeps the seat's timeline.
"""

from __future__ import annotations

import json
import wave
from pathlib import Path
from typing import Any, TextIO

from protocol import Voice
from protocol.opus import OpusPacketError, packet_duration_ms

RATE = 48_000
CHANNELS = 2
SAMPLE_BYTES = 2


class VoiceRecorder:
    def __init__(self, out: Path, start: float) -> None:
        self.out, self.start = out, start
        self._log: TextIO = (out / "voice.jsonl").open("w")
        self._seats: dict[int | str, dict[str, Any]] = {}  # seat index, or "mix"
        self.packets = 0
        self.undecodable = 0

    @staticmethod
    def _file(index: int | str) -> str:
        return f"voice-{index}.wav" if index == "mix" else f"voice-seat{index}.wav"

    def _seat(self, index: int | str) -> dict[str, Any]:
        if index not in self._seats:
            import av

            decoder = av.CodecContext.create("opus", "r")
            decoder.sample_rate = RATE
            wav = wave.open(str(self.out / self._file(index)), "wb")
            wav.setnchannels(CHANNELS)
            wav.setsampwidth(SAMPLE_BYTES)
            wav.setframerate(RATE)
            # FFmpeg's Opus decoder gives float planar: the WAV wants packed s16.
            resampler = av.AudioResampler(format="s16", layout="stereo", rate=RATE)
            self._seats[index] = {"decoder": decoder, "resampler": resampler, "wav": wav,
                                  "samples": 0,
                                  "seq": None, "last_ms": 20.0}
        return self._seats[index]

    def __call__(self, message: Voice, received: float) -> None:
        import av

        seat = self._seat("mix" if message.seat is None else message.seat)
        if seat["seq"] is not None and message.seq > seat["seq"] + 1:
            missing = message.seq - seat["seq"] - 1
            silence = int(missing * seat["last_ms"] * RATE / 1000)
            seat["wav"].writeframes(bytes(silence * CHANNELS * SAMPLE_BYTES))
            seat["samples"] += silence
        seat["seq"] = message.seq
        offset = seat["samples"]
        try:
            seat["last_ms"] = packet_duration_ms(message.data)
            for decoded in seat["decoder"].decode(av.Packet(message.data)):
                for frame in seat["resampler"].resample(decoded):
                    pcm = frame.to_ndarray()  # [1, samples * channels] packed s16
                    seat["wav"].writeframes(pcm.tobytes())
                    seat["samples"] += frame.samples
        except (OpusPacketError, av.FFmpegError):
            self.undecodable += 1
        self.packets += 1
        self._log.write(json.dumps({
            "seat": message.seat, "seq": message.seq, "t_capture": message.t_capture,
            "received_s": round(received - self.start, 4), "bytes": len(message.data),
            "sample": offset}) + "\n")

    def close(self) -> dict[str, Any]:
        self._log.close()
        for seat in self._seats.values():
            seat["wav"].close()
        return {"voice_packets": self.packets, "voice_undecodable": self.undecodable,
                "voice_files": sorted(self._file(i) for i in self._seats)}
