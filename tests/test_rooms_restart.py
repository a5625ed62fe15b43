"""Rooms survive a restart, against a real server subprocess (``python -m server``).

A room with a performer (StreamClient performing seat 0 with a perform invitation, driving all
along) and three viewers (StreamClients with a watch invitation, as ``watch --room``). The
server is stopped, with SIGTERM (graceful: every participant gets error ``restarting`` and
close 1012) or SIGKILL (nothing told: connections just drop), and started again on the same
port and data dir. Every participant reconnects by itself (client/stream.py's backoff) into
the same room (same id), the performer on the same seat, and receives frames again within 10 s
of the new server being up; the performer's drives reach the viewers again; a new join with
the old invitation token works. Reconnect times are measured and printed (pytest -s shows
them): from the lost connection and from the new server's start to the first new frame.
"""

from __future__ import annotations

import asyncio
import contextlib
import signal
import sqlite3
import statistics
import time

import httpx
import pytest

from client.cli import build_parser
from client.stream import Backoff, StreamClient, StreamError
from server.rooms.store import store_path
from tests.server_process import ServerProcess

SIZE = 64               # frames: small, the two cores are shared
DRIVE_HZ = 5.0
BACK_WITHIN_S = 10.0    # from the new server's start to each participant's first new frame
WAIT_S = 60.0           # any single wait here (bounded)
# Generous tries: the new server takes seconds to start (imports, warm-up) on a busy machine.
BACKOFF = Backoff(attempts=30, initial_s=0.25, max_s=4.0)


class Participant:
    """A StreamClient and the monotonic arrival time of every frame it gets."""

    def __init__(self, name: str, client: StreamClient) -> None:
        self.name, self.client = name, client
        self.arrivals: list[tuple[float, int]] = []  # (time, seq)
        self.task = asyncio.create_task(self._consume())

    async def _consume(self) -> None:
        with contextlib.suppress(StreamError):  # a refusal ends it: the test reads `closed`
            async for frame in self.client.frames():  # ends when the client gives up/closes
                self.arrivals.append((time.monotonic(), frame.seq))

    def first_frame_after(self, t: float) -> float | None:
        return next((at for at, _ in self.arrivals if at > t), None)

    def newest_seq_after(self, t: float) -> int:
        return max((seq for at, seq in self.arrivals if at > t), default=-2)


async def _until(predicate, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():  # bounded by the deadline
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout} s waiting for {what}")
        await asyncio.sleep(0.05)


async def _drive(performer: StreamClient, sent: list[int]) -> None:
    """Open and close the jaw at DRIVE_HZ until cancelled; each drive's seq in ``sent``."""
    i = 0
    while True:  # cancelled by the test; each pass sleeps
        sent.append(await performer.drive(jaw_pose=[0.3 * (i % 2), 0.0, 0.0]))
        i += 1
        await asyncio.sleep(1 / DRIVE_HZ)


def _room_and_invitations(srv: ServerProcess, owner: str | None = None
                          ) -> tuple[str, str, str]:
    with httpx.Client(base_url=srv.url, headers=srv.headers(owner), timeout=30) as http:
        room = http.post("/v1/rooms", json={"name": "restart"}).raise_for_status().json()
        tokens = [http.post(f"/v1/rooms/{room['id']}/invitations",
                            json={"scope": scope}).raise_for_status().json()["token"]
                  for scope in ("perform", "watch")]
    return room["id"], tokens[0], tokens[1]


async def _join(srv: ServerProcess, room: str, token: str, role: str, name: str,
                reconnect: Backoff | None = BACKOFF) -> StreamClient:
    client = await StreamClient.connect(srv.url, token=token, room=room, role=role,
                                        client_name=name, timeout=30, reconnect=reconnect)
    await client.request(width=SIZE, height=SIZE, codec="jpeg", max_fps=10)
    return client


