"""Rooms, seats and invitations in SQLite (server/rooms/store.py) through the registry that
writes them through: a registry made again on the same file (a restart) has the same rooms,
seats, placements and invitations; revoked and expired invitations stay refused; deleting a
room or closing it for idleness deletes its rows; private rooms never get there. Then the
start-up room of two real servers run one after the other on one data dir."""

from __future__ import annotations

import sqlite3
import time
from pathlib import Path

import pytest

from server.auth import LOCAL_SUBJECT, SCOPES, Principal
from server.config import Settings
from server.rooms.registry import Placement, RoomError, RoomRegistry, SeatSpec
from server.rooms.store import SCHEMA_VERSION, RoomStore, StoreVersionError, store_path
from tests.server_fixtures import run_server

ALICE = Principal("alice", frozenset({"stream"}))


def settings(tmp_path: Path, **overrides) -> Settings:
    return Settings(data_dir=tmp_path, **overrides)


def registry(tmp_path: Path, **overrides) -> RoomRegistry:
    """A registry on the store under ``tmp_path``: what the server makes at each start."""
    s = settings(tmp_path, **overrides)
    return RoomRegistry(s, RoomStore(store_path(s.data_dir)))


def test_the_store_is_the_jobs_database_file(tmp_path):
    from server.jobs.service import DB_FILE, JOBS_DIR
    from server.jobs.store import NewJob, SQLiteJobStore

    path = store_path(tmp_path)
    assert path == tmp_path / JOBS_DIR / DB_FILE
    rooms = registry(tmp_path)
    rooms.create(ALICE, "r", [SeatSpec(0, "demo")])
    jobs = SQLiteJobStore(path)  # both stores on one file, each with its own tables
    jobs.create(NewJob("alice", "upload", "/x", {"iterations": 1}, 1))
    assert len(jobs.list()) == 1 and registry(tmp_path).store.counts()["rooms"] == 1
    jobs.close()


def test_rooms_seats_and_invitations_round_trip(tmp_path):
    first = registry(tmp_path)
    seats = [SeatSpec(0, "demo"),
             SeatSpec(1, "other", Placement((0.5, 0.0, -1.25), (0.0, 1.5707963, 0.0)))]
    room = first.create(ALICE, "two seats", seats)
    pinned = first.create(Principal(LOCAL_SUBJECT, frozenset(SCOPES)), "demo",
                          [SeatSpec(0, "demo")], pinned=True)
    watch, watch_token = first.invite(room, "watch", None, None)
    perform, perform_token = first.invite(room, "perform", 1, 600.0)

    again = registry(tmp_path)  # the restart
    assert len(again) == 2
    back = again.get(room.id)
    assert (back.name, back.owner, back.created, back.pinned, back.private) == (
        "two seats", "alice", room.created, False, False)
    assert back.seats == seats  # avatars and placements, exactly
    assert again.get(pinned.id).pinned
    assert back.live is None and back.empty_since is not None  # nobody in it yet
    assert {i.id: (i.scope, i.seat, i.expires_at, i.revoked) for i in back.invitations.values()} \
        == {watch.id: ("watch", None, watch.expires_at, False),
            perform.id: ("perform", 1, perform.expires_at, False)}
    # The tokens themselves were never stored, yet they still open the room.
    assert again.resolve(watch_token).id == watch.id
    assert again.resolve(perform_token).seat == 1
    raw = (tmp_path / "jobs" / "jobs.db").read_bytes()
    assert watch_token.encode() not in raw and perform_token.encode() not in raw
    assert [r.id for r in again.list(ALICE)] == [room.id]


def test_revoked_and_expired_invitations_stay_refused_after_a_reload(tmp_path):
    first = registry(tmp_path)
    room = first.create(ALICE, None, [SeatSpec(0, "demo")])
    revoked, revoked_token = first.invite(room, "watch", None, None)
    _, short_token = first.invite(room, "watch", None, 0.05)
    kept, kept_token = first.invite(room, "perform", None, None)
    first.revoke(room, revoked.id)
    time.sleep(0.1)  # the short one expires
    assert first.resolve(revoked_token) is None and first.resolve(short_token) is None

    again = registry(tmp_path)
    assert again.resolve(revoked_token) is None
    assert again.resolve(short_token) is None
    assert again.resolve(kept_token).id == kept.id
    assert again.get(room.id).invitations[revoked.id].revoked
    # A new invitation prunes the expired and revoked ones, in memory and in the store.
    again.invite(again.get(room.id), "watch", None, None)
    assert again.store.counts()["room_invitations"] == 2
    third = registry(tmp_path)
    assert third.resolve(revoked_token) is None and third.resolve(short_token) is None
    assert third.resolve(kept_token).id == kept.id


def test_deleting_a_room_deletes_its_rows(tmp_path):
    rooms = registry(tmp_path)
    room = rooms.create(ALICE, None, [SeatSpec(0, "demo"), SeatSpec(1, "demo")])
    other = rooms.create(ALICE, None, [SeatSpec(0, "demo")])
    rooms.invite(room, "watch", None, None)
    _, other_token = rooms.invite(other, "watch", None, None)
    assert rooms.store.counts() == {"rooms": 2, "room_seats": 3, "room_invitations": 2}
    assert rooms.remove(room.id) is room
    assert rooms.store.counts() == {"rooms": 1, "room_seats": 1, "room_invitations": 1}
    again = registry(tmp_path)
    with pytest.raises(RoomError):
        again.get(room.id)
    assert again.resolve(other_token).room_id == other.id


