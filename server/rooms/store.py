"""Rooms, their seats and their invitations as rows of the jobs' SQLite file, so a restart
(even ``kill -9``) loses no room and no link.

:class:`RoomStore` is the registry's write-through store (server/rooms/registry.py): every
change (a room created, an invitation issued or revoked, a room deleted or closed for
idleness) is one ``BEGIN IMMEDIATE`` transaction, committed before the change is visible to
anyone, and :meth:`RoomStore.load` reads everything back at start-up. It shares the jobs'
database file (``data_dir/jobs/jobs.db``, server/jobs/store.py) and its patterns: WAL, one
connection per thread, explicit transactions, a busy timeout (the training process writes to
the same file). WAL with ``synchronous=NORMAL`` keeps a committed transaction across a
crash of the process; only a power loss may lose the newest ones.

What is stored: a room's id, name, owner, creation time and ``pinned``; each seat's index,
avatar and placement; each invitation's id, sha256 digest (never the token), scope, seat,
expiry and ``revoked``. Not stored: who is in a room, the seats' poses, a plain session's
private room (``Room.private``). The schema has a version (table ``store_versions``, row
``rooms``): an older one is migrated on open, a newer one refused.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path

from ..sqlite import SQLiteFile
from .registry import Invitation, Placement, Room, SeatSpec

# The jobs' store file (server/jobs/service.py JOBS_DIR / DB_FILE; tests/test_rooms_store.py
# checks they agree): rooms are rows of the same store.
STORE_FILE = Path("jobs") / "jobs.db"
SCHEMA_VERSION = 1

_SCHEMA = """
CREATE TABLE IF NOT EXISTS store_versions (
    part TEXT PRIMARY KEY,
    version INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS rooms (
    id TEXT PRIMARY KEY,
    name TEXT NOT NULL,
    owner TEXT NOT NULL,
    created REAL NOT NULL,
    pinned INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX IF NOT EXISTS rooms_owner ON rooms (owner, created);
CREATE TABLE IF NOT EXISTS room_seats (
    room_id TEXT NOT NULL REFERENCES rooms (id) ON DELETE CASCADE,
    idx INTEGER NOT NULL,
    avatar TEXT NOT NULL,
    tx REAL NOT NULL, ty REAL NOT NULL, tz REAL NOT NULL,
    rx REAL NOT NULL, ry REAL NOT NULL, rz REAL NOT NULL,
    PRIMARY KEY (room_id, idx)
);
CREATE TABLE IF NOT EXISTS room_invitations (
    id TEXT PRIMARY KEY,
    room_id TEXT NOT NULL REFERENCES rooms (id) ON DELETE CASCADE,
    digest TEXT NOT NULL UNIQUE,
    scope TEXT NOT NULL CHECK (scope IN ('perform', 'watch')),
    seat INTEGER,
    expires_at REAL NOT NULL,
    revoked INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX IF NOT EXISTS room_invitations_room ON room_invitations (room_id);
"""
# Migrations from version N to N + 1, in order (none yet: version 1 is the first).
_MIGRATIONS: dict[int, str] = {}


class StoreVersionError(RuntimeError):
    """The database was written by a newer release (its rooms schema is past ours)."""


def store_path(data_dir: str | Path) -> Path:
    return Path(data_dir) / STORE_FILE


class RoomStore(SQLiteFile):
    """Rooms in one SQLite file; usable from many threads (a connection each)."""

    def __init__(self, path: str | Path, *, timeout_s: float = 30.0) -> None:
        super().__init__(path, _SCHEMA, timeout_s=timeout_s)
        self._migrate()

    def _migrate(self) -> None:
        with self._write() as db:
            row = db.execute("SELECT version FROM store_versions WHERE part = 'rooms'").fetchone()
            version = SCHEMA_VERSION if row is None else int(row["version"])
            if version > SCHEMA_VERSION:
                raise StoreVersionError(
                    f"{self.path}: rooms schema version {version} is newer than this "
                    f"release's ({SCHEMA_VERSION}); run the newer server or restore a backup")
            while version < SCHEMA_VERSION:
                db.executescript(_MIGRATIONS[version])
                version += 1
            db.execute("INSERT INTO store_versions (part, version) VALUES ('rooms', ?) "
                       "ON CONFLICT (part) DO UPDATE SET version = excluded.version",
                       (SCHEMA_VERSION,))

    # -- writes (one transaction each) -------------------------------------------------------

    def add_room(self, room: Room) -> None:
        if room.private:
            raise ValueError("a plain session's private room is never stored")
        with self._write() as db:
            db.execute("INSERT INTO rooms (id, name, owner, created, pinned) "
                       "VALUES (?, ?, ?, ?, ?)",
                       (room.id, room.name, room.owner, room.created, int(room.pinned)))
            db.executemany(
                "INSERT INTO room_seats (room_id, idx, avatar, tx, ty, tz, rx, ry, rz) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                [(room.id, seat.index, seat.avatar, *map(float, seat.placement.translation),
                  *map(float, seat.placement.rotation)) for seat in room.seats])
            for inv in room.invitations.values():
                self._insert_invitation(db, inv)

    def remove_rooms(self, room_ids: list[str]) -> None:
        """The rooms and (cascading) their seats and invitations."""
        if not room_ids:
            return
        with self._write() as db:
            db.executemany("DELETE FROM rooms WHERE id = ?", [(i,) for i in room_ids])

    def add_invitation(self, inv: Invitation, pruned: list[str] = ()) -> None:
        """A new invitation; ``pruned``: ids of the room's expired or revoked ones, deleted in
        the same transaction."""
        with self._write() as db:
            db.executemany("DELETE FROM room_invitations WHERE id = ?", [(i,) for i in pruned])
            self._insert_invitation(db, inv)

    def revoke_invitation(self, invitation_id: str) -> None:
        with self._write() as db:
            db.execute("UPDATE room_invitations SET revoked = 1 WHERE id = ?", (invitation_id,))

    @staticmethod
    def _insert_invitation(db: sqlite3.Connection, inv: Invitation) -> None:
        db.execute("INSERT INTO room_invitations (id, room_id, digest, scope, seat, expires_at, "
                   "revoked) VALUES (?, ?, ?, ?, ?, ?, ?)",
                   (inv.id, inv.room_id, inv.digest, inv.scope, inv.seat, inv.expires_at,
                    int(inv.revoked)))

    # -- reading -----------------------------------------------------------------------------

    def load(self, empty_since: float) -> list[Room]:
        """Every stored room with its seats and invitations, oldest first; each empty since
        ``empty_since`` (monotonic: nobody is in a room after a restart)."""
        db = self._db()
        seats: dict[str, list[SeatSpec]] = {}
        for r in db.execute("SELECT * FROM room_seats ORDER BY room_id, idx"):
            seats.setdefault(r["room_id"], []).append(SeatSpec(
                r["idx"], r["avatar"], Placement((r["tx"], r["ty"], r["tz"]),
                                                 (r["rx"], r["ry"], r["rz"]))))
        invitations: dict[str, dict[str, Invitation]] = {}
        for r in db.execute("SELECT * FROM room_invitations ORDER BY rowid"):
            invitations.setdefault(r["room_id"], {})[r["id"]] = Invitation(
                r["id"], r["room_id"], r["digest"], r["scope"], r["seat"], r["expires_at"],
                bool(r["revoked"]))
        rooms = []
        for r in db.execute("SELECT * FROM rooms ORDER BY created, rowid"):
            if r["id"] not in seats:  # cannot be written so (one transaction); skip if it is
                continue
            rooms.append(Room(r["id"], r["name"], r["owner"], seats[r["id"]], r["created"],
                              pinned=bool(r["pinned"]),
                              invitations=invitations.get(r["id"], {}),
                              empty_since=empty_since))
        return rooms

    def counts(self) -> dict[str, int]:
        """Rows per table (tests, diagnostics)."""
        db = self._db()
        return {table: int(db.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0])
                for table in ("rooms", "room_seats", "room_invitations")}
