"""Procedural materials with large-scale structure, as ground truth for every stage.

A material is a set of per-texel fields defined on the whole integer plane (so any window, with
any halo, can be computed on its own):

- ``height``: surface height in pixels, within ``[0, relief]``;
- ``albedo``: diffuse reflectance, linear RGB in ``[0, 1]``;
- ``roughness``: GGX ``alpha`` of the specular lobe (small is glossy);
- ``specular``: Fresnel reflectance at normal incidence ``F0``.

Gloss and colour are correlated with the structure (latewood is darker and glossier, leather
creases are dark and rough, tile glaze is glossy and the grout is not), so directions really
differ. ``scale`` is each material's characteristic length in pixels; for ``tiles`` it is the
exact period of the pattern. ``relief`` is proportional to ``scale``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy  # submodules load on first use, not at every btf command (test_layout: HEAVY)

from tasks.noise import fbm, gradient_noise, smoothstep, worley


@dataclass(frozen=True)
class Fields:
    """Per-texel material fields of a window (see the module docstring)."""

    height: np.ndarray
    albedo: np.ndarray
    roughness: np.ndarray
    specular: np.ndarray

    def crop(self, y: slice, x: slice) -> Fields:
        """The fields of a sub-window."""
        return Fields(self.height[y, x], self.albedo[y, x], self.roughness[y, x],
                      self.specular[y, x])

    def pack(self) -> np.ndarray:
        """All fields as one float32 array ``(..., 6)``: height, albedo RGB, roughness, F0."""
        return np.concatenate([self.height[..., None], self.albedo, self.roughness[..., None],
                               self.specular[..., None]], axis=-1)

    @staticmethod
    def unpack(packed: np.ndarray) -> Fields:
        """Inverse of :meth:`pack`."""
        return Fields(packed[..., 0], packed[..., 1:4], packed[..., 4], packed[..., 5])

    @staticmethod
    def stack(height, albedo, roughness, specular) -> Fields:
        """Build fields as float32 arrays of one shape (albedo with a trailing RGB axis)."""
        shape = np.shape(height)
        return Fields(
            np.asarray(height, np.float32),
            np.asarray(np.broadcast_to(albedo, (*shape, 3)), np.float32),
            np.asarray(np.broadcast_to(roughness, shape), np.float32),
            np.asarray(np.broadcast_to(specular, shape), np.float32),
        )


def _lerp(a, b, t):
    """Blend colours ``a`` and ``b`` (trailing RGB axis) by the scalar field ``t``."""
    return a + (b - a) * np.asarray(t)[..., None]


def _palette(seed: int, base: tuple[float, ...], spread: float) -> np.ndarray:
    """A colour near ``base`` whose brightness and tint vary with the seed."""
    rng = np.random.default_rng([seed, 0x5EED])
    tint = 1.0 + spread * (rng.random(3) - 0.5)
    return np.clip(np.asarray(base) * tint * (0.8 + 0.4 * rng.random()), 0.005, 0.95)


def _wood(y, x, *, seed, scale, relief):
    # Growth rings: bands across x, warped by slow noise like a plank cut from a curved log.
    warp = fbm(x / (6 * scale), y / (10 * scale), seed=seed, octaves=3)
    wobble = gradient_noise(x / (2 * scale), y / (12 * scale), seed=seed + 1)
    phase = (x + 2.5 * scale * warp + 0.6 * scale * wobble + 0.08 * y) / scale
    ring = phase - np.floor(phase)
    late = smoothstep(0.55, 0.8, ring) * (1.0 - smoothstep(0.93, 1.0, ring))
    # Grain: fine pores stretched along the fibres (y).
    grain = fbm(x / (0.12 * scale), y / (3.0 * scale), seed=seed + 2, octaves=3)
    pores = smoothstep(0.3, 0.65, grain)
    early_rgb = _palette(seed, (0.55, 0.33, 0.17), 0.15)
    late_rgb = early_rgb * np.array([0.55, 0.47, 0.42])
    albedo = _lerp(early_rgb, late_rgb, late) * (1.0 - 0.35 * pores)[..., None]
    # Latewood is harder, so it stands proud of the worn earlywood; pores are grooves.
    height = relief * np.clip(0.55 + 0.35 * late - 0.45 * pores + 0.1 * grain, 0.0, 1.0)
    roughness = 0.35 - 0.17 * late + 0.3 * pores
    return Fields.stack(height, albedo, roughness, 0.04)


def _leather(y, x, *, seed, scale, relief):
    wu = 0.35 * fbm(x / (3 * scale), y / (3 * scale), seed=seed, octaves=2)
    wv = 0.35 * fbm(x / (3 * scale), y / (3 * scale), seed=seed + 1, octaves=2)
    f1, f2, cell = worley(x / scale + wu, y / scale + wv, seed=seed + 2)
    groove = 1.0 - smoothstep(0.0, 0.22, f2 - f1)
    dome = 1.0 - np.clip(f1 / 0.8, 0.0, 1.0) ** 2
    # Long creases where the hide was folded: ridges of a slow noise.
    ridge = 1.0 - np.abs(fbm(x / (7 * scale), y / (5 * scale), seed=seed + 3, octaves=3))
    crease = smoothstep(0.88, 0.98, ridge)
    fine = gradient_noise(x / (0.35 * scale), y / (0.35 * scale), seed=seed + 4)
    height = relief * np.clip(
        0.35 + 0.55 * dome * (1.0 - groove) - 0.3 * crease + 0.04 * fine, 0.0, 1.0
    )
    base = _palette(seed, (0.30, 0.13, 0.06), 0.4)
    shade = (0.85 + 0.3 * cell) * (1.0 - 0.45 * groove - 0.35 * crease)
    albedo = base * shade[..., None]
    roughness = 0.25 + 0.35 * groove + 0.2 * (1.0 - dome) + 0.05 * crease
    return Fields.stack(height, albedo, roughness, 0.045)


def _fabric(y, x, *, seed, scale, relief):
    # Plain weave with a thread pitch of half the repeat. The threads wander slowly, so the
    # pattern is near-periodic, as real cloth is.
    pitch = scale / 2.0
    xs = x + 0.3 * pitch * fbm(x / (8 * scale), y / (8 * scale), seed=seed, octaves=2)
    ys = y + 0.3 * pitch * fbm(x / (8 * scale), y / (8 * scale), seed=seed + 1, octaves=2)
    cu, cv = xs / pitch, ys / pitch
    iu, iv = np.floor(cu), np.floor(cv)
    u, v = cu - iu, cv - iv
    warp_on_top = (iu + iv) % 2 == 0
    across_warp = np.sqrt(np.clip(1.0 - ((2 * u - 1) / 0.9) ** 2, 0.0, 1.0))
    across_weft = np.sqrt(np.clip(1.0 - ((2 * v - 1) / 0.9) ** 2, 0.0, 1.0))
    bulge_warp = np.where(warp_on_top, 0.55 + 0.45 * 4 * v * (1 - v), 0.45)
    bulge_weft = np.where(warp_on_top, 0.45, 0.55 + 0.45 * 4 * u * (1 - u))
    h_warp, h_weft = across_warp * bulge_warp, across_weft * bulge_weft
    is_warp = h_warp >= h_weft
    fib_warp = fbm(x / (0.15 * pitch), y / (2 * pitch), seed=seed + 2, octaves=2)
    fib_weft = fbm(x / (2 * pitch), y / (0.15 * pitch), seed=seed + 3, octaves=2)
    fibres = np.where(is_warp, fib_warp, fib_weft)
    height_n = np.clip(np.maximum(h_warp, h_weft) + 0.06 * fibres, 0.0, 1.0)
    warp_rgb = _palette(seed, (0.12, 0.20, 0.45), 0.5)
    weft_rgb = _palette(seed + 1, (0.60, 0.55, 0.45), 0.3)
    colour = np.where(is_warp[..., None], warp_rgb, weft_rgb)
    albedo = colour * ((0.8 + 0.25 * fibres) * (0.45 + 0.55 * height_n))[..., None]
    roughness = 0.55 + 0.15 * fibres
    return Fields.stack(relief * height_n, albedo, roughness, 0.04)


def _tiles(y, x, *, seed, scale, relief):
    # Everything is a function of the coordinates modulo the period, and the noise lattice wraps
    # with the period, so the texture (and every rendered layer) repeats exactly.
    period = round(scale)
    yw, xw = y % period, x % period
    grout = max(1.0, period / 24.0)
    bevel = max(1.0, period / 32.0)
    # distance from the texel centre to the nearest grout line (the period's edges)
    edge = np.minimum(np.minimum(xw + 0.5, period - xw - 0.5),
                      np.minimum(yw + 0.5, period - yw - 0.5))
    body = smoothstep(grout, grout + bevel, edge)
    cells = 8
    u, v = (xw + 0.5) * cells / period, (yw + 0.5) * cells / period
    glaze = fbm(u, v, seed=seed, octaves=3, period=cells)
    sand = fbm(4 * u, 4 * v, seed=seed + 1, octaves=2, period=4 * cells)
    height = relief * np.clip(0.15 + 0.8 * body + 0.04 * body * glaze + 0.03 * sand, 0.0, 1.0)
    glaze_rgb = _palette(seed, (0.55, 0.22, 0.12), 0.6)
    grout_rgb = _palette(seed + 1, (0.45, 0.43, 0.40), 0.1)
    albedo = _lerp(grout_rgb * (0.9 + 0.1 * sand)[..., None],
                   glaze_rgb * (0.92 + 0.12 * glaze)[..., None], body)
    roughness = 0.8 + (0.06 + 0.03 * glaze - 0.8) * body
    specular = 0.03 + 0.03 * body
    return Fields.stack(height, albedo, roughness, specular)


_MINERALS = np.array(  # linear RGB albedo and GGX alpha: quartz, feldspar, mica, hornblende
    [[0.62, 0.62, 0.60, 0.30], [0.66, 0.45, 0.38, 0.45], [0.05, 0.05, 0.06, 0.12],
     [0.16, 0.17, 0.15, 0.50]]
)


def _stone(y, x, *, seed, scale, relief):
    wu = 0.3 * fbm(x / (2 * scale), y / (2 * scale), seed=seed, octaves=2)
    wv = 0.3 * fbm(x / (2 * scale), y / (2 * scale), seed=seed + 1, octaves=2)
    f1, f2, cell = worley(x / scale + wu, y / scale + wv, seed=seed + 2)
    kind = np.searchsorted(np.cumsum([0.35, 0.35, 0.15, 0.15]), cell, side="right")
    mineral = _MINERALS[np.minimum(kind, 3)]
    crack = 1.0 - smoothstep(0.0, 0.08, f2 - f1)
    big = fbm(x / (4 * scale), y / (4 * scale), seed=seed + 3, octaves=5)
    fine = fbm(x / (0.3 * scale), y / (0.3 * scale), seed=seed + 4, octaves=2)
    height = relief * np.clip(0.5 + 0.35 * big + 0.08 * fine - 0.25 * crack, 0.0, 1.0)
    tint = _palette(seed, (1.0, 1.0, 1.0), 0.15)
    albedo = mineral[..., :3] * tint * ((0.85 + 0.2 * fine) * (1.0 - 0.4 * crack))[..., None]
    roughness = mineral[..., 3] + 0.08 * fine + 0.2 * crack
    return Fields.stack(height, np.clip(albedo, 0.0, 1.0), roughness, 0.045)


@dataclass(frozen=True)
class MaterialKind:
    """A procedural material: its field function, default scale and relief per unit scale."""

    function: Callable[..., Fields]
    default_scale: float
    relief_per_scale: float
    description: str


MATERIALS: dict[str, MaterialKind] = {
    "wood": MaterialKind(_wood, 20.0, 0.15, "warped growth rings and grain"),
    "leather": MaterialKind(_leather, 14.0, 0.4, "cells, grooves and creases"),
    "fabric": MaterialKind(_fabric, 16.0, 0.3, "a woven, near-periodic pattern"),
    "tiles": MaterialKind(_tiles, 64.0, 0.08, "a strictly periodic grid with grout"),
    "stone": MaterialKind(_stone, 20.0, 0.3, "irregular, stochastic mineral grains"),
}


@dataclass(frozen=True)
class Material:
    """A procedural material instance: kind, seed and scale (pixels).

    ``fields(y0, x0, ny, nx)`` evaluates any window of the infinite texture; windows overlap
    consistently, which is what lets tiles be rendered independently with halos.
    """

    name: str
    seed: int = 0
    scale: float | None = None

    def __post_init__(self):
        if self.name not in MATERIALS:
            raise ValueError(f"unknown material {self.name!r}; choose from {sorted(MATERIALS)}")
        if self.scale is not None and not self.scale >= 2:
            raise ValueError(f"material scale must be at least 2 pixels, got {self.scale}")

    @property
    def kind(self) -> MaterialKind:
        """The material's kind."""
        return MATERIALS[self.name]

    @property
    def effective_scale(self) -> float:
        """The characteristic length in pixels (the default of the kind if unset)."""
        return float(self.kind.default_scale if self.scale is None else self.scale)

    @property
    def relief(self) -> float:
        """Height range in pixels: ``height`` lies in ``[0, relief]``."""
        scale = round(self.effective_scale) if self.name == "tiles" else self.effective_scale
        return self.kind.relief_per_scale * scale

    def fields(self, y0: int, x0: int, ny: int, nx: int) -> Fields:
        """Fields of the window of ``ny x nx`` texels whose first texel is ``(y0, x0)``."""
        y = np.arange(y0, y0 + ny, dtype=np.int64)[:, None]
        x = np.arange(x0, x0 + nx, dtype=np.int64)[None, :]
        if self.name == "tiles":  # works on integer coordinates (exact periodicity)
            yy, xx = y, x
        else:  # texel centres
            yy, xx = y + 0.5, x + 0.5
        return self.kind.function(
            yy, xx, seed=self.seed, scale=self.effective_scale, relief=self.relief
        )


