"""A session's body-model state: partial ``drive`` updates merged per family, and the SMPL-X
parameters they amount to, with FLAME (face) and MANO (hands) fused in.

Fusion goes through the trainer's and the evaluator's front door (``FusionModels.fuse``: world-frame
head and wrist rotations) on the avatar's own upper-body model; MANO keys need the MANO model
files next to the body model (the synthetic family has them).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from avatar_core.body.fusion import FusionModels
from avatar_core.body.models import MANOModel, SMPLXModel
from avatar_core.body.rest_pose import rest_body_pose
from protocol import Drive, ProtocolError
from protocol.params import FAMILIES, FLAME_FIELDS

from .capture_clock import ArrivalClock

FAMILY_NAMES = tuple(FAMILIES)  # smplx, flame, mano_left, mano_right

# FLAME fields fusion reads live: the protocol's fixed-shape ones, plus expr (fitted to the
# body model's size below); `shape` (identity) is not driven live.
FLAME_SHAPES = {name: shape for name, (kind, shape) in FLAME_FIELDS.items() if kind == "fixed"}

# What a parameter nobody has sent is: the rest pose's body_pose (body/rest_pose.py), else zero.
REST_BODY_POSE = rest_body_pose()
REST_BODY_POSE.flags.writeable = False


def rest_value(family: str, name: str, like: np.ndarray) -> np.ndarray:
    """The rest value of one parameter, shaped like ``like``: where easing back to rest goes."""
    if family == "smplx" and name == "body_pose" and np.shape(like) == REST_BODY_POSE.shape:
        return REST_BODY_POSE
    return np.zeros_like(like)


def drive_shapes(model: SMPLXModel, manos: dict[str, MANOModel]
                 ) -> dict[str, dict[str, tuple[int, ...]]]:
    """Per family, the per-frame shape each parameter must have for this avatar."""
    smplx = {k: v for k, v in model.param_spec().items() if k != "vertex_offsets"}
    flame = {**FLAME_SHAPES, "expr": (model.num_expression,)}
    out = {"smplx": smplx, "flame": flame}
    for side in ("left", "right"):
        if side in manos:
            out[f"mano_{side}"] = manos[side].param_spec()
    return out


def fit_drive(drive: Drive, shapes: dict[str, dict[str, tuple[int, ...]]]
              ) -> dict[str, dict[str, np.ndarray]]:
    """The drive's families with shapes this avatar takes: coefficient vectors (betas,
    expression) are cut or zero-padded to the model's count, as SMPL-X / FLAME tools do.
    ProtocolError for what cannot fit (a family or field this avatar does not take)."""
    out: dict[str, dict[str, np.ndarray]] = {}
    for family, values in drive.families().items():
        spec = shapes.get(family)
        if spec is None:
            raise ProtocolError("unsupported", f"{family}: this avatar's body model has no "
                                               "model for it", {"type": "drive", "seq": drive.seq})
        fitted = {}
        for name, arr in values.items():
            want = spec.get(name)
            if want is None:
                raise ProtocolError("unsupported", f"{family}.{name} cannot be driven live",
                                    {"type": "drive", "seq": drive.seq})
            if arr.shape != want and arr.ndim == 1 and len(want) == 1:
                arr = np.pad(arr[:want[0]], (0, max(0, want[0] - arr.size)))
            if arr.shape != want:
                raise ProtocolError("invalid", f"{family}.{name}: this avatar takes shape "
                                               f"{list(want)}, got {list(arr.shape)}",
                                    {"type": "drive", "seq": drive.seq})
            fitted[name] = arr
        out[family] = fitted
    return out


@dataclass
class DriveState:
    """The newest value of every parameter sent so far, per family; ``seq`` of the last drive."""

    families: dict[str, dict[str, np.ndarray]] = field(
        default_factory=lambda: {name: {} for name in FAMILY_NAMES})
    seq: int = -1
    version: int = 0  # +1 per applied drive: equal versions pose the same mesh
    captured: float | None = None  # the last drive's t_capture (the performer's clock)
    arrived: float | None = None   # time.monotonic() when it was applied here
    # its capture instant on this server's clock (t_capture through the performer's
    # ArrivalClock; its arrival when it had no t_capture): the WebRTC senders' clock
    captured_at: float | None = None

    def apply(self, drive: Drive, fitted: dict[str, dict[str, np.ndarray]],
              clock: ArrivalClock | None = None, arrived: float | None = None) -> None:
        """Merge a drive (its families as :func:`fit_drive` returned them) that came at
        ``arrived`` (monotonic; None: now); ``clock`` maps its t_capture to this server's
        clock."""
        if drive.reset:
            self.families = {name: {} for name in FAMILY_NAMES}
        for name, values in fitted.items():
            self.families[name] = {**self.families[name], **values}
        self.seq = drive.seq
        self.version += 1
        self.captured = drive.t_capture
        self.arrived = time.monotonic() if arrived is None else arrived
        self.captured_at = (self.arrived if clock is None or drive.t_capture is None
                            else clock.observe(drive.t_capture, self.arrived))

    def restore(self, failed: DriveState, good: DriveState) -> bool:
        """A frame of ``failed`` did not render: every value it held that is still current
        and differs from ``good`` (the last state that rendered) goes back to ``good``'s.
        Values sent since the failure stay. True when something was put back.

        Arrays are replaced, never mutated, so identity tells what changed."""
        restored = False
        for family, values in failed.families.items():
            current, before = self.families[family], good.families[family]
            for name, value in values.items():
                if current.get(name) is not value or before.get(name) is value:
                    continue
                current = {k: v for k, v in current.items() if k != name}
                if name in before:
                    current[name] = before[name]
                restored = True
            self.families[family] = current
        if restored:
            self.version += 1
        return restored

    def copy(self) -> DriveState:
        # Arrays are never mutated in place (updates replace them), so a shallow copy is enough.
        return DriveState({k: dict(v) for k, v in self.families.items()}, self.seq,
                          self.version, self.captured, self.arrived, self.captured_at)

    def smplx_params(self, model: SMPLXModel, manos: dict[str, MANOModel]) -> dict[str, Any]:
        """SMPL-X parameters (no batch axis, or batch 1) with the face and hands fused in.

        Raises ValueError (ParameterError) when the parameters do not fit the model."""
        hands = {side: self.families[f"mano_{side}"] for side in ("left", "right")}
        body = {"body_pose": REST_BODY_POSE, **self.families["smplx"]}  # unsent: at rest
        return FusionModels(model, manos).fuse(body, self.families["flame"], hands)
