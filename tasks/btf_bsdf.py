"""A compressed BTF as a Mitsuba 3 BSDF, written in Dr.Jit.

The BSDF evaluates what ``btf view``'s page shows, for any incident and outgoing direction and
texture coordinate:

- the view (``si.wi``) and light (``wo``) directions, in the local shading frame (z the normal,
  x along the texture's u, y along v), are projected onto the unit disk, ``(x, y)``, and each
  is located in its blending mesh (:func:`tasks.viewer.mesh`: Delaunay triangles of the
  measured directions and a ring of ghosts) exactly as :func:`tasks.viewer.locate` does: of
  its grid cell's triangles, the one whose smallest barycentric weight is largest, weights
  under :data:`tasks.viewer.SNAP` dropped. At most 3 x 3 measured (view, light) pairs
  remain;
- their rows of ``U diag(S)`` are blended with the products of the weights, multiplied with
  the ``k`` eigentextures ``V`` at the texture coordinate (bilinear between texel centres,
  wrapping: a tile repeats), and the store's transform turns the values into radiance
  (:class:`tasks.transform.Transform`; a cosine store's blended ``1 / cos theta_light`` too).

What a value means radiometrically (docs/mitsuba.md): a stored layer is the radiance the
sample reflects towards the view under a directional light of unit irradiance (measured
perpendicular to the light), as a camera photographs it. Mitsuba's ``eval`` is
``f(wi, wo) cos theta_o``, and a plane under a directional light of irradiance ``E`` shows
``eval * E``: so ``eval`` returns the blended layer's value itself, and such a plane seen by an
orthographic camera reproduces the stored layer. Sampling is cosine-weighted over the upper
hemisphere (``pdf = cos theta_o / pi``), so ``sample`` returns ``eval / pdf``.

Everything here is Dr.Jit operations: on the ``llvm`` and ``cuda`` variants the BSDF compiles
into the renderer's kernels; on ``scalar`` it runs per sample in Python (slow, for tests and
small images). Mitsuba is imported when a class is made, not with this module.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tasks.transform import LOG_MAX, YUV_TO_RGB, Transform
from tasks.viewer import SNAP, Mesh, cell_triangles

CELLS = 256  # cells per side of the grid that lists the triangles a point may lie in


@dataclass(frozen=True)
class Tables:
    """What the BSDF holds (host arrays): the factors, the meshes, the transform.

    ``us`` ``(views, lights, channels, k)``: rows of ``U diag(S)``; ``v`` ``(y, x, k)``: the
    eigentextures (row 0 the top of the picture); ``scale`` ``(lights,)`` or None: a cosine
    store's ``1 / cos theta_light``.
    """

    us: np.ndarray
    v: np.ndarray
    view_mesh: Mesh
    light_mesh: Mesh
    transform: Transform
    scale: np.ndarray | None = None

    @property
    def channels(self) -> int:
        """Channels of the store."""
        return self.us.shape[2]

    @property
    def rank(self) -> int:
        """Components used."""
        return self.us.shape[3]


def _buffers(mi, dr):
    """The array types that hold a table: the variant's own, or dynamic ones on ``scalar``."""
    if mi.variant().startswith("scalar"):
        return dr.scalar.ArrayXf, dr.scalar.ArrayXi
    return mi.Float, mi.Int32


def _gather(mi, dr):
    """``gather(dtype, buffer, index, active)``: ``dr.gather``, or indexing on ``scalar``."""
    if mi.variant().startswith("scalar"):
        return lambda dtype, buffer, index, active=True: (
            dtype(buffer[int(index)]) if active else dtype(0))
    return dr.gather