PHOTO_SCALE = 20.0  # default characteristic length of a photo material (pixels)
PHOTO_RELIEF_PER_SCALE = 0.2


def photo_relief(scale: float | None) -> float:
    """Relief (px) given to a photo material of characteristic length ``scale``."""
    return PHOTO_RELIEF_PER_SCALE * (PHOTO_SCALE if scale is None else scale)


BUMP_RELIEF_PER_SCALE = 0.3
HEIGHTS = ("photo", "bumps")


def bump_relief(scale: float | None) -> float:
    """Relief (px) of :func:`bump_height` at characteristic length ``scale``."""
    return BUMP_RELIEF_PER_SCALE * (PHOTO_SCALE if scale is None else scale)


def bump_height(ny: int, nx: int, *, seed: int, scale: float, relief: float) -> np.ndarray:
    """Smooth bumps of two scales, independent of any photo: a height field in ``[0, relief]``.

    Gradient noise at ``scale`` and at a third of it, each shaped by a smoothstep into rounded
    domes and hollows (three quarters of the relief from the large bumps). Not periodic: the
    lattice has no period, so no window repeats at any scale a sample could hold.
    """
    y = np.arange(ny, dtype=np.float64)[:, None] + 0.5
    x = np.arange(nx, dtype=np.float64)[None, :] + 0.5
    large = gradient_noise(x / scale, y / scale, seed=seed)
    small = gradient_noise(3.0 * x / scale, 3.0 * y / scale, seed=seed + 1)
    shape = 0.75 * smoothstep(-0.6, 0.6, large) + 0.25 * smoothstep(-0.6, 0.6, small)
    return (relief * shape).astype(np.float32)


