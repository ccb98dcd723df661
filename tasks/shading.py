"""Rendering BTF layers of a height-field material: parallax, cast shadows, diffuse + GGX.

Each layer is what a camera at the view direction records of the sample lit from the light
direction, rectified onto the sample plane (as measured BTFs are):

- the view ray through a texel meets the height field somewhere else (parallax and occlusion,
  :func:`tasks.heightfield.parallax_hits`); that surface point is what the texel shows. Views
  are registered on the plane at half the relief, so structure at that height stays put from
  view to view and higher or lower structure moves with the view, as in rectified BTF data;
- its normal comes from the height gradient; the light reaching it is cut by cast shadows
  (:func:`tasks.heightfield.visibility`);
- reflection is Lambertian diffuse plus a GGX microfacet lobe with Smith masking and Schlick's
  Fresnel term, under a light of irradiance pi at normal incidence, so a white diffuse texel
  facing the light has radiance 1 and glossy highlights exceed 1 (HDR);
- a small ambient term stands in for interreflections, so shadows are dark but not black.
"""

from __future__ import annotations

import hashlib
import math
import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from dataclasses import dataclass

import numpy as np

from tasks.heightfield import (
    bilinear_layers,
    parallax_hits,
    parallax_length,
    shadow_length,
    visibility,
)
from tasks.materials import Fields
from tasks.sampling import direction_vectors


@dataclass(frozen=True)
class ShadingModel:
    """Parameters of the renderer.

    Attributes
    ----------
    relief
        Height range of the material in pixels (heights lie in ``[0, relief]``).
    ambient
        Fraction of the unshadowed diffuse irradiance that reaches every texel.
    penumbra
        Height (px) over which a shadow edge fades.
    max_shadow
        Longest horizontal shadow ray traced (px).
    shadows
        Cast shadows on or off (off only to study their effect).
    """

    relief: float
    ambient: float = 0.04
    penumbra: float = 0.3
    max_shadow: float = 96.0
    shadows: bool = True

    def __post_init__(self):
        if not self.relief > 0:
            raise ValueError(f"relief must be positive, got {self.relief}")
        if not self.penumbra > 0:
            raise ValueError(f"penumbra must be positive, got {self.penumbra}")
        if not self.ambient >= 0:
            raise ValueError(f"ambient must be non-negative, got {self.ambient}")
        if not self.max_shadow > 0:
            raise ValueError(f"max_shadow must be positive, got {self.max_shadow}")

    @property
    def reference(self) -> float:
        """Height of the plane the views are registered on: half the relief."""
        return 0.5 * self.relief

    def halo(self, theta_view_max: float, theta_light_max: float) -> int:
        """Texels of context a tile needs on each side to be rendered exactly."""
        parallax = parallax_length(theta_view_max, relief=self.relief,
                                   reference=self.reference)
        shadow = shadow_length(theta_light_max, relief=self.relief, penumbra=self.penumbra,
                               max_length=self.max_shadow) if self.shadows else 0.0
        return math.ceil(parallax) + math.ceil(shadow) + 4


