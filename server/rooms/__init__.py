"""Rooms: live scenes of one or more seats (an avatar each, driven by at most one performer)
watched by any number of viewers, with the work shared between them.

``registry`` holds rooms and their invitations (in memory, written through to ``store``: rows
of the jobs' SQLite file, so rooms and links survive a restart), ``live`` the runtime of an
occupied room (seats, participants, presence, hold/ease/idle), ``frames`` the shared posing,
rendering and encoding, ``participant`` one WebSocket in a room, ``join`` the WebSocket's
authentication and admission.
"""
