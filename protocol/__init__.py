"""Wire protocol shared by server and clients: message types, msgpack codec, limits.

It imports numpy, msgpack and pydantic only. ``client/web/protocol.js`` is generated from
these definitions by ``python -m protocol.jsgen`` and a test checks that the two agree.
"""

from .arrays import pack_array, unpack_array
from .codec import decode_client, decode_server, encode
from .errors import ERROR_CODES, ProtocolError
from .limits import DEFAULT_LIMITS, Limits
from .messages import (
    CLIENT_TYPES,
    CODECS,
    OUTPUTS,
    PROTOCOL_MINOR,
    PROTOCOL_VERSION,
    SERVER_TYPES,
    AvatarInfo,
    AvatarReplaced,
    CameraSpec,
    Drive,
    Error,
    Frame,
    Framing,
    Hello,
    Image,
    Orbit,
    Ping,
    Pong,
    Presence,
    Request,
    RoomWelcome,
    SeatPresence,
    Stats,
    Timings,
    Tracked,
    View,
    Voice,
    VoiceBounds,
    Welcome,
)
from .params import FAMILIES

__all__ = [
    "CLIENT_TYPES", "CODECS", "DEFAULT_LIMITS", "ERROR_CODES", "FAMILIES", "OUTPUTS",
    "PROTOCOL_MINOR", "PROTOCOL_VERSION", "SERVER_TYPES", "AvatarInfo", "AvatarReplaced",
    "CameraSpec", "Drive",
    "Error", "Frame", "Framing", "Hello", "Image", "Limits", "Orbit", "Ping", "Pong", "Presence",
    "ProtocolError", "Request", "RoomWelcome", "SeatPresence", "Stats", "Timings", "Tracked",
    "View", "Voice", "VoiceBounds", "Welcome", "decode_client", "decode_server", "encode",
    "pack_array", "unpack_array",
]
