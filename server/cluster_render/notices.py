"""What participants are told when their render worker is lost: ``reconnecting`` (their
scene moves to another worker; frames follow), or, when none is left, an error and a close."""

from __future__ import annotations

from typing import Any

from protocol import Error

from ..stream.gate import CLOSE_BUSY


def reconnecting(worker: str) -> Error:
    return Error(code="reconnecting",
                 message=f"render worker {worker} was lost; this session moves to another "
                         "worker and its frames resume shortly (its state is kept)")


async def close_unavailable(session: Any, message: str) -> None:
    """Tell a session no worker can render it, then close it (1013: try again later)."""
    await session.close_with("internal", message, CLOSE_BUSY)