class _DeviceMesh:
    """A blending mesh as Dr.Jit arrays, and :func:`tasks.viewer.locate` on them.

    Each grid cell's triangles are a span of a list (:func:`tasks.viewer.cell_triangles`, on a
    grid of :data:`CELLS` per side: the pick does not depend on the grid, only the work does),
    walked by a loop of as many steps as the cell has triangles: a symbolic loop on the JIT
    variants, so a lane stops at its own cell's count rather than at the fullest cell's.
    """

    def __init__(self, mi, dr, m: Mesh):
        self.dr, self.mi = dr, mi
        self.gather = _gather(mi, dr)
        floats, ints = _buffers(mi, dr)
        self.single = len(m.triangles) == 0
        if self.single:
            return
        spans, items = cell_triangles(m, CELLS)
        self.start = ints(spans[..., 0].ravel())
        self.count = ints(spans[..., 1].ravel())
        self.items = ints(items if len(items) else np.zeros(1, np.int32))
        self.px = floats(m.points[:, 0].astype(np.float32))
        self.py = floats(m.points[:, 1].astype(np.float32))
        self.triangles = ints(m.triangles.ravel())
        self.labels = ints(m.labels)

    def _step(self, x, y, t, live, best, corners, weights):
        """Keep triangle ``t`` where its smallest barycentric weight beats ``best``."""
        dr, mi, gather = self.dr, self.mi, self.gather
        ia, ib, ic = (gather(mi.Int32, self.triangles, 3 * t + i, live) for i in range(3))
        (ax, ay), (bx, by), (qx, qy) = (
            (gather(mi.Float, self.px, c, live), gather(mi.Float, self.py, c, live))
            for c in (ia, ib, ic))
        m00, m01, m10, m11 = bx - ax, qx - ax, by - ay, qy - ay
        det = m00 * m11 - m01 * m10
        proper = live & (dr.abs(det) >= 1e-15)  # a degenerate triangle is never taken
        det = dr.select(proper, det, 1.0)
        px, py = x - ax, y - ay
        wb = (px * m11 - m01 * py) / det
        wc = (m00 * py - px * m10) / det
        wa = 1.0 - wb - wc
        smallest = dr.select(proper, dr.minimum(wa, dr.minimum(wb, wc)), -dr.inf)
        better = smallest > best  # the first of equals, as numpy's argmax
        best = dr.select(better, smallest, best)
        corners = tuple(dr.select(better, c, old) for c, old in zip((ia, ib, ic), corners,
                                                                     strict=True))
        weights = tuple(dr.select(better, w, old) for w, old in zip((wa, wb, wc), weights,
                                                                     strict=True))
        return best, corners, weights

    def locate(self, x, y, active):
        """``(labels, weights)``: three measured directions and their weights at ``(x, y)``."""
        dr, mi, gather = self.dr, self.mi, self.gather
        if self.single:
            zero = mi.Int32(0)
            return (zero, zero, zero), (mi.Float(1.0), mi.Float(0.0), mi.Float(0.0))
        cx = dr.clip(mi.Int32(dr.floor((x * 0.5 + 0.5) * CELLS)), 0, CELLS - 1)
        cy = dr.clip(mi.Int32(dr.floor((y * 0.5 + 0.5) * CELLS)), 0, CELLS - 1)
        cell = cy * CELLS + cx
        start = gather(mi.Int32, self.start, cell, active)
        count = gather(mi.Int32, self.count, cell, active)

        def cond(j, best, c0, c1, c2, w0, w1, w2):
            return j < count

        def body(j, best, c0, c1, c2, w0, w1, w2):
            t = gather(mi.Int32, self.items, start + j, j < count)
            best, corners, weights = self._step(x, y, t, j < count, best, (c0, c1, c2),
                                                (w0, w1, w2))
            return (j + 1, best, *corners, *weights)

        zero, none = mi.Int32(0), mi.Float(0.0)
        state = (mi.Int32(0), mi.Float(-dr.inf), zero, zero, zero, none, none, none)
        _, _, *found = dr.while_loop(state, cond, body)
        corners, weights = found[:3], found[3:]
        weights = [dr.select(w > SNAP, w, 0.0) for w in weights]
        total = weights[0] + weights[1] + weights[2]
        total = dr.select(total > 0, total, 1.0)
        labels = tuple(gather(mi.Int32, self.labels, c, active) for c in corners)
        return labels, tuple(w / total for w in weights)


def _decode(dr, mi, transform: Transform, values: list):
    """Radiance (>= 0) of one texel's channel values (Dr.Jit), as :meth:`Transform.decode`."""
    eps = transform.eps
    if transform.name == "linear":
        return [dr.maximum(a, 0.0) for a in values]
    if transform.name == "log":
        return [dr.maximum(dr.exp(dr.minimum(a, LOG_MAX)) - eps, 0.0) for a in values]
    a0, a1, a2 = values
    y = dr.exp(dr.minimum(a0, LOG_MAX))  # Y + eps
    if transform.name == "ylog-uv-over-y":
        u, v = a1 * y, a2 * y
    elif transform.name == "ylog-ulog-vlog":
        log_eps = float(np.log(np.float32(eps)))
        u, v = (dr.sign(c) * dr.exp(dr.minimum(dr.abs(c), LOG_MAX) + log_eps) for c in (a1, a2))
    else:
        u, v = a1, a2
    y = y - eps
    m = YUV_TO_RGB.astype(np.float32)
    return [dr.maximum(float(m[i, 0]) * y + float(m[i, 1]) * u + float(m[i, 2]) * v, 0.0)
            for i in range(3)]


