"""Procedural surface appearance of the synthetic actor: solid textures and studio lighting.

Every texture is a *solid* texture: a function of the surface point's canonical position (the
rest pose of the actor's own shape, metres), so a pattern sticks to the body however it moves.
Textures are evaluated per rendered sample, vectorised in float32, and only for the material
groups that cover the sample. Base colours come from the identity palette; patterns keep their
features at about a centimetre or more so a Gaussian avatar can reproduce them.

Noise is a sum of sine waves with random directions (`wave_bank`): smooth, isotropic enough at
these amplitudes, exactly reproducible, and cheap with numpy's SIMD float32 `sin`.

Lighting is fixed in the world (a studio): hemispheric ambient, a soft key light, a fill and a
back light, diffuse Lambert only, so every camera sees the same colour at a surface point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .humanoid import MATERIALS

__all__ = ["GROUPS", "MATERIAL_GROUP", "Appearance", "FaceLayout", "irradiance",
           "make_appearance", "shade_albedo", "wave_bank", "waves"]

# Texture groups: lips and brows are drawn procedurally inside "skin", the eye's sclera, iris
# and pupil procedurally inside "eye"; their coarse vertex materials would look blocky.
GROUPS = ("skin", "hair", "eye", "mouth", "teeth", "shirt", "trousers", "shoes")
_G = {g: i for i, g in enumerate(GROUPS)}
MATERIAL_GROUP = tuple(_G[g] for g in (
    "skin", "hair", "skin", "skin", "eye", "eye", "eye", "mouth", "teeth", "shirt", "trousers",
    "shoes"))  # aligned with humanoid.MATERIALS

# World-space studio lights: (direction toward the light, intensity). The subject faces +z and
# its left is +x; the key comes from front-left and above, the fill from front-right, a back
# light keeps the rear cameras' views from going flat.
LIGHTS = (((0.45, 0.60, 0.66), 0.62), ((-0.75, 0.20, 0.50), 0.26), ((0.10, 0.50, -0.86), 0.30))
AMBIENT, SKY = 0.30, 0.07  # ambient + SKY * n_y: brighter from above
SHIRT_STYLES = ("plaid", "stripes", "gingham")
_FIXED = {"eye_white": (0.92, 0.90, 0.87), "pupil": (0.02, 0.02, 0.025),
          "mouth": (0.42, 0.12, 0.13), "teeth": (0.90, 0.87, 0.80), "shoes": (0.11, 0.09, 0.08),
          "sole": (0.78, 0.75, 0.70), "belt": (0.13, 0.08, 0.05), "buckle": (0.63, 0.58, 0.44),
          "mole": (0.30, 0.18, 0.12), "accent": (0.92, 0.88, 0.76)}  # fmt: skip


@dataclass(frozen=True)
class FaceLayout:
    """Where the face features sit on the canonical surface (from the rest mesh)."""

    eyes: np.ndarray  # [2, 3] eyeball centres (left +x, right -x)
    pupil_cos: float  # cosine of the pupil's angular radius about the eye's +z axis
    iris_cos: float
    brow: np.ndarray  # [3] brow centre line y = c0 + c1 |x| + c2 |x|^2
    brow_x: tuple[float, float]  # |x| range of a brow
    mouth: np.ndarray  # [4] lip line y, half width, upper and lower lip height
    front_z: float  # face features only where z > front_z (not on the back of the head)
    hair_center: np.ndarray  # [3] the hair direction field radiates from here
    scale: float  # head size relative to the design head (eye distance / 65 mm)


@dataclass(frozen=True)
class Appearance:
    """Everything the textures of one identity need (arrays are float32 where per sample)."""

    colors: dict[str, np.ndarray]  # name -> [3, 1]
    shirt_style: str
    face: FaceLayout
    moles: np.ndarray  # [K, 4] canonical centre and radius (sigma)
    shoulder: np.ndarray  # [3] |x|, y, z of the shoulder joint: the sleeve seam and axis
    waist_y: float  # top of the trousers (the belt sits just below)
    sole_y: float  # shoe soles below this height
    skin_noise: np.ndarray  # wave banks, see `wave_bank`
    red_noise: np.ndarray
    hair_warp: np.ndarray
    hair_clump: np.ndarray
    cloth_noise: np.ndarray


# ------------------------------------------------------------------------------------ noise
# Per-sample arrays are channel-first ([3, N] points and colours, [N] scalars) so that every
# numpy operation runs over long contiguous float32 rows.


def wave_bank(rng: np.random.Generator, wavelengths, amplitudes, per_octave: int = 2
              ) -> np.ndarray:
    """Random sine waves [M, 5]: wave vector (2 pi / wavelength along a random direction),
    phase and amplitude; each octave's sum has about the given standard deviation."""
    rows = []
    for lam, amp in zip(wavelengths, amplitudes, strict=True):
        d = rng.normal(size=(per_octave, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        phase = rng.uniform(0.0, 2.0 * np.pi, per_octave)
        a = np.full(per_octave, amp / np.sqrt(per_octave / 2.0))
        rows.append(np.column_stack([d * (2.0 * np.pi / lam), phase, a]))
    return np.concatenate(rows).astype(np.float32)


def waves(bank: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Sum of the bank's sine waves at points p [3, N] (float32) -> [N]."""
    out = np.zeros(p.shape[1], dtype=np.float32)
    for kx, ky, kz, phase, amp in bank:
        out += amp * np.sin(p[0] * kx + p[1] * ky + p[2] * kz + phase)
    return out


def _smooth(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    """Smoothstep from e0 to e1 (either order), float32."""
    t = np.clip((x - np.float32(e0)) * np.float32(1.0 / (e1 - e0)), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _mix(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """a + (b - a) t for colours [3, N] or [3, 1] and weights [N]."""
    return a + (b - a) * t


def _band(u: np.ndarray, period: float, width: float, offset: float = 0.0) -> np.ndarray:
    """1 inside stripes of `width` repeating every `period` along u, with soft 4 mm edges
    (a splat-friendly transition, still a crisp line at capture resolution)."""
    f = (u - np.float32(offset)) * np.float32(1.0 / period)
    d = np.abs(f - np.floor(f) - 0.5) * np.float32(period)  # distance to the stripe centre
    return _smooth(width / 2 + 0.002, width / 2 - 0.002, d)


# ---------------------------------------------------------------------------- construction


def _face_layout(v: np.ndarray, materials: np.ndarray, joints: np.ndarray) -> FaceLayout:
    """Feature geometry fitted to the rest mesh's eye, brow and lip vertices."""
    m = {name: materials == i for i, name in enumerate(MATERIALS)}
    eyes = joints[[23, 24]]  # left_eye_smplhf, right_eye_smplhf

    def cos_about_eye(mask: np.ndarray) -> np.ndarray:
        d = v[mask & (v[:, 0] > 0)] - eyes[0]
        return d[:, 2] / np.linalg.norm(d, axis=1)

    pupil, iris, white = (cos_about_eye(m[k]) for k in ("pupil", "iris", "eye_white"))
    brow = v[m["eyebrow"] & (v[:, 0] > 0)]
    ax = brow[:, 0]
    coeff = np.polynomial.polynomial.polyfit(ax, brow[:, 1], 2)
    lips = v[m["lips"]]
    scale = float(np.linalg.norm(eyes[0] - eyes[1]) / 0.065)
    half_w = float(np.abs(lips[:, 0]).max())
    mouth = np.array([np.median(lips[:, 1]), half_w, 0.34 * half_w, 0.38 * half_w])
    return FaceLayout(
        eyes=eyes.astype(np.float32),
        pupil_cos=float(pupil.min() + iris.max()) / 2,  # halfway between the vertex rings
        iris_cos=float(iris.min() + white.max()) / 2,
        brow=coeff.astype(np.float32), brow_x=(float(ax.min()), float(ax.max())),
        mouth=mouth.astype(np.float32), front_z=float(eyes[0, 2] - 0.02 * scale),
        hair_center=(joints[15] + scale * np.array([0.0, 0.075, 0.0])).astype(np.float32),
        scale=scale)


def _moles(v: np.ndarray, materials: np.ndarray, rng: np.random.Generator, count: int
           ) -> np.ndarray:
    """A few moles and freckles on the skin above the waist (face, neck, arms, hands)."""
    skin = np.flatnonzero((materials == MATERIALS.index("skin")) & (v[:, 1] > 0.3))
    centres = v[rng.choice(skin, size=count, replace=False)]
    radius = rng.uniform(0.0018, 0.0035, size=count)
    return np.column_stack([centres, radius]).astype(np.float32)


def make_appearance(palette: dict, style: int, rest_vertices: np.ndarray,
                    materials: np.ndarray, joints: np.ndarray, seed: int) -> Appearance:
    """The appearance of one identity. palette: `model_files.PALETTES` entry; style: picks
    the shirt pattern; rest_vertices [V, 3] canonical; materials [V] into MATERIALS;
    joints [55, 3] canonical; seed: noise phases and mole placement."""
    rng = np.random.default_rng([seed, 2718])
    colors = {k: np.asarray(c, dtype=np.float32).reshape(3, 1) for k, c in _FIXED.items()}
    for k in ("skin", "hair", "iris", "shirt", "lips", "trousers"):
        colors[k] = np.asarray(palette[k], dtype=np.float32).reshape(3, 1)
    v = np.asarray(rest_vertices, dtype=np.float64)
    shirt = v[materials == MATERIALS.index("shirt")]
    trousers = v[materials == MATERIALS.index("trousers")]
    shoes = v[materials == MATERIALS.index("shoes")]
    return Appearance(
        colors=colors, shirt_style=SHIRT_STYLES[style % len(SHIRT_STYLES)],
        face=_face_layout(v, materials, joints),
        moles=_moles(v, materials, rng, 10),
        shoulder=np.array([abs(joints[16, 0]), joints[16, 1], joints[16, 2]]),
        waist_y=float(trousers[:, 1].max() + shirt[:, 1].min()) / 2,
        sole_y=float(shoes[:, 1].min() + 0.018),
        skin_noise=wave_bank(rng, (0.09, 0.035, 0.014), (0.5, 0.3, 0.2)),
        red_noise=wave_bank(rng, (0.06, 0.025), (0.6, 0.4)),
        hair_warp=wave_bank(rng, (0.07, 0.03), (1.2, 0.5)),
        hair_clump=wave_bank(rng, (0.045, 0.02), (0.6, 0.4)),
        cloth_noise=wave_bank(rng, (0.12, 0.011), (0.7, 0.3)))


# ---------------------------------------------------------------------------------- textures
# Each texture maps canonical points [3, n] to albedo [3, n].


def _skin(a: Appearance, p: np.ndarray) -> np.ndarray:
    """Skin with blotches, redness and moles; cheeks, lips and brows painted on the face."""
    c, f = a.colors, a.face
    tone = 1.0 + 0.05 * waves(a.skin_noise, p)
    red = 0.03 + 0.03 * waves(a.red_noise, p)
    out = c["skin"] * tone * (1.0 + red * np.float32([[0.5], [-0.4], [-0.4]]))
    x, y, z = p
    for cx, cy, cz, r in a.moles:
        d2 = (x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2
        near = np.flatnonzero(d2 < np.float32((4 * r) ** 2))
        if len(near):
            w = 0.75 * np.exp(d2[near] * np.float32(-1 / (2 * r * r)))
            out[:, near] = _mix(out[:, near], c["mole"], w)
    eye_y = float(f.eyes[0, 1])
    face = np.flatnonzero((z > f.front_z - 0.01) & (y > eye_y - 0.11 * f.scale)
                          & (y < eye_y + 0.06 * f.scale))
    if len(face):
        out[:, face] = _face_paint(a, p[:, face], out[:, face])
    return out


def _face_paint(a: Appearance, p: np.ndarray, skin: np.ndarray) -> np.ndarray:
    """Blushed cheeks, lips and brows over the skin of the face's front."""
    f = a.face
    x, y, z = p
    front = _smooth(f.front_z - 0.01, f.front_z, z)
    cheek_d2 = (np.abs(x) - 0.047 * f.scale) ** 2 + (y - (f.eyes[0, 1] - 0.03 * f.scale)) ** 2
    blush = 0.05 * np.exp(cheek_d2 * np.float32(-1 / (2 * 0.016**2))) * front
    out = skin * (1.0 + blush * np.float32([[0.5], [-0.4], [-0.4]]))
    out = _mix(out, _lips(a, p, out), _lip_mask(f, x, y) * front)
    return _mix(out, a.colors["hair"] * 0.85, 0.9 * _brow_mask(f, x, y) * front)


def _lip_mask(f: FaceLayout, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    y0, w, hu, hl = (float(t) for t in f.mouth)
    ax = np.abs(x)
    lat = np.clip(1.0 - (ax * np.float32(1 / w)) ** 2, 0.0, 1.0)
    bow = 1.0 - 0.22 * np.exp(-(ax * np.float32(1 / (0.0045 * f.scale))) ** 2)  # cupid's bow
    dy = y - np.float32(y0)
    h = np.where(dy > 0, hu * np.sqrt(lat) * bow, hl * np.sqrt(lat) * np.sqrt(np.sqrt(lat)))
    return _smooth(0.0008, -0.0008, np.abs(dy) - h) * _smooth(w + 0.001, w - 0.002, ax)


def _lips(a: Appearance, p: np.ndarray, skin: np.ndarray) -> np.ndarray:
    """Lip colour, darker along the lip line and toward the corners."""
    y0, w = float(a.face.mouth[0]), float(a.face.mouth[1])
    line = np.exp(-((p[1] - np.float32(y0)) * np.float32(1 / 0.0016)) ** 2)
    corner = _smooth(0.5 * w, w, np.abs(p[0]))
    return 0.25 * skin + 0.75 * a.colors["lips"] * (1.0 - 0.35 * line - 0.12 * corner)


def _brow_mask(f: FaceLayout, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    ax = np.abs(x)
    x0, x1 = f.brow_x
    c0, c1, c2 = (np.float32(t) for t in f.brow)
    t = np.clip((ax - np.float32(x0)) * np.float32(1.0 / (x1 - x0)), 0.0, 1.0)
    half = np.float32(f.scale) * (0.0045 - 0.0025 * t)  # thick inner end, thin tail
    d = np.abs(y - (c0 + c1 * ax + c2 * ax * ax)) - half
    return _smooth(0.0012, -0.0006, d) * _smooth(x0 - 0.004, x0 + 0.001, ax) * _smooth(
        x1 + 0.004, x1 - 0.001, ax)


def _hair(a: Appearance, p: np.ndarray) -> np.ndarray:
    """Strand-like streaks radiating from the crown, clumped and wavy."""
    d = p - a.face.hair_center[:, None]
    # Azimuth about a crown axis tilted backward: strands run from the whorl down and out.
    u = d[0]
    w = 0.8 * d[1] - 0.6 * d[2]
    v = 0.6 * d[1] + 0.8 * d[2]
    phi = np.arctan2(u, v)
    horizontal = np.sqrt(u * u + v * v)
    fade = _smooth(0.15, 0.45, horizontal / np.sqrt(horizontal * horizontal + w * w + 1e-12))
    warp = waves(a.hair_warp, p)
    s = (0.6 * np.sin(40.0 * phi + warp) + 0.4 * np.sin(64.0 * phi + 1.7 * warp + 1.3)) * fade
    gain = 0.84 + 0.2 * s + 0.12 * waves(a.hair_clump, p)
    return a.colors["hair"] * gain + np.float32([[0.03], [0.026], [0.021]]) * (s + 1.0)


def _eye(a: Appearance, p: np.ndarray) -> np.ndarray:
    """Sclera, iris with radial fibres and a dark limbal ring, pupil."""
    f, c = a.face, a.colors
    d = p - np.where(p[0] > 0, f.eyes[0][:, None], f.eyes[1][:, None])
    cos = d[2] / (np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) + 1e-12)
    e = 0.004
    iris = _smooth(f.iris_cos - e, f.iris_cos + e, cos)
    pupil = _smooth(f.pupil_cos - e, f.pupil_cos + e, cos)
    fibres = np.sin(9.0 * np.arctan2(d[1], d[0]))
    limbal = _smooth(f.iris_cos + 6 * e, f.iris_cos, cos)
    inner = _smooth(f.pupil_cos - 8 * e, f.pupil_cos, cos)
    gain = (0.85 + 0.12 * fibres) * (1.0 - 0.5 * limbal) * (1.0 + 0.3 * inner)
    white = c["eye_white"] * (1.0 - 0.1 * _smooth(0.75, 0.3, cos))
    return _mix(_mix(white, c["iris"] * gain, iris), c["pupil"], pupil)


def _cloth_coords(a: Appearance, p: np.ndarray, period: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Pattern coordinates (across, along) in metres, like a sewn shirt's: around and up the
    torso; around and along each sleeve past the shoulder seam. The circumferences are whole
    multiples of `period`, so a pattern closes around the body without a seam."""
    x, y, z = p
    sx, sy, sz = (float(t) for t in a.shoulder)
    ax = np.abs(x)
    # Past the seam and near the arm's axis; the torso's flanks below the arm stay torso.
    sleeve = (ax > sx) & ((y - sy) ** 2 + (z - sz) ** 2 < np.float32(0.075**2))

    def around(s: np.ndarray, t: np.ndarray, radius: float) -> np.ndarray:
        turns = max(round(2 * np.pi * radius / period), 1)
        return np.arctan2(s, t) * np.float32(turns * period / (2 * np.pi))

    across = np.where(sleeve, around(z - sz, y - sy, 0.05), around(x, z - sz, 0.15))
    along = np.where(sleeve, ax - sx, y)
    return across, along


def _shirt(a: Appearance, p: np.ndarray) -> np.ndarray:
    """Plaid, horizontal stripes (rings on the sleeves) or gingham, with a fine weave."""
    base = a.colors["shirt"] * (1.0 + 0.05 * waves(a.cloth_noise, p))
    accent = a.colors["accent"]
    if a.shirt_style == "stripes":
        _, along = _cloth_coords(a, p, 0.04)
        return _mix(base, accent, 0.85 * _band(along, 0.04, 0.016))
    if a.shirt_style == "gingham":
        u, v = _cloth_coords(a, p, 0.026)
        bu, bv = _band(u, 0.026, 0.013), _band(v, 0.026, 0.013)
        return base * (1.0 - 0.22 * (bu + bv)) + 0.18 * (1.0 - np.minimum(bu + bv, 1.0))
    u, v = _cloth_coords(a, p, 0.08)
    dark = _band(u, 0.08, 0.024) + _band(v, 0.08, 0.024)
    line = np.maximum(_band(u, 0.08, 0.009, 0.04), _band(v, 0.08, 0.009, 0.04))
    return _mix(base * (1.0 - 0.28 * dark), accent, 0.6 * line)


def _trousers(a: Appearance, p: np.ndarray) -> np.ndarray:
    """Twill with a belt and buckle at the waist."""
    x, y, z = p
    twill = np.sin((y + 0.7 * x + 0.7 * z) * np.float32(2 * np.pi / 0.012))
    out = a.colors["trousers"] * (1.0 + 0.04 * twill + 0.07 * waves(a.cloth_noise, p))
    top = np.float32(a.waist_y)
    belt = _smooth(top - 0.040, top - 0.037, y) * _smooth(top - 0.004, top - 0.007, y)
    out = _mix(out, a.colors["belt"], belt)
    buckle = belt * _smooth(0.026, 0.022, np.abs(x)) * _smooth(0.0, 0.03, z)
    return _mix(out, a.colors["buckle"], buckle)


def _shoes(a: Appearance, p: np.ndarray) -> np.ndarray:
    sole = _smooth(a.sole_y + 0.002, a.sole_y - 0.002, p[1])
    return _mix(a.colors["shoes"], a.colors["sole"], sole)


def _mouth(a: Appearance, p: np.ndarray) -> np.ndarray:
    return a.colors["mouth"] * (1.0 + 0.05 * waves(a.skin_noise, p))


def _teeth(a: Appearance, p: np.ndarray) -> np.ndarray:
    return a.colors["teeth"] * (1.0 + 0.03 * waves(a.skin_noise, p))


_TEXTURES = (_skin, _hair, _eye, _mouth, _teeth, _shirt, _trousers, _shoes)  # GROUPS order


def albedo(a: Appearance, p: np.ndarray, group: np.ndarray, weights: np.ndarray
           ) -> np.ndarray:
    """Albedo [3, N] at canonical points p [3, N] (float32). group [N], sorted: each
    sample's only texture group, or -1 for the first M samples, which blend the groups with
    weights [len(GROUPS), M] (columns sum to 1). Each texture runs only where it is needed,
    on contiguous slices."""
    bounds = np.searchsorted(group, np.arange(len(_TEXTURES) + 1))
    out = np.zeros(p.shape, dtype=np.float32)
    for g, texture in enumerate(_TEXTURES):
        lo, hi = bounds[g], bounds[g + 1]
        if hi > lo:
            out[:, lo:hi] = texture(a, p[:, lo:hi])
        part = np.flatnonzero(weights[g] > 0.0)
        if len(part):
            out[:, part] += weights[g, part] * texture(a, p[:, part])
    return out


# --------------------------------------------------------------------------------- lighting


def irradiance(normals: np.ndarray) -> np.ndarray:
    """Diffuse light arriving at unit world normals [3, N] -> [N] (view independent)."""
    n = normals.astype(np.float32, copy=False)
    out = AMBIENT + SKY * n[1]
    for direction, power in LIGHTS:
        d = np.asarray(direction, dtype=np.float64)
        dx, dy, dz = (np.float32(t) for t in d / np.linalg.norm(d))
        out += power * np.maximum(n[0] * dx + n[1] * dy + n[2] * dz, 0.0)
    return out


def shade_albedo(albedo_rgb: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Lambert-shaded colour in [0, 1]: albedo [3, N] under the studio lights."""
    return np.clip(albedo_rgb * irradiance(normals), 0.0, 1.0)
