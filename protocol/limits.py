"""Every limit the protocol enforces, explicit and configurable.

The server sends its :class:`Limits` in ``welcome`` so a client knows them up front; the codec
checks a message against them before anything else runs.
"""

from __future__ import annotations

import math

from pydantic import BaseModel, ConfigDict, Field, model_validator


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
    # Value ranges: finite but absurd values are refused at the boundary, never reach a model.
    # Rotations are axis-angle: two full turns cover any tracker's or clip's winding.
    max_rotation_rad: float = Field(4 * math.pi, gt=0)   # norm of each axis-angle rotation
    max_coefficient: float = Field(10.0, gt=0)           # |x| of betas, expression, PCA hands
    max_translation_m: float = Field(10.0, gt=0)         # norm of a body / head / hand transl
    max_position_m: float = Field(100.0, gt=0)           # camera centre, orbit target
    min_orbit_distance_m: float = Field(0.05, gt=0)
    max_orbit_distance_m: float = Field(100.0, gt=0)
    min_fov_deg: float = Field(5.0, gt=0, lt=180)        # vertical field of view of a view
    max_fov_deg: float = Field(120.0, gt=0, lt=180)
    max_camera_size: int = Field(16384, ge=16)           # a full camera's own width / height
    min_fps: float = Field(1.0, gt=0)                    # lowest max_fps a request may ask
    max_name_chars: int = Field(32, ge=1, le=200)        # a participant's display name

    @model_validator(mode="after")
    def _ordered(self) -> Limits:
        for low, high in (("min_orbit_distance_m", "max_orbit_distance_m"),
                          ("min_fov_deg", "max_fov_deg"), ("min_fps", "max_fps")):
            if getattr(self, low) > getattr(self, high):
                raise ValueError(f"{low} must not exceed {high}")
        return self


DEFAULT_LIMITS = Limits()
