"""Rooms: live scenes of one or more seats (an avatar each, driven by at most one performer)
watched by any number of viewers, with the work shared between them.

``registry`` holds rooms and their invitations (in memory: a room is a live scene and does not
survive a restart), ``live`` the runtime of an occupied room (seats, participants, presence,
hold/ease/idle), ``frames`` the shared posing, rendering and encoding, ``participant`` one
WebSocket in a room, ``join`` the WebSocket's authentication and admission.
"""