def normals(height: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit normals ``(nx, ny, nz)`` of a height field by central differences (float32).

    In the store's frame (:mod:`tasks.heightfield`): +y is towards row 0, so ``dh/dy`` is minus
    the gradient along rows and ``ny = +dh/drow`` (before normalisation).
    """
    grow, gx = np.gradient(height)
    inv = 1.0 / np.sqrt(gx * gx + grow * grow + 1.0)
    return (-gx * inv).astype(np.float32), (grow * inv).astype(np.float32), inv.astype(np.float32)


def _smith_g1(cosine: np.ndarray, a2: np.ndarray) -> np.ndarray:
    return 2.0 * cosine / (cosine + np.sqrt(a2 + (1.0 - a2) * cosine * cosine))


@dataclass(frozen=True)
class Surface:
    """What one view sees: the surface attributes under each texel and the view's own terms."""

    normal: tuple[np.ndarray, np.ndarray, np.ndarray]
    albedo: np.ndarray
    a2: np.ndarray  # GGX alpha squared
    f0: np.ndarray
    view: tuple[float, float, float]
    masking: np.ndarray  # Smith G1 of the view over 4 cos(view): shared by every light

    @staticmethod
    def seen_from(normal, albedo, alpha, f0, view) -> Surface:
        """Bundle the attributes seen from the unit vector ``view`` with its view terms."""
        vx, vy, vz = (float(c) for c in view)
        n_x, n_y, n_z = normal
        cos_v = np.maximum(n_x * vx + n_y * vy + n_z * vz, 1e-4)
        a2 = alpha * alpha
        return Surface(normal, albedo, a2, f0, (vx, vy, vz), _smith_g1(cos_v, a2) / (4.0 * cos_v))


def shade(surface: Surface, vis: np.ndarray, light: np.ndarray, *, ambient: float,
          out: np.ndarray | None = None) -> np.ndarray:
    """Radiance ``(..., 3)`` of a :class:`Surface` lit from the unit vector ``light``.

    ``vis`` is the unshadowed fraction of the light at each texel. Returns ``out`` if given.
    The renderer runs :func:`shade_all`, which gives these bits for every light at once; this
    is its readable reference (tests/test_shading.py).
    """
    lx, ly, lz = (float(c) for c in light)
    vx, vy, vz = surface.view
    hx, hy, hz = lx + vx, ly + vy, lz + vz
    norm = math.sqrt(hx * hx + hy * hy + hz * hz)
    hx, hy, hz = hx / norm, hy / norm, hz / norm
    n_x, n_y, n_z = surface.normal
    cos_l = np.maximum(n_x * lx + n_y * ly + n_z * lz, 0.0)
    cos_h = np.maximum(n_x * hx + n_y * hy + n_z * hz, 0.0)
    a2 = surface.a2
    denom = cos_h * cos_h * (a2 - 1.0) + 1.0
    fresnel = surface.f0 + (1.0 - surface.f0) * (1.0 - max(vx * hx + vy * hy + vz * hz, 0.0)) ** 5
    # pi * BRDF * cos_l with pi * D = a2 / denom**2; cos_l of the BRDF's denominator cancels.
    specular = a2 / (denom * denom) * _smith_g1(cos_l, a2) * surface.masking * fresnel
    if out is None:
        out = np.empty((*cos_l.shape, 3), np.float32)
    np.multiply(surface.albedo, (vis * cos_l + ambient * max(lz, 0.0))[..., None], out=out)
    out += (vis * specular)[..., None]
    return out


def light_terms(surface: Surface, lights: np.ndarray, *, ambient: float) -> np.ndarray:
    """Per-light scalars of :func:`shade`, ``(lights, 8)`` float32, for the compiled loop.

    ``lx, ly, lz``, the half vector ``hx, hy, hz``, Schlick's ``(1 - v.h)^5`` and the ambient
    irradiance, each computed in float64 and rounded once, as numpy rounds a Python float
    that meets a float32 array in :func:`shade`.
    """
    vx, vy, vz = surface.view
    terms = np.empty((len(lights), 8), np.float32)
    for il, light in enumerate(lights):
        lx, ly, lz = (float(c) for c in light)
        hx, hy, hz = lx + vx, ly + vy, lz + vz
        norm = math.sqrt(hx * hx + hy * hy + hz * hz)
        hx, hy, hz = hx / norm, hy / norm, hz / norm
        schlick = (1.0 - max(vx * hx + vy * hy + vz * hz, 0.0)) ** 5
        terms[il] = (lx, ly, lz, hx, hy, hz, schlick, ambient * max(lz, 0.0))
    return terms


def shade_all(surface: Surface, vis: np.ndarray, lights: np.ndarray, *, ambient: float,
              out: np.ndarray) -> np.ndarray:
    """:func:`shade` for every light at once ``out[l] = shade(.., vis[l], lights[l], ..)``.

    The same float32 operations in the same order, texel by texel in one compiled loop
    (:mod:`tasks.render_kernels`) that makes no temporaries and releases the GIL: the same
    bits, about 3x faster than :func:`shade` per light (a 512^2 wood store's shading in 0.33 s
    against 1.06 s), and threads render in parallel.
    """
    from tasks.render_kernels import shade_lights

    nx, ny, nz = surface.normal
    shade_lights(nx, ny, nz, surface.albedo, surface.a2, surface.f0, surface.masking, vis,
                 light_terms(surface, lights, ambient=ambient), out)
    return out


STRIP_ROWS = 64  # rows rendered at once: keeps the temporaries in cache (measured ~30% faster)


class ByteCache:
    """Arrays kept by key, at most ``limit`` bytes, the least recently used dropped first.

    Shared by the process's threads (two that miss at once both compute; the second's entry
    stays). ``computed`` counts the entries put, i.e. the misses. Nothing writes to an
    entry's arrays once it is kept.
    """

    def __init__(self, limit: int = 64 << 20) -> None:
        self.limit, self.size, self.computed = limit, 0, 0
        self.entries: OrderedDict[tuple, tuple[int, object]] = OrderedDict()
        self.lock = threading.Lock()

    def get(self, key: tuple):
        """The value kept for ``key``, or None."""
        with self.lock:
            found = self.entries.get(key)
            if found is None:
                return None
            self.entries.move_to_end(key)
            return found[1]

    def put(self, key: tuple, value, nbytes: int) -> None:
        """Keep ``value`` (``nbytes`` of arrays) for ``key``, dropping the oldest past the limit.

        A value over the limit is not kept, and the entries kept stay.
        """
        with self.lock:
            self.computed += 1
            if nbytes > self.limit:
                return
            old = self.entries.pop(key, None)
            if old is not None:
                self.size -= old[0]
            self.entries[key] = (nbytes, value)
            self.size += nbytes
            while self.size > self.limit:
                self.size -= self.entries.popitem(last=False)[1][0]

    def clear(self) -> None:
        """Drop every entry (the counter stays)."""
        with self.lock:
            self.entries.clear()
            self.size = 0


class ShadowCache(ByteCache):
    """Cast-shadow visibility of a strip under one light, kept for the blocks of other views.

    A store's task blocks hold one view each (its chunks are a view's), and every view of a
    tile needs the same shadows under each light: a 151 x 151 dome computed them 151 times,
    most of a block's shading. Entries are keyed by what the strip's fields are (the
    caller's key, else their hash), the light and the model, and cover the widest margin
    asked for so far; a narrower one is their centre, the same bits (a texel's visibility
    depends on the heights along its own ray, not on the region around it; tested).
    """

    def visibility(self, window: tuple, h: np.ndarray, halo: int, margin: int, ny: int,
                   nx: int, theta: float, phi: float, model: ShadingModel) -> np.ndarray:
        """:func:`tasks.heightfield.visibility` of the strip's texels and ``margin`` around."""
        key = (window, theta, phi, model.relief, model.penumbra, model.max_shadow)
        found = self.get(key)
        if found is not None and found[0] >= margin:
            cut = found[0] - margin
            return found[1][cut : cut + ny + 2 * margin, cut : cut + nx + 2 * margin]
        r0 = halo - margin
        values = visibility(h, r0, r0, ny + 2 * margin, nx + 2 * margin, theta=theta, phi=phi,
                            relief=model.relief, penumbra=model.penumbra,
                            max_length=model.max_shadow)
        self.put(key, (margin, values), values.nbytes)
        return values


SHADOWS = ShadowCache()


class ViewCache(ByteCache):
    """What an oblique view sees of a strip, kept for the view's other blocks of lights.

    An entry is the :class:`Surface` and the parallax offsets of a view. A store's task
    blocks hold one view and a block of lights each: a 151 x 151 dome at ``--dir-chunk 16``
    traced each oblique view's parallax and resampled its surface for each of its 10 blocks
    of lights. Entries are keyed by what the strip's fields are (the caller's key, else their
    hash), the view and the model; a hit gives the arrays computed before, so the same bits.
    """


VIEWS = ViewCache()


def _fields_digest(fields: Fields) -> bytes:
    """A hash of every field's bytes, shape and type."""
    digest = hashlib.blake2b(digest_size=16)
    for a in (fields.height, fields.albedo, fields.roughness, fields.specular):
        a = np.ascontiguousarray(a)
        digest.update(repr((a.shape, a.dtype.str)).encode())
        digest.update(a.data)
    return digest.digest()


def _view(fields: Fields, halo: int, n: Callable[[], tuple], layers: Callable[[], np.ndarray],
          theta: float, phi: float, view: np.ndarray, model: ShadingModel
          ) -> tuple[Surface, tuple[np.ndarray, np.ndarray] | None]:
    """The :class:`Surface` a view sees of a strip, and its parallax offsets (None: none)."""
    h = fields.height
    ny, nx = h.shape[0] - 2 * halo, h.shape[1] - 2 * halo
    inner = (slice(halo, halo + ny), slice(halo, halo + nx))
    if parallax_length(theta, relief=model.relief, reference=model.reference) == 0.0:
        # A top view sees each texel straight below it: plain slices, no resampling.
        normal = tuple(c[inner] for c in n())
        return Surface.seen_from(normal, fields.albedo[inner], fields.roughness[inner],
                                 fields.specular[inner], view), None
    oy, ox = parallax_hits(h, halo, halo, ny, nx, theta=theta, phi=phi,
                           relief=model.relief, reference=model.reference)
    gx, gy, gz, alpha, f0, *rgb = bilinear_layers(layers(), halo, halo, oy, ox)
    inv = 1.0 / np.sqrt(gx * gx + gy * gy + gz * gz)
    normal = (gx * inv, gy * inv, gz * inv)
    # f0 copied out of the resampled stack, so that a kept surface holds only its own arrays
    return Surface.seen_from(normal, np.stack(rgb, axis=-1), alpha, f0.copy(), view), (oy, ox)


def _nbytes(value) -> int:
    """Bytes of the arrays in a nest of tuples and :class:`Surface` objects."""
    if isinstance(value, np.ndarray):
        return value.nbytes
    if isinstance(value, Surface):
        value = (value.normal, value.albedo, value.a2, value.f0, value.masking)
    if isinstance(value, tuple):
        return sum(_nbytes(v) for v in value)
    return 0


def render_block(
    fields: Fields, *, halo: int, theta_view: np.ndarray, phi_view: np.ndarray,
    theta_light: np.ndarray, phi_light: np.ndarray, model: ShadingModel,
    key: Hashable | None = None,
) -> np.ndarray:
    """Render every (view, light) layer of one tile.

    Parameters
    ----------
    fields
        Material fields of the tile plus ``halo`` texels on every side (see
        :meth:`ShadingModel.halo`).
    halo
        Width of that margin.
    theta_view, phi_view, theta_light, phi_light
        Directions in degrees.
    model
        Renderer parameters.
    key
        What the fields are, where the caller knows it (a stage: its material and the block's
        place): equal keys promise equal fields for as long as :data:`SHADOWS` and
        :data:`VIEWS` keep them, which is the life of the process (a cluster's workers keep
        them from run to run; the stage empties its own process's when it ends). The caches
        then need not hash the fields; None: they hash them.

    Returns
    -------
    numpy.ndarray
        Float32 radiance of shape ``(views, lights, ny, nx, 3)`` for the tile without its halo.
        Every texel depends only on the fields within ``halo`` of it, so the tile is rendered in
        strips of :data:`STRIP_ROWS` rows with the same result.
    """
    ny = fields.height.shape[0] - 2 * halo
    nx = fields.height.shape[1] - 2 * halo
    out = np.empty((len(theta_view), len(theta_light), ny, nx, 3), np.float32)
    for r0 in range(0, ny, STRIP_ROWS):
        rows = min(STRIP_ROWS, ny - r0)
        strip = fields.crop(slice(r0, r0 + rows + 2 * halo), slice(None))
        _render_strip(strip, halo=halo, theta_view=theta_view, phi_view=phi_view,
                      theta_light=theta_light, phi_light=phi_light, model=model,
                      out=out[:, :, r0 : r0 + rows], key=None if key is None else (key, r0))
    return out


def _render_strip(
    fields: Fields, *, halo: int, theta_view: np.ndarray, phi_view: np.ndarray,
    theta_light: np.ndarray, phi_light: np.ndarray, model: ShadingModel, out: np.ndarray,
    key: Hashable | None = None,
) -> None:
    """Render every (view, light) layer of a strip into ``out`` (see :func:`render_block`).

    ``key``: what the strip's fields are (see :func:`render_block`), or None.
    """
    h = fields.height
    ny, nx = h.shape[0] - 2 * halo, h.shape[1] - 2 * halo
    # Shadows are needed wherever a view ray of this block can land.
    margin = math.ceil(parallax_length(float(np.max(theta_view)), relief=model.relief,
                                       reference=model.reference)) + 1
    size_y, size_x = ny + 2 * margin, nx + 2 * margin
    vis = np.ones((len(theta_light), size_y, size_x), np.float32)
    if key is None and (model.shadows or VIEWS.limit):
        key = _fields_digest(fields)  # what the strip is, for the caches
    if model.shadows:
        window = (key, h.shape, h.dtype.str, halo, ny, nx)
        for i, (t, p) in enumerate(zip(theta_light, phi_light, strict=True)):
            vis[i] = SHADOWS.visibility(window, h, halo, margin, ny, nx, float(t), float(p),
                                        model)
    lights = direction_vectors(theta_light, phi_light)
    views = direction_vectors(theta_view, phi_view)
    strip = (key, h.shape, halo, model.relief, model.reference) if VIEWS.limit else None
    n = layers = None

    def normals_once() -> tuple:
        nonlocal n
        if n is None:
            n = normals(h)
        return n

    def layers_once() -> np.ndarray:  # the fields every oblique view resamples, as one stack
        nonlocal layers
        if layers is None:
            layers = np.stack([*normals_once(), fields.roughness, fields.specular,
                               *np.moveaxis(fields.albedo, -1, 0)])
        return layers

    for iv, (t, p) in enumerate(zip(theta_view, phi_view, strict=True)):
        entry = None if strip is None else (strip, float(t), float(p))
        seen = None if entry is None else VIEWS.get(entry)
        if seen is None:
            seen = _view(fields, halo, normals_once, layers_once, float(t), float(p),
                         views[iv], model)
            if entry is not None and seen[1] is not None:  # a top view is a few slices
                VIEWS.put(entry, seen, _nbytes(seen))
        surface, offsets = seen
        if offsets is None:
            seen_vis = vis[:, margin : margin + ny, margin : margin + nx]
        else:
            seen_vis = bilinear_layers(vis, margin, margin, *offsets)
        shade_all(surface, seen_vis, lights, ambient=model.ambient, out=out[iv])
