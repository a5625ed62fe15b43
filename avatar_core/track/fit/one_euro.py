"""The One Euro filter (Casiez, Roussel and Vogel, CHI 2012), on arrays of any shape.

A first-order low-pass whose cutoff rises with the signal's speed: slow motion is smoothed
hard (less jitter), fast motion passes with little lag. Per element:

    dx    = lowpass((x - x_prev) / dt, d_cutoff)
    cut   = min_cutoff + beta * |dx|
    x_hat = lowpass(x, cut),  lowpass(v, f): alpha = 1 / (1 + 1 / (2 pi f dt))
"""

from __future__ import annotations

import math

import numpy as np


def _alpha(cutoff: np.ndarray | float, dt: float) -> np.ndarray | float:
    tau = 1.0 / (2.0 * math.pi * np.asarray(cutoff))
    return 1.0 / (1.0 + tau / dt)


class OneEuroFilter:
    def __init__(self, min_cutoff: float = 1.0, beta: float = 0.05,
                 d_cutoff: float = 1.0) -> None:
        if min_cutoff <= 0 or d_cutoff <= 0 or beta < 0:
            raise ValueError("min_cutoff and d_cutoff must be > 0, beta >= 0")
        self.min_cutoff, self.beta, self.d_cutoff = min_cutoff, beta, d_cutoff
        self.reset()

    def reset(self) -> None:
        self._x: np.ndarray | None = None
        self._dx: np.ndarray | None = None
        self._t: float | None = None

    def __call__(self, x: np.ndarray, t: float) -> np.ndarray:
        """The filtered value of sample `x` taken at time `t` (seconds, increasing)."""
        x = np.asarray(x, dtype=np.float64)
        if self._x is None or self._x.shape != x.shape or self._t is None or t <= self._t:
            self._x, self._dx, self._t = x.copy(), np.zeros_like(x), t  # (re)start: pass
            return x.copy()
        dt = t - self._t
        dx = (x - self._x) / dt
        self._dx = self._dx + _alpha(self.d_cutoff, dt) * (dx - self._dx)
        cutoff = self.min_cutoff + self.beta * np.abs(self._dx)
        self._x = self._x + _alpha(cutoff, dt) * (x - self._x)
        self._t = t
        return self._x.copy()


class ParamSmoother:
    """One filter per parameter name, for dicts of arrays."""

    def __init__(self, min_cutoff: float = 1.0, beta: float = 0.05,
                 d_cutoff: float = 1.0) -> None:
        self.settings = (min_cutoff, beta, d_cutoff)
        self.filters: dict[str, OneEuroFilter] = {}

    def reset(self) -> None:
        self.filters.clear()

    def __call__(self, params: dict[str, np.ndarray], t: float) -> dict[str, np.ndarray]:
        out = {}
        for name, value in params.items():
            f = self.filters.get(name)
            if f is None:
                f = self.filters[name] = OneEuroFilter(*self.settings)
            out[name] = f(value, t)
        return out