def image_fields(image: np.ndarray, *, relief: float,
                 height: np.ndarray | None = None) -> Fields:
    """Fields from a photograph: its colour as albedo, its band-passed lightness as height.

    Dark detail is taken to be low (crevices), as is usual for photos of rough surfaces;
    brighter texels are made slightly glossier. ``image`` is linear, ``(ny, nx)`` or
    ``(ny, nx, channels)``; a single channel gives a grey albedo. ``height``: a relief of
    its own (e.g. :func:`bump_height`) instead of the photo's lightness.
    """
    image = np.asarray(image, np.float32)
    rgb = np.repeat(image[..., None], 3, axis=-1) if image.ndim == 2 else image[..., :3]
    if rgb.shape[-1] == 1:
        rgb = np.repeat(rgb, 3, axis=-1)
    elif rgb.shape[-1] == 2:
        raise ValueError("an albedo image needs 1 or at least 3 channels, got 2")
    albedo = np.clip(rgb, 0.0, 1.0)
    lightness = albedo @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    if height is None:
        blur = scipy.ndimage.gaussian_filter
        detail = blur(lightness, 1.0) - blur(lightness, 12.0)
        lo, hi = np.percentile(detail, [1.0, 99.0])
        height = relief * np.clip((detail - lo) / max(hi - lo, 1e-6), 0.0, 1.0)
    elif height.shape != lightness.shape:
        raise ValueError(f"a height of shape {height.shape} for an image of {lightness.shape}")
    level = lightness / max(float(lightness.max()), 1e-6)
    return Fields.stack(height, albedo, 0.55 - 0.3 * level, 0.04)
