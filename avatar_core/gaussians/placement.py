"""Seats in one scene: Gaussians moved rigidly, and several avatars' Gaussians as one set."""

from __future__ import annotations

import torch

from avatar_core.render.types import GaussianSet
from avatar_core.rotations import matrix_to_quaternion, quaternion_multiply


def place(gaussians: GaussianSet, rotation: torch.Tensor | None,
          translation: torch.Tensor | None) -> GaussianSet:
    """Gaussians moved rigidly: means rotated then translated, orientations composed.
    (View-dependent SH colour is not rotated: exact for the DC term.)"""
    if rotation is None and translation is None:
        return gaussians
    means, quats = gaussians.means, gaussians.quats
    if rotation is not None:
        means = means @ rotation.T
        q = matrix_to_quaternion(rotation).expand_as(quats)
        quats = quaternion_multiply(q, quats)
    if translation is not None:
        means = means + translation
    return GaussianSet(means=means, quats=quats, scales=gaussians.scales,
                       opacities=gaussians.opacities, sh=gaussians.sh)


def union(sets: list[GaussianSet]) -> GaussianSet:
    """One set of every seat's Gaussians (SH padded with zeros to the highest degree)."""
    if len(sets) == 1:
        return sets[0]
    bases = max(g.sh.shape[1] for g in sets)
    sh = [g.sh if g.sh.shape[1] == bases else
          torch.nn.functional.pad(g.sh, (0, 0, 0, bases - g.sh.shape[1])) for g in sets]
    return GaussianSet(means=torch.cat([g.means for g in sets]),
                       quats=torch.cat([g.quats for g in sets]),
                       scales=torch.cat([g.scales for g in sets]),
                       opacities=torch.cat([g.opacities for g in sets]), sh=torch.cat(sh))
