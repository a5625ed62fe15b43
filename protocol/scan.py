"""Count a msgpack message's objects before unpacking it, stopping at a limit.

Why: msgpack's unpacker is C code that holds the GIL, and its cost grows with the number of
objects, not bytes: 7 MiB of tiny nested arrays take over a second to unpack, on whichever
thread does it. Walking the headers in Python costs well under a microsecond per object and
stops at the limit, so the unpack that follows is bounded too. Bin and str payloads are
skipped by length, so a message carrying one large image costs a handful of steps.
"""

from __future__ import annotations

from .errors import ProtocolError

# Header byte -> bytes of payload that follow it (fixed-size scalars and fixext).
_FIXED = {0xc0: 0, 0xc2: 0, 0xc3: 0, 0xca: 4, 0xcb: 8, 0xcc: 1, 0xcd: 2, 0xce: 4, 0xcf: 8,
          0xd0: 1, 0xd1: 2, 0xd2: 4, 0xd3: 8, 0xd4: 2, 0xd5: 3, 0xd6: 5, 0xd7: 9, 0xd8: 17}
# Header byte -> (width of the length field, extra bytes after it) for bin, str and ext.
_SIZED = {0xc4: (1, 0), 0xc5: (2, 0), 0xc6: (4, 0), 0xd9: (1, 0), 0xda: (2, 0), 0xdb: (4, 0),
          0xc7: (1, 1), 0xc8: (2, 1), 0xc9: (4, 1)}
# Header byte -> (width of the count field, objects per counted entry) for arrays and maps.
_CONTAINERS = {0xdc: (2, 1), 0xdd: (4, 1), 0xde: (2, 2), 0xdf: (4, 2)}


def check_object_count(data: bytes | bytearray | memoryview, max_objects: int) -> int:
    """How many objects ``data`` holds (its first top-level value); ProtocolError
    ``too_large`` past ``max_objects``. A malformed or truncated message ends the walk early:
    the unpacker reports it, having read no more objects than were counted here."""
    view = bytes(data) if isinstance(data, memoryview) else data
    end = len(view)
    pos = 0
    pending = 1  # objects still to read
    count = 0
    while pending and pos < end:
        pending -= 1
        count += 1
        if count > max_objects:
            raise ProtocolError("too_large", f"message has more than {max_objects} msgpack "
                                             "objects")
        head = view[pos]
        pos += 1
        if head <= 0x7f or head >= 0xe0:  # positive / negative fixint
            continue
        if head <= 0x8f:  # fixmap
            pending += 2 * (head & 0x0f)
        elif head <= 0x9f:  # fixarray
            pending += head & 0x0f
        elif head <= 0xbf:  # fixstr
            pos += head & 0x1f
        elif head in _FIXED:
            pos += _FIXED[head]
        elif head in _SIZED:
            width, extra = _SIZED[head]
            pos += width + extra + int.from_bytes(view[pos:pos + width], "big")
        elif head in _CONTAINERS:
            width, per_entry = _CONTAINERS[head]
            pending += per_entry * int.from_bytes(view[pos:pos + width], "big")
            pos += width
        else:  # 0xc1, never used: the unpacker refuses it
            break
    return count
