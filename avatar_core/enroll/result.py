"""What one enrollment produced: frames used and dropped (by cause), the fitted shape,
training stats and the avatar package it wrote."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any


@dataclass
class FrameCounts:
    """Frames of the video by fate: each frame is counted once, under its first cause."""

    total: int = 0
    used: int = 0
    failed_track: int = 0
    blurred: int = 0
    duplicate: int = 0
    subsampled: int = 0              # sharp and new, but above max_frames (not tracked)

    def dropped(self) -> dict[str, int]:
        return {"failed_track": self.failed_track, "blurred": self.blurred,
                "duplicate": self.duplicate, "subsampled": self.subsampled}


@dataclass
class EnrollResult:
    package: Path                    # the avatar package directory written in out_dir
    frames: FrameCounts
    betas: list[float]               # the one body shape fitted across the video
    focal_px: float                  # at the video's resolution
    focal_source: str                # "metadata" or "prior+fit"
    yaw_range_deg: float
    train: dict[str, Any] = field(default_factory=dict)   # iterations, seconds, gaussians, loss
    timings: dict[str, float] = field(default_factory=dict)  # seconds per stage

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["package"] = str(self.package)
        out["frames"]["dropped"] = self.frames.dropped()
        return out
