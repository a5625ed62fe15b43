"""The protocol's error type and its codes (sent back in ``error`` messages)."""

from __future__ import annotations

# Codes a server sends in `error.code`; clients may branch on them.
ERROR_CODES = (
    "bad_message",       # not msgpack, not a map, no/unknown type
    "invalid",           # a known type whose fields fail validation
    "too_large",         # over a size limit
    "rate_limited",      # over the inbound message rate
    "unsupported",       # a valid request this server cannot serve (codec, backend)
    "version",           # protocol version mismatch
    "unauthorized",      # missing or bad token
    "forbidden",         # token lacks the scope, the avatar is another owner's, a watcher
                         # sent drive/image, or a room seat is taken
    "not_found",         # unknown avatar or room
    "gone",              # the room was deleted while this session was in it
    "busy",              # session cap reached
    "internal",          # the server failed; the session goes on
    "reconnecting",      # a notice: the render worker was lost, the session moves to another
                         # (render_backend ray); frames resume, the session's state is kept
    "restarting",        # the server is restarting: the connection closes next (code 1012);
                         # reconnect (with backoff) into the same room and seat
)


class ProtocolError(ValueError):
    """A message that cannot be accepted. ``code`` is one of :data:`ERROR_CODES`."""

    def __init__(self, code: str, message: str, answers: dict | None = None) -> None:
        if code not in ERROR_CODES:
            raise ValueError(f"unknown protocol error code {code!r}")
        super().__init__(message)
        self.code = code
        self.message = message
        self.answers = answers