def _summary(values: list[float]) -> str:
    return f"p50 {statistics.median(values):.2f} s, max {max(values):.2f} s"


def _forget_room(srv: ServerProcess, room: str) -> None:
    """Delete a room's rows while the server is down (as if deleted meanwhile)."""
    db = sqlite3.connect(store_path(srv.data_dir), isolation_level=None)
    try:
        db.execute("PRAGMA foreign_keys=ON")
        assert db.execute("DELETE FROM rooms WHERE id = ?", (room,)).rowcount == 1
    finally:
        db.close()


async def _restart_scenario(srv: ServerProcess, sig: int,
                            alice: str) -> dict[str, list[float]]:
    room, perform_token, watch_token = _room_and_invitations(srv)
    # Alice's room, deleted while the server is down: her viewer (her own token, which
    # outlives restarts) and an invited one must stop trying, saying why.
    doomed_room, _, doomed_token = _room_and_invitations(srv, alice)
    doomed = [Participant("doomed-owner", await _join(srv, doomed_room, alice, "watch",
                                                      "doomed-owner")),
              Participant("doomed-invited", await _join(srv, doomed_room, doomed_token, "watch",
                                                        "doomed-invited"))]
    performer = Participant("performer", await _join(srv, room, perform_token, "perform",
                                                     "performer"))
    viewers = [Participant(f"viewer-{i}", await _join(srv, room, watch_token, "watch",
                                                      f"viewer-{i}")) for i in range(3)]
    everyone = [performer, *viewers]
    sent: list[int] = []
    driving = asyncio.create_task(_drive(performer.client, sent))
    try:
        await _until(lambda: all(p.arrivals for p in everyone) and len(sent) > 2, WAIT_S,
                     "everyone's first frames")
        assert performer.client.room.seat == 0 and performer.client.room.role == "perform"

        stopped_at = time.monotonic()
        status = await asyncio.to_thread(srv.stop, sig)
        await _until(lambda: all(p.client.reconnecting for p in [*everyone, *doomed]),
                     WAIT_S, "every client to notice")
        _forget_room(srv, doomed_room)
        if sig == signal.SIGTERM:  # a graceful stop (uvicorn re-raises the signal at its end)
            assert status in (0, -signal.SIGTERM), "".join(srv.output)
            assert "Traceback" not in "".join(srv.output), "".join(srv.output)
            for p in everyone:  # told before the close, each of them
                assert [e.code for e in p.client.errors].count("restarting") == 1, p.name
        else:
            assert status == -signal.SIGKILL
            assert not any(e.code == "restarting" for p in everyone for e in p.client.errors)
        await asyncio.to_thread(srv.start)
        up_at = srv.started_at
        await _until(lambda: all(p.client.reconnections and p.first_frame_after(
            p.client.reconnections[-1].back_at) for p in everyone), WAIT_S,
            "every participant's first frame after the restart")

        from_up, downtime, rejoin = [], [], []
        for p in everyone:
            again = p.client.reconnections[-1]
            assert len(p.client.reconnections) == 1, p.name
            assert again.reason == ("restarting" if sig == signal.SIGTERM else "closed 1006")
            assert p.client.room.id == room, p.name  # the same room
            first = p.first_frame_after(again.back_at)
            from_up.append(first - up_at)
            downtime.append(first - again.lost_at)
            rejoin.append(again.back_at - up_at)
        assert performer.client.room.role == "perform" and performer.client.room.seat == 0
        assert all(v.client.room.role == "watch" for v in viewers)
        # A room gone meanwhile stops the retries at once, saying so.
        await _until(lambda: all(d.client.closed for d in doomed), WAIT_S, "the doomed")
        owner, invited = (d.client for d in doomed)
        assert owner.closed.code == "not_found" and not owner.reconnections
        assert f"room {doomed_room} is gone" in str(owner.closed)
        assert invited.closed.code == "unauthorized" and not invited.reconnections
        assert "room that was deleted" in str(invited.closed)
        assert all("not reconnecting" in str(c.closed) for c in (owner, invited))
        for d in doomed:
            await asyncio.wait_for(d.task, WAIT_S)  # its frames() ended
        assert max(from_up) <= BACK_WITHIN_S, from_up

        # The performer's drives reach the viewers again (the seat is performed anew).
        mark, target = time.monotonic(), sent[-1]
        await _until(lambda: all(v.newest_seq_after(mark) >= target for v in viewers), WAIT_S,
                     "the performer's newest drives in the viewers' frames")
        assert performer.client.closed is None and all(v.client.closed is None
                                                       for v in viewers)

        # The old invitation still opens the room for someone new.
        late = await _join(srv, room, watch_token, "watch", "late", reconnect=None)
        try:
            assert late.room.id == room and late.room.role == "watch"
            await late.next_frame(WAIT_S)
        finally:
            await late.close()
        with httpx.Client(base_url=srv.url, timeout=30) as http:
            seen = http.get(f"/v1/rooms/{room}", headers={
                "Authorization": f"Bearer {perform_token}"}).raise_for_status().json()
        assert seen["seats"][0]["performer"] == "performer" and seen["viewers"] >= 3
        name = signal.Signals(sig).name
        print(f"\n{name}: stopped at 0, server up again after {up_at - stopped_at:.2f} s; "
              f"first frame after the new server's start: {_summary(from_up)}; "
              f"rejoined (welcome) after its start: {_summary(rejoin)}; "
              f"lost connection to first new frame: {_summary(downtime)} "
              f"(4 participants)")
        return {"from_up": from_up, "downtime": downtime}
    finally:
        driving.cancel()
        for p in [*everyone, *doomed]:
            await p.client.close()
            p.task.cancel()


