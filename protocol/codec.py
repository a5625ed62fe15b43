"""msgpack codec: message objects <-> bytes, with size limits checked before parsing."""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np
from pydantic import BaseModel, TypeAdapter, ValidationError

from .arrays import pack_array
from .errors import ProtocolError
from .limits import DEFAULT_LIMITS, Limits
from .messages import CLIENT_TYPES, SERVER_TYPES, ClientMessage, ServerMessage

_CLIENT = TypeAdapter(ClientMessage)
_SERVER = TypeAdapter(ServerMessage)


def _plain(obj: Any) -> Any:
    """Model dumps with numpy arrays packed for the wire."""
    if isinstance(obj, np.ndarray):
        return pack_array(obj)
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    return obj


def encode(message: BaseModel | dict[str, Any]) -> bytes:
    """A message (model or plain dict) as msgpack bytes; None fields are left out."""
    data = message.model_dump(exclude_none=True) if isinstance(message, BaseModel) else message
    return msgpack.packb(_plain(data), use_bin_type=True)


def _unpack(data: bytes, limits: Limits) -> dict[str, Any]:
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError("bad_message", "messages are binary msgpack frames")
    if len(data) > limits.max_message_bytes:
        raise ProtocolError("too_large", f"message of {len(data)} bytes exceeds the limit "
                                         f"{limits.max_message_bytes}")
    try:
        obj = msgpack.unpackb(
            data, raw=False, strict_map_key=True, use_list=True,
            max_str_len=limits.max_string_chars, max_bin_len=limits.max_message_bytes,
            max_array_len=limits.max_array_elements, max_map_len=256, max_ext_len=0)
    except (ValueError, TypeError, msgpack.ExtraData, msgpack.FormatError,
            msgpack.StackError, RecursionError) as exc:
        raise ProtocolError("bad_message", f"not a msgpack message: {exc}") from exc
    if not isinstance(obj, dict):
        raise ProtocolError("bad_message", "a message is a msgpack map")
    return obj


def _answers(obj: dict[str, Any]) -> dict[str, Any]:
    seq = obj.get("seq")
    return {"type": obj.get("type") if isinstance(obj.get("type"), str) else None,
            "seq": seq if isinstance(seq, int) and not isinstance(seq, bool) else None}


def _validate(adapter: TypeAdapter, known: dict, obj: dict[str, Any], limits: Limits):
    kind = obj.get("type")
    if not isinstance(kind, str) or kind not in known:  # a list or map is unhashable
        raise ProtocolError("bad_message", f"unknown message type {kind!r}; expected one of "
                                           f"{sorted(known)}", _answers(obj))
    try:
        return adapter.validate_python(obj, context={"limits": limits})
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"][1:]) or kind
        msg = first["msg"].removeprefix("Value error, ")
        code = "too_large" if "exceeds the limit" in msg else "invalid"
        raise ProtocolError(code, f"{kind}: {where}: {msg}", _answers(obj)) from exc


def decode_client(data: bytes, limits: Limits = DEFAULT_LIMITS):
    """Bytes from a client -> a validated client message, or ProtocolError."""
    return _validate(_CLIENT, CLIENT_TYPES, _unpack(data, limits), limits)


def decode_server(data: bytes, limits: Limits = DEFAULT_LIMITS):
    """Bytes from a server -> a validated server message, or ProtocolError."""
    big = limits.model_copy(update={"max_message_bytes": max(limits.max_message_bytes,
                                                             64 * 1024 * 1024)})
    return _validate(_SERVER, SERVER_TYPES, _unpack(data, big), big)
