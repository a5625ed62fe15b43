"""Server CPU of a room's mixed voice (issue 30): the mix against plain forwarding, side by side.

In one process, ``--rooms`` rooms of ``--seats`` seats each get 20 ms Opus packets of a tone
per seat (libopus, 32 kbit/s, published through each seat's real ``SeatVoice``) for
``--seconds``; each room has one listener that drains either every seat's own voice
(``forward``: what a room costs without a mix) or the room's one ``RoomMix``
(server/rooms/voice_mix.py: decode, sum, encode on the mix's thread). The process CPU time
(all threads) over the run, per room, is the cost; ``mix - forward`` is what the mix adds.
Also the ``MixCodec.step`` alone (decode the seats' packets, mix, encode one frame), per
20 ms frame.

    nice -n 10 .venv/bin/python bench/voice_mix.py [--rooms 4] [--seats 2] [--seconds 5]
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time
from pathlib import Path
from types import SimpleNamespace

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from server.config import Settings  # noqa: E402
from server.rooms.voice import seat_voice  # noqa: E402
from server.rooms.voice_mix import FRAME, FRAME_S, MixCodec, room_mix, tone_packets  # noqa: E402
from server.stream.drive import DriveState  # noqa: E402


def room(seats: int) -> SimpleNamespace:
    return SimpleNamespace(seats=[SimpleNamespace(voice=None, drive=DriveState(), performer=None,
                                                  on_speaking=None) for _ in range(seats)],
                           voice_mix=None)


async def drain(listener) -> int:
    got = 0
    while await listener.next() is not None:
        got += 1
    return got


async def run(mode: str, rooms: int, seats: int, seconds: float,
              packets: list[list[bytes]]) -> dict[str, float]:
    settings = Settings()
    lives = [room(seats) for _ in range(rooms)]
    listeners = []
    for live in lives:
        if mode == "mix":
            listeners.append(room_mix(live, settings).subscribe())
        else:
            listeners += [seat_voice(s, settings).subscribe() for s in live.seats]
    drains = [asyncio.create_task(drain(lis)) for lis in listeners]
    frames = int(seconds / FRAME_S)
    cpu, wall = time.process_time(), time.monotonic()
    for i in range(frames):
        for live in lives:
            for k, seat in enumerate(live.seats):
                seat_voice(seat, settings).publish(seat, packets[k][i % len(packets[k])],
                                                   i * FRAME)
        await asyncio.sleep(max(0.0, wall + (i + 1) * FRAME_S - time.monotonic()))
    cpu, wall = time.process_time() - cpu, time.monotonic() - wall
    mixed = sum(live.voice_mix.counts["mixed"] for live in lives if live.voice_mix)
    for lis in listeners:
        lis.close()
    await asyncio.gather(*drains, return_exceptions=True)
    return {"cpu_per_room": cpu / wall / rooms, "mixed_per_s": mixed / wall / rooms}


def codec_step_ms(seats: int, packets: list[list[bytes]], frames: int = 500) -> float:
    codec = MixCodec(48_000, 64)
    start = time.process_time()
    for i in range(frames):
        codec.step([(k, packets[k][i % len(packets[k])], None) for k in range(seats)])
    return (time.process_time() - start) / frames * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rooms", type=int, default=4)
    parser.add_argument("--seats", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=5.0)
    args = parser.parse_args()
    packets = [tone_packets(300.0 + 200 * k, 250) for k in range(args.seats)]
    step = codec_step_ms(args.seats, packets)
    print(f"MixCodec.step, {args.seats} seats: {step:.3f} ms CPU per 20 ms frame "
          f"({step / 20 * 100:.2f}% of a core)")
    print(f"| {args.rooms} rooms x {args.seats} seats, {args.seconds:g} s | CPU per room "
          "(cores) | mixed frames/s per room |")
    print("|---|---:|---:|")
    results = {}
    for mode in ("forward", "mix"):
        results[mode] = asyncio.run(run(mode, args.rooms, args.seats, args.seconds, packets))
        r = results[mode]
        print(f"| {mode} | {r['cpu_per_room']:.4f} | {r['mixed_per_s']:.1f} |")
    added = results["mix"]["cpu_per_room"] - results["forward"]["cpu_per_room"]
    print(f"the mix adds {added:.4f} cores per room ({added * 100:.2f}% of a core)")


if __name__ == "__main__":
    main()
