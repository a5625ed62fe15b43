"""Whether a participant's view is moving, and what its frames cost while it is.

A viewer who orbits asks a new picture every frame, none of which is shared and each of which
is seen for a few tens of milliseconds. While the view moves its frames are previews: rendered
at ``render_scale`` of the asked size (upscaled back before encoding) and with at most
``quality`` of the Gaussians (the render budget), at the lower JPEG quality. Once the view has
been still for ``settle_s`` one full-quality frame follows, even when nothing else changes, so
a view that stops always ends sharp.

The view moves when the client says so (``view.moving``, the page's drag) or when its camera
changed twice within ``settle_s`` (a client that sends orbits without the flag). A single
change (a preset, the first view) is not a movement: it renders at full quality at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from protocol import View


@dataclass(frozen=True)
class MovingViewCost:
    """What a moving view's frames cost (server settings ``moving_view_*``)."""

    settle_s: float = 0.15     # still this long: full quality again
    render_scale: float = 0.5  # of the asked width and height, upscaled back
    quality: float = 1.0       # most Gaussians rendered, a fraction (the render budget)

    def __post_init__(self) -> None:
        if not (self.settle_s >= 0 and math.isfinite(self.settle_s)):
            raise ValueError(f"settle_s must be a finite number >= 0, got {self.settle_s}")
        if not 0.0 < self.render_scale <= 1.0:
            raise ValueError(f"render_scale must be in (0, 1], got {self.render_scale}")
        if not 0.0 < self.quality <= 1.0:
            raise ValueError(f"quality must be in (0, 1], got {self.quality}")

    @property
    def cheaper(self) -> bool:
        """Whether a moving view's frame costs less at all (off: both 1)."""
        return self.render_scale < 1.0 or self.quality < 1.0


def camera_of(view: View) -> str:
    """The view's camera, whatever its ``moving`` flag says (what is compared)."""
    return view.model_dump_json(exclude={"moving", "type"})


class ViewMotion:
    """One participant's view changes: moving now, and when it will be still."""

    def __init__(self, settle_s: float) -> None:
        self.settle_s = settle_s
        self.flagged = False           # the client's view.moving
        self._camera: str | None = None
        self._changed_at = -math.inf   # the latest camera change
        self._before = -math.inf       # the change before it

    def update(self, view: View, now: float) -> None:
        """A view arrived at ``now`` (monotonic seconds)."""
        self.flagged = view.moving
        camera = camera_of(view)
        if camera != self._camera:
            if self._camera is not None:
                self._before, self._changed_at = self._changed_at, now
            self._camera = camera

    def moving(self, now: float) -> bool:
        """The client drags, or the camera changed twice within ``settle_s`` and the last
        change is less than ``settle_s`` old."""
        return self.flagged or (self._changed_at - self._before < self.settle_s
                                and now - self._changed_at < self.settle_s)

    def still_at(self) -> float:
        """When the view will count as still if nothing changes (for the final full frame);
        ``inf`` while the client says it drags."""
        return math.inf if self.flagged else self._changed_at + self.settle_s
