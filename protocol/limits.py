"""Every limit the protocol enforces, explicit and configurable.

The server sends its :class:`Limits` in ``welcome`` so a client knows them up front; the codec
checks a message against them before anything else runs.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class Limits(BaseModel):
    """Upper bounds on what one session may send or ask for."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    max_message_bytes: int = Field(8 * 1024 * 1024, ge=1024)  # one WebSocket message
    max_image_bytes: int = Field(4 * 1024 * 1024, ge=1024)    # one encoded webcam frame
    max_image_pixels: int = Field(1920 * 1080, ge=64 * 64)    # decoded webcam frame, w*h
    max_width: int = Field(1920, ge=16)                       # rendered frame
    max_height: int = Field(1080, ge=16)
    max_fps: float = Field(60.0, gt=0)                        # per-session frame-rate cap
    max_messages_per_s: float = Field(240.0, gt=0)            # inbound rate, token bucket
    max_array_elements: int = Field(4096, ge=64)              # one parameter array
    max_string_chars: int = Field(4096, ge=64)


DEFAULT_LIMITS = Limits()
