"""Voice over the WebSocket (issue 30) on a real uvicorn: a performer's ``voice`` messages reach
the viewers who asked for voices, byte for byte with their capture times; garbage is dropped
and counted; a viewer may not speak; frames carry the capture time of the drive they show."""

from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest

from protocol import Drive, Voice, encode
from tests.server_fixtures import WS_TIMEOUT_S, is_type, recv_until, run_server
from tests.test_server_rooms import create_room, invite, join, live
from tests.test_voice_units import libopus_packets

PACKETS = 30


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    with run_server(tmp_path_factory.mktemp("voice_ws"), default_width=64,
                    default_height=64) as running:
        yield running


def test_voices_reach_viewers_who_ask_with_capture_times_and_garbage_never(srv):
    room = create_room(srv)
    perform = invite(srv, room["id"], "perform")
    watch = invite(srv, room["id"], "watch")
    opus = libopus_packets(20, 32000, PACKETS)

    async def run():
        async with join(srv, room["id"], perform["token"], client="mic") as performer, \
                join(srv, room["id"], watch["token"], voice=True) as listener, \
                join(srv, room["id"], watch["token"]) as deaf:
            await asyncio.sleep(0.3)  # the relay subscribed
            await performer.send(encode(Drive(seq=1, smplx={"jaw_pose": np.array([0.3, 0, 0])},
                                              t_capture=50.0)))
            frame = await recv_until(listener, lambda m: m.type == "frame" and m.seq == 1)
            for i, packet in enumerate(opus):
                await performer.send(encode(Voice(seq=i, data=packet, t_capture=50.0 + i / 50)))
                if i == PACKETS // 2:
                    await performer.send(encode(Voice(seq=999, data=b"\x03\x00")))  # R5
            heard = [await recv_until(listener, is_type("voice")) for _ in opus]
            # The viewer that did not ask gets none; a frame shows it is served meanwhile.
            seen: list = []
            await recv_until(deaf, is_type("frame"), seen=seen)
            await listener.send(encode(Voice(seq=0, data=opus[0])))
            error = await recv_until(listener, is_type("error"))
            return frame, heard, seen, error, dict(live(srv, room["id"]).seats[0].voice.counts)

    frame, heard, seen, error, counts = asyncio.run(run())
    assert frame.t_capture == 50.0  # the frame carries its drive's capture time
    assert [m.data for m in heard] == opus
    assert [m.t_capture for m in heard] == pytest.approx([50.0 + i / 50 for i in range(PACKETS)])
    assert {m.seat for m in heard} == {0} and [m.seq for m in heard] == list(range(PACKETS))
    assert not any(m.type == "voice" for m in seen)
    assert error.code == "forbidden"
    assert counts == {"forwarded": PACKETS, "garbage": 1}


def test_a_voice_message_larger_than_an_opus_packet_is_refused_by_the_protocol(srv):
    room = create_room(srv)
    perform = invite(srv, room["id"], "perform")

    async def run():
        async with join(srv, room["id"], perform["token"]) as performer:
            await performer.send(encode({"type": "voice", "seq": 0, "data": b"\xf8" * 2000}))
            return await recv_until(performer, is_type("error"), timeout=WS_TIMEOUT_S)

    error = asyncio.run(run())
    assert error.code == "invalid" and "data" in error.message


def test_cli_watch_voice_records_a_wav_and_capture_times(srv, tmp_path):
    from client.cli import main as cli_main
    from client.stream import StreamClient

    room = create_room(srv)
    watch = invite(srv, room["id"], "watch")
    opus = libopus_packets(20, 32000, 50)  # one second
    out = tmp_path / "heard"
    argv = ["watch", "--room", room["id"], "--out", str(out), "--seconds", "120", "--frames",
            "3", "--size", "64", "--voice", "--server", srv.url, "--token", watch["token"]]

    async def run():
        async with await StreamClient.connect(srv.url, token=srv.token, room=room["id"],
                                              role="perform", seat=0) as performer:
            recorder = asyncio.create_task(asyncio.to_thread(cli_main, argv))
            await performer.wait_presence(lambda p: p.viewers >= 1, timeout=60)
            await asyncio.sleep(0.5)  # its voice relay subscribed
            for i, packet in enumerate(opus):
                await performer.voice(packet, t_capture=10.0 + i / 50)
                if i == 20:
                    await performer.voice(b"\xfb\x00")  # garbage: never heard
            for i in range(400):  # bounded; ends once the recorder has its frames
                if recorder.done():
                    break
                seq = await performer.drive(jaw_pose=[0.1 * (i % 5), 0.0, 0.0],
                                            t_capture=11.0 + i / 10)
                await performer.wait_frame(seq, timeout=30)
            return await recorder

    assert asyncio.run(run()) == 0
    import wave

    lines = [json.loads(x) for x in (out / "voice.jsonl").read_text().splitlines()]
    assert [x["seq"] for x in lines] == list(range(len(opus)))
    assert [x["t_capture"] for x in lines] == pytest.approx([10.0 + i / 50 for i in range(50)])
    with wave.open(str(out / "voice-seat0.wav")) as wav:
        assert wav.getframerate() == 48000 and wav.getnchannels() == 2
        samples = np.frombuffer(wav.readframes(wav.getnframes()), np.int16)
    assert len(samples) // 2 == 50 * 960  # every packet decoded: one second
    assert np.abs(samples).max() > 1000   # the noise, not silence
    frames = [json.loads(x) for x in (out / "frames.jsonl").read_text().splitlines()]
    assert any(f["t_capture"] is not None and f["t_capture"] >= 11.0 for f in frames)


def test_presence_says_who_speaks_from_the_packets_level_and_not_per_packet(srv):
    room = create_room(srv)
    perform = invite(srv, room["id"], "perform")
    watch = invite(srv, room["id"], "watch")
    opus = libopus_packets(20, 32000, 25)

    async def speak(performer, level_dbov: float) -> None:
        for i, packet in enumerate(opus):  # half a second, paced as a microphone
            await performer.send(encode(Voice(seq=i, data=packet, level_dbov=level_dbov)))
            await asyncio.sleep(0.02)

    async def run():
        async with join(srv, room["id"], perform["token"]) as performer, \
                join(srv, room["id"], watch["token"]) as viewer:
            await recv_until(viewer, is_type("presence"))  # its own join
            await speak(performer, -90.0)  # quiet packets: forwarded, nobody speaks
            await speak(performer, -20.0)
            await speak(performer, -90.0)
            presences = []
            while not presences or presences[-1].seats[0].speaking:  # bounded by recv_until
                presences.append(await recv_until(viewer, is_type("presence")))
            counts = dict(live(srv, room["id"]).seats[0].voice.counts)
            return presences, counts

    presences, counts = asyncio.run(run())
    # one update each way, not one per packet; none while the packets were quiet
    assert [p.seats[0].speaking for p in presences] == [True, False]
    assert counts == {"forwarded": 75}