def test_idle_close_deletes_the_rows_and_the_idle_clock_restarts_at_load(tmp_path):
    rooms = registry(tmp_path, room_idle_timeout_s=60)
    idle = rooms.create(ALICE, None, [SeatSpec(0, "demo")])
    pinned = rooms.create(ALICE, "pinned", [SeatSpec(0, "demo")], pinned=True)
    idle.empty_since = time.monotonic() - 120  # empty for two timeouts
    assert rooms.idle_rooms(time.monotonic()) == [idle]
    assert rooms.store.counts()["rooms"] == 1

    rooms.create(ALICE, None, [SeatSpec(0, "demo")])
    start = time.monotonic()
    again = registry(tmp_path, room_idle_timeout_s=60)  # a restart: everyone's clock restarts
    assert all(r.empty_since >= start for r in again.list(ALICE))
    assert again.idle_rooms(time.monotonic()) == []
    assert again.idle_rooms(time.monotonic() + 61) != [] and len(again) == 1
    assert [r.id for r in registry(tmp_path).list(ALICE)] == [pinned.id]


def test_quota_counts_stored_rooms(tmp_path):
    rooms = registry(tmp_path, max_rooms_per_user=2)
    for _ in range(2):
        rooms.create(ALICE, None, [SeatSpec(0, "demo")])
    again = registry(tmp_path, max_rooms_per_user=2)
    with pytest.raises(RoomError) as refused:
        again.create(ALICE, None, [SeatSpec(0, "demo")])
    assert refused.value.status == 429


def test_private_rooms_are_never_stored(tmp_path):
    from server.rooms.registry import Room

    store = RoomStore(store_path(tmp_path))
    with pytest.raises(ValueError, match="private"):
        store.add_room(Room("p", "session p", "alice", [SeatSpec(0, "demo")], time.time(),
                            private=True))
    assert store.counts()["rooms"] == 0


def test_a_failed_write_changes_nothing(tmp_path):
    rooms = registry(tmp_path)
    room = rooms.create(ALICE, None, [SeatSpec(0, "demo")])
    inv, _ = rooms.invite(room, "watch", None, None)
    # Another connection holds the write lock: writes time out (a short busy timeout here).
    rooms.store.close()
    rooms.store.timeout_s = 0.05
    blocker = sqlite3.connect(store_path(tmp_path), isolation_level=None)
    blocker.execute("BEGIN IMMEDIATE")
    try:
        for attempt in (lambda: rooms.create(ALICE, None, [SeatSpec(0, "demo")]),
                        lambda: rooms.invite(room, "watch", None, None),
                        lambda: rooms.revoke(room, inv.id),
                        lambda: rooms.remove(room.id)):
            with pytest.raises(RoomError) as refused:
                attempt()
            assert refused.value.status == 503
    finally:
        blocker.execute("ROLLBACK")
        blocker.close()
    assert len(rooms) == 1 and rooms.get(room.id) is room
    assert list(room.invitations) == [inv.id] and not inv.revoked
    assert registry(tmp_path).store.counts() == {"rooms": 1, "room_seats": 1,
                                                 "room_invitations": 1}


def test_a_newer_schema_is_refused(tmp_path):
    RoomStore(store_path(tmp_path)).close()
    db = sqlite3.connect(store_path(tmp_path), isolation_level=None)
    assert db.execute("SELECT version FROM store_versions WHERE part = 'rooms'"
                      ).fetchone() == (SCHEMA_VERSION,)
    db.execute("UPDATE store_versions SET version = ? WHERE part = 'rooms'",
               (SCHEMA_VERSION + 1,))
    db.close()
    with pytest.raises(StoreVersionError, match="newer"):
        RoomStore(store_path(tmp_path))


def test_the_startup_room_keeps_its_id_and_its_old_links(tmp_path):
    """Two real servers, one after the other, on one data dir: the same demo room, new links
    each time, the first start's links still valid at the second; a third start at the
    invitation cap revokes the oldest instead of failing."""
    fast = {"warmup": False, "max_invitations_per_room": 4}
    with run_server(tmp_path, **fast) as first:
        links = dict(first.ctx.startup_links)
    with run_server(tmp_path, **fast) as second:
        again = second.ctx.startup_links
        assert again["room"] == links["room"]
        assert again["watch"] != links["watch"] and again["perform"] != links["perform"]
        for scope in ("watch", "perform"):
            token = links[scope].split("#token=")[1]
            inv = second.ctx.rooms.resolve(token)
            assert inv is not None and inv.scope == scope and inv.room_id == links["room"]
        assert len(second.ctx.rooms.list(Principal(LOCAL_SUBJECT, frozenset(SCOPES)))) == 1
    with run_server(tmp_path, **fast) as third:
        assert third.ctx.startup_links["room"] == links["room"]
        first_watch = links["watch"].split("#token=")[1]
        assert third.ctx.rooms.resolve(first_watch) is None  # the oldest, revoked for room
        room = third.ctx.rooms.get(links["room"])
        assert sum(i.valid(time.time()) for i in room.invitations.values()) == 4
