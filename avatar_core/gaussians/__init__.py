"""Gaussians bound to mesh triangles: frames, the avatar, packages, .ply export."""