def test_backoff_doubles_to_its_cap_with_jitter_and_is_checked():
    policy = Backoff()
    assert [policy.delay(a, rand=lambda: 0.0) for a in range(7)] == [
        0.25, 0.5, 1.0, 2.0, 4.0, 4.0, 4.0]
    assert policy.delay(2, rand=lambda: 0.999999) == pytest.approx(0.5, abs=1e-5)
    assert all(2.0 <= policy.delay(9) <= 4.0 for _ in range(100))  # jitter: at most half off
    assert policy.delay(10_000, rand=lambda: 0.0) == 4.0  # no overflow
    assert sum(policy.delay(a, rand=lambda: 0.0) for a in range(policy.attempts)) < 30
    for bad in ({"attempts": -1}, {"initial_s": 0}, {"initial_s": 5, "max_s": 4},
                {"jitter": 1.0}):
        with pytest.raises(ValueError):
            Backoff(**bad)


def test_watch_and_drive_reconnect_by_default_and_can_be_told_not_to():
    from client.cli import _backoff

    watch = build_parser().parse_args(["watch", "--room", "r", "--out", "o"])
    assert _backoff(watch) == Backoff(attempts=10)
    drive = build_parser().parse_args(["drive", "--room", "r", "--video", "v.mp4",
                                       "--reconnect", "3"])
    assert _backoff(drive) == Backoff(attempts=3)
    off = build_parser().parse_args(["watch", "--room", "r", "--out", "o", "--reconnect", "0"])
    assert _backoff(off) is None


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL], ids=["sigterm", "sigkill"])
def test_room_participants_come_back_after_a_restart(tmp_path, sig):
    from server.auth import TokenStore

    # A user's token, besides the local admin token (kept in data_dir/local_token).
    alice = TokenStore(tmp_path / "tokens.json").issue("alice", ("stream",))
    with ServerProcess(tmp_path, default_width=SIZE, default_height=SIZE,
                       stats_interval_s=1.0) as srv:
        asyncio.run(asyncio.wait_for(_restart_scenario(srv, sig, alice), 5 * WAIT_S))
