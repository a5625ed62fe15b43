"""Camera presets by name, defined once: ``telesplat render --camera NAME`` and
``telesplat-client watch --view NAME`` take them.

Each fixed preset is an orbit around the avatar's upper body (``Orbit`` fields: yaw and pitch
in degrees, distance in metres). Yaw 0 is the front; the engine's orbit puts yaw > 0 toward
+x, the avatar's own left, so ``right`` (yaw +60) is to your right as you face the avatar and
``left`` (yaw -60) to your left. ``orbit`` sweeps from ``left`` to ``right`` over a rendered
sequence; a sequence of one frame is the front. (A viewer's ``orbit`` is the room's own
camera: no view of its own.)
"""

from __future__ import annotations

from types import MappingProxyType

__all__ = ["CAMERA_NAMES", "CAMERA_PRESETS", "ORBIT_SWEEP_DEG", "orbit_yaws"]

PITCH_DEG = 5.0
DISTANCE_M = 2.7
ORBIT_SWEEP_DEG = (-60.0, 60.0)  # the orbit's first and last yaw

CAMERA_PRESETS = MappingProxyType({
    "front": {"yaw_deg": 0.0, "pitch_deg": PITCH_DEG, "distance": DISTANCE_M},
    "left": {"yaw_deg": ORBIT_SWEEP_DEG[0], "pitch_deg": PITCH_DEG, "distance": DISTANCE_M},
    "right": {"yaw_deg": ORBIT_SWEEP_DEG[1], "pitch_deg": PITCH_DEG, "distance": DISTANCE_M},
})
CAMERA_NAMES = ("front", "orbit", "left", "right")


def orbit_yaws(n: int) -> list[float]:
    """The orbit's yaw per frame: ``left`` to ``right`` over ``n`` frames; one frame: front."""
    if n == 1:
        return [CAMERA_PRESETS["front"]["yaw_deg"]]
    a, b = ORBIT_SWEEP_DEG
    return [a + (b - a) * i / (n - 1) for i in range(n)]
