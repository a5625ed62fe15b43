"""A session's frame-rate cap as a rate, not a minimum interval (GCRA, the leaky bucket).

A drive arriving a little early for a strict ``1 / max_fps`` interval waits for its slot: at
matched rates (a 30 Hz tracker, a 30 fps cap) the frames lock to the latest arrival phase seen.
With a burst of ``burst`` frames a frame may start up to ``burst - 1`` intervals ahead of the
cap's schedule; over any span the count stays at most ``span * max_fps + burst``. ``burst`` 1
(the server's default) is the strict interval: a burst gained one viewer 5 ms and cost 16
viewers sharing renders on 2 cores 40 ms (docs/benchmarks.md, "The frame-rate cap as a rate").
"""

from __future__ import annotations

import math


class FrameRateCap:
    """When the next frame may start at ``fps`` frames a second on average, ``burst`` at
    most back to back: the generic cell-rate algorithm, its schedule kept as where the last
    frame's slot began so that a new ``fps`` applies at once to the wait for the next."""

    def __init__(self, burst: int = 1) -> None:
        if burst < 1:
            raise ValueError(f"burst {burst} must be >= 1")
        self.burst = burst
        self._slot = -math.inf  # where the last frame's slot began on the cap's schedule

    def earliest(self, fps: float) -> float:
        """The earliest start (time.monotonic()) for the next frame."""
        return self._slot + 1.0 / fps - (self.burst - 1) / fps

    def started(self, at: float, fps: float) -> None:
        """A frame started at ``at``: its slot is taken."""
        self._slot = max(self._slot + 1.0 / fps, at)
