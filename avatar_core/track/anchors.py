"""SSD anchors for MediaPipe's detectors (SsdAnchorsCalculator, fixed-size anchors).

Every detector here uses the same recipe: feature maps at the listed strides, anchor centres
at the cell centres, aspect ratio 1 plus one interpolated-scale anchor per layer, and
``fixed_anchor_size`` (every anchor is 1 x 1, so the regressors are offsets in input pixels).
Consecutive layers with the same stride share one feature map: each of its cells gets
2 anchors per layer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class AnchorSpec:
    input_size: int  # square model input, px
    strides: tuple[int, ...]
    offset: float = 0.5  # anchor_offset_x / _y
    anchors_per_layer: int = 2  # aspect ratio 1.0 + the interpolated scale


# The options in MediaPipe's graphs for each detector.
FACE_SHORT_RANGE = AnchorSpec(128, (8, 16, 16, 16))
PALM_192 = AnchorSpec(192, (8, 16, 16, 16))
POSE_224 = AnchorSpec(224, (8, 16, 32, 32, 32))


def ssd_anchors(spec: AnchorSpec) -> np.ndarray:
    """[N, 2] float32 anchor centres (x, y), normalised to the model input, in the order the
    model's outputs use: per stride group, row-major over cells, anchors innermost."""
    centres = []
    i = 0
    while i < len(spec.strides):
        stride = spec.strides[i]
        layers = 0
        while i < len(spec.strides) and spec.strides[i] == stride:
            layers += 1
            i += 1
        size = int(np.ceil(spec.input_size / stride))
        ys, xs = np.meshgrid((np.arange(size) + spec.offset) / size,
                             (np.arange(size) + spec.offset) / size, indexing="ij")
        cells = np.stack([xs.ravel(), ys.ravel()], axis=1)  # [size*size, 2]
        centres.append(np.repeat(cells, layers * spec.anchors_per_layer, axis=0))
    return np.concatenate(centres).astype(np.float32)
