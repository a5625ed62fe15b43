"""What `telesplat track build-embedding` films: identities, clips, views (no heavy imports,
so the CLI can show its defaults)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

# The webcam protocol's take (sad+angry+clapping on identity 0) is never trained on.
TRAIN_CLIPS = ("thumbs_up", "pointing", "heart", "talk_animated", "shrug", "peace")
HELD_OUT_CLIPS = ("sad", "angry", "clapping")
TRAIN_IDENTITIES = (2, 3, 4, 5)
HELD_OUT_IDENTITIES = (0, 1)
FRAMINGS = {"waist_up": 1.05, "head_shoulders": 0.7}  # `subject_transl` margins


@dataclass(frozen=True)
class BuildSpec:
    train_identities: tuple[int, ...] = TRAIN_IDENTITIES
    held_out_identities: tuple[int, ...] = HELD_OUT_IDENTITIES
    train_clips: tuple[str, ...] = TRAIN_CLIPS
    held_out_clips: tuple[str, ...] = HELD_OUT_CLIPS
    yaws_deg: tuple[float, ...] = (-30.0, 0.0, 30.0)
    framings: tuple[str, ...] = ("waist_up", "head_shoulders")
    frames_per_view: int = 2   # random instants of each clip per (identity, clip, view)
    seed: int = 0
    supersample: int = 2
    min_samples: int = 40      # a landmark seen fewer times keeps offset 0

    def __post_init__(self) -> None:
        if self.frames_per_view < 1 or not self.train_identities or not self.train_clips:
            raise ValueError("frames_per_view >= 1 and at least one training identity "
                             "and clip are needed")
        if set(self.train_identities) & set(self.held_out_identities):
            raise ValueError("training and held-out identities must differ")
        if set(self.train_clips) & set(self.held_out_clips):
            raise ValueError("training and held-out clips must differ")
        unknown = [f for f in self.framings if f not in FRAMINGS]
        if unknown:
            raise ValueError(f"unknown framing(s) {unknown}; known: {sorted(FRAMINGS)}")

    def jobs(self, identities: Sequence[int], clips: Sequence[str]) -> list[tuple]:
        return [(i, c, y, f) for i in identities for c in clips for y in self.yaws_deg
                for f in self.framings]

    def count(self) -> int:
        n = len(self.jobs(self.train_identities, self.train_clips)) + len(
            self.jobs(self.held_out_identities, self.held_out_clips))
        return n * self.frames_per_view