def bsdf_class(mi, dr):
    """The BSDF class for the active Mitsuba variant (``mi.BSDF``'s subclass of that variant).

    Its constructor takes ``(props, tables)``: Mitsuba's properties (``uv_scale``, a float:
    texture repeats per unit of ``uv``) and the :class:`Tables` to render.
    """

    class BTF(mi.BSDF):
        def __init__(self, props, tables: Tables):
            super().__init__(props)
            self.tables = tables
            self.uv_scale = float(props.get("uv_scale", 1.0)) if props is not None else 1.0
            _, nl, nc, k = tables.us.shape
            self.nl, self.nc, self.k = nl, nc, k
            floats, _ = _buffers(mi, dr)
            self.gather = _gather(mi, dr)
            self.us = floats(np.ascontiguousarray(tables.us, np.float32).ravel())
            v = np.ascontiguousarray(tables.v, np.float32)
            self.texture = mi.Texture2f(mi.TensorXf(v.ravel(), shape=v.shape),
                                        filter_mode=dr.FilterMode.Linear,
                                        wrap_mode=dr.WrapMode.Repeat)
            self.views = _DeviceMesh(mi, dr, tables.view_mesh)
            self.lights = _DeviceMesh(mi, dr, tables.light_mesh)
            self.scale = (None if tables.scale is None
                          else floats(np.asarray(tables.scale, np.float32)))
            flags = (mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
                     | mi.BSDFFlags.SpatiallyVarying)
            self.m_components = [flags]
            self.m_flags = flags

        def values(self, wi, wo, uv, active):
            """The blended layer's radiance per channel (list of ``Float``)."""
            gather = self.gather
            (lv, wv) = self.views.locate(wi.x, wi.y, active)
            (ll, wl) = self.lights.locate(wo.x, wo.y, active)
            # row 0 of V is the top of the picture; v grows towards the top
            at = mi.Point2f(uv.x * self.uv_scale, 1.0 - uv.y * self.uv_scale)
            vk = self.texture.eval(at, active)
            nc, k = self.nc, self.k
            acc = [mi.Float(0.0) for _ in range(nc)]
            for a in range(3):
                for b in range(3):
                    w = wv[a] * wl[b]
                    live = active & (w > 0)
                    base = (lv[a] * self.nl + ll[b]) * (nc * k)
                    for c in range(nc):
                        dot = mi.Float(0.0)
                        for j in range(k):
                            dot = dr.fma(gather(mi.Float, self.us, base + c * k + j, live),
                                         vk[j], dot)
                        acc[c] = dr.fma(w, dot, acc[c])
            radiance = _decode(dr, mi, self.tables.transform, acc)
            if self.scale is not None:
                factor = sum(wl[b] * gather(mi.Float, self.scale, ll[b], active)
                             for b in range(3))
                radiance = [r * factor for r in radiance]
            return radiance

        def _spectrum(self, radiance):
            if len(radiance) == 1:
                return mi.Color3f(radiance[0], radiance[0], radiance[0])
            return mi.Color3f(radiance[0], radiance[1], radiance[2])

        def eval(self, ctx, si, wo, active=True):
            active = (mi.Bool(active) & (mi.Frame3f.cos_theta(si.wi) > 0)
                      & (mi.Frame3f.cos_theta(wo) > 0))
            value = self._spectrum(self.values(si.wi, wo, si.uv, active))
            return dr.select(active, value, 0.0)

        def pdf(self, ctx, si, wo, active=True):
            active = (mi.Bool(active) & (mi.Frame3f.cos_theta(si.wi) > 0)
                      & (mi.Frame3f.cos_theta(wo) > 0))
            return dr.select(active, mi.warp.square_to_cosine_hemisphere_pdf(wo), 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def sample(self, ctx, si, sample1, sample2, active=True):
            wo = mi.warp.square_to_cosine_hemisphere(sample2)
            pdf = mi.warp.square_to_cosine_hemisphere_pdf(wo)
            active = mi.Bool(active) & (mi.Frame3f.cos_theta(si.wi) > 0) & (pdf > 0)
            bs = dr.zeros(mi.BSDFSample3f)
            bs.wo, bs.pdf, bs.eta = wo, pdf, 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
            bs.sampled_component = mi.UInt32(0)
            value = self._spectrum(self.values(si.wi, wo, si.uv, active))
            return bs, dr.select(active, value / dr.maximum(pdf, 1e-12), 0.0)

        def traverse(self, callback):
            pass

        def to_string(self):
            nv, nl, nc, k = self.tables.us.shape
            ny, nx = self.tables.v.shape[:2]
            return (f"BTF[{nv} views x {nl} lights, {ny} x {nx} texels, {nc} channels, rank "
                    f"{k}, transform {self.tables.transform.name}]")

    return BTF
