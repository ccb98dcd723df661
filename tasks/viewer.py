"""What the relighting viewer (``btf view``) computes before the page is written.

The page renders a layer of a compressed store as the viewer's shader does (one dot product of
length ``k`` per texel and channel, then the store's transform and the report's tone mapping).
Between measured directions it blends the measured (view, light) pairs with barycentric
weights over a triangulation of the directions projected onto the unit disk
(``(sin theta cos phi, sin theta sin phi)``): the Delaunay triangles of the measured
directions, and round their hull a ring of *ghost* vertices outside the unit disk, one per
hull vertex on the ray from a centre through it and standing for that hull vertex
(:func:`mesh`). Every point of the disk lies in a triangle, so the blend is C0 everywhere,
beyond the last measured ring too: exactly one pair at a measured pair, on the edge between
two measured directions a blend of those two only, and past the hull the blend of the hull
edge's two directions, the nearer one alone along its ghost ray.

The page's sphere is a replica of :func:`sphere_image`: a unit sphere seen from the front
(orthographic, the camera on +z), lit by a point light ``distance`` radii away, its surface
parametrised by stereographic coordinates from the back pole (conformal, no pole on the
visible hemisphere). This module holds the parts the page's script and shaders mirror, so
that tests can compute what the page must show.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

SNAP = 1e-9  # barycentric weights below this are rounding noise: dropped
ENERGY_KEPT = 0.9999  # the default rank keeps this share of the store's ||A||^2 (btf view)
LIGHT_DISTANCE = 4.0  # the sphere's point light, in radii from its centre
CELL_MARGIN = 1e-4  # a cell's triangles: those within this of it (float32 lookups in the page)
GRID = 128  # cells per side of the grid over [-1, 1]^2 that lists each cell's triangles


def disk(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Directions (degrees) projected onto the unit disk, ``(n, 2)`` float64."""
    t, p = np.radians(np.asarray(theta, np.float64)), np.radians(np.asarray(phi, np.float64))
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p)], -1)


def triangulate(theta: np.ndarray, phi: np.ndarray, what: str) -> np.ndarray:
    """Triangles ``(m, 3)`` (int32 indices) of a Delaunay triangulation of the directions.

    One direction needs none (an empty array); two, or directions on one line, cannot be
    blended over a surface and raise ``ValueError`` naming ``what``.
    """
    from scipy.spatial import Delaunay, QhullError

    points = disk(theta, phi)
    if len(points) == 1:
        return np.zeros((0, 3), np.int32)
    if len(np.unique(np.round(points, 9), axis=0)) < 3:
        raise ValueError(f"{len(points)} {what} direction(s) cannot be triangulated: the "
                         "viewer blends between at least three directions not on one line")
    try:
        return Delaunay(points).simplices.astype(np.int32)
    except QhullError:
        raise ValueError(f"the {len(points)} {what} directions lie on one line and cannot be "
                         "triangulated") from None


@dataclass(frozen=True)
class Mesh:
    """A triangulation that covers the unit disk, and what each of its vertices stands for.

    ``points`` ``(n + g, 2)``: the ``n`` measured directions on the disk, then ``g`` ghosts;
    ``triangles`` ``(m, 3)`` int32 indices into ``points``; ``labels`` ``(n + g,)`` int32: the
    measured direction each point stands for (itself, or a ghost's hull vertex).
    """

    points: np.ndarray
    triangles: np.ndarray
    labels: np.ndarray

    @cached_property
    def cells(self) -> tuple[np.ndarray, np.ndarray]:
        """The triangles of every cell of a :data:`GRID` grid (:func:`cell_triangles`)."""
        return cell_triangles(self, GRID)

    def to_dict(self) -> dict:
        """The page's copy (JSON)."""
        return {"points": self.points.tolist(), "triangles": self.triangles.tolist(),
                "labels": self.labels.tolist()}


def _boundary(triangles: np.ndarray) -> np.ndarray:
    """The triangulation's boundary vertices in order round it (edges in one triangle only)."""
    edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]],
                                    triangles[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    outer = unique[counts == 1]
    after: dict[int, list[int]] = {}
    for a, b in outer.tolist():
        after.setdefault(a, []).append(b)
        after.setdefault(b, []).append(a)
    ring, previous = [int(outer[0, 0])], None
    while True:
        here = ring[-1]
        step = next(v for v in after[here] if v != previous)
        if step == ring[0]:
            return np.array(ring)
        previous = here
        ring.append(step)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The z of the cross products of 2-D vectors."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def mesh(theta: np.ndarray, phi: np.ndarray, what: str) -> Mesh:
    """The blending mesh of directions (degrees): Delaunay triangles and a ring of ghosts.

    Round the Delaunay triangulation's boundary (the convex hull, collinear points included)
    each boundary vertex ``h`` gets a ghost ``c + R (h - c) / |h - c|`` standing for it: ``c``
    is the disk's centre where the hull holds it (every dome-like sampling), else the mean of
    the boundary; ``R`` puts the ghosts' polygon round the whole unit disk. Each quad of two
    neighbouring boundary vertices and their ghosts is convex (a wedge from ``c`` cut by two
    lines) and split into two triangles. The measured triangles are kept as they are, so
    inside the hull the blend is the Delaunay one. Raises ``ValueError`` as
    :func:`triangulate`.
    """
    points = disk(theta, phi)
    triangles = triangulate(theta, phi, what)
    labels = np.arange(len(points), dtype=np.int32)
    if len(triangles) == 0:
        return Mesh(points, triangles, labels)
    ring = _boundary(triangles)
    hull = points[ring]
    edges = np.roll(hull, -1, axis=0) - hull
    if _cross(edges, np.roll(edges, -1, axis=0)).sum() < 0:  # clockwise: turn it round
        ring, hull = ring[::-1], hull[::-1]
        edges = np.roll(hull, -1, axis=0) - hull
    # the origin is inside when it is left of every edge (with a margin)
    inside = (_cross(edges, -hull) / np.linalg.norm(edges, axis=1)).min() > 1e-6
    centre = np.zeros(2) if inside else hull.mean(axis=0)
    rays = hull - centre
    angles = np.arctan2(rays[:, 1], rays[:, 0])
    gap = float(np.max((np.roll(angles, -1) - angles) % (2 * np.pi)))
    radius = max(2.0, (np.linalg.norm(centre) + 1.5) / np.cos(gap / 2))
    ghosts = centre + radius * rays / np.linalg.norm(rays, axis=1, keepdims=True)
    n, g = len(points), len(ring)
    quads = []
    for i in range(g):
        j = (i + 1) % g
        h0, h1, g0, g1 = ring[i], ring[j], n + i, n + j
        quads += [(h0, h1, g1), (h0, g1, g0)]
    return Mesh(np.concatenate([points, ghosts]),
                np.concatenate([triangles, np.array(quads, np.int32)]).astype(np.int32),
                np.concatenate([labels, ring.astype(np.int32)]))


def _barycentric(points: np.ndarray, triangles: np.ndarray, at: np.ndarray, *,
                 paired: bool = False) -> np.ndarray:
    """Barycentric coordinates ``(N, m, 3)`` of points ``at`` ``(N, 2)`` in every triangle.

    ``paired``: of each point in its own triangle only, ``(N, 3)``. The page's script
    computes them with the same formula, operation for operation, so that both pick the same
    triangle.
    """
    a, b, c = (points[triangles[:, i]] for i in range(3))
    m00, m01 = b[:, 0] - a[:, 0], c[:, 0] - a[:, 0]
    m10, m11 = b[:, 1] - a[:, 1], c[:, 1] - a[:, 1]
    det = m00 * m11 - m01 * m10
    if paired:
        px, py = at[:, 0] - a[:, 0], at[:, 1] - a[:, 1]
    else:
        px = at[:, None, 0] - a[None, :, 0]
        py = at[:, None, 1] - a[None, :, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        wb = (px * m11 - m01 * py) / det
        wc = (m00 * py - px * m10) / det
    w = np.stack([1.0 - wb - wc, wb, wc], -1)
    w[..., np.abs(det) < 1e-15, :] = -np.inf
    return w


def locate(m: Mesh, at: np.ndarray, *, block: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """Labels ``(N, 3)`` and weights ``(N, 3)`` of the points ``at`` ``(N, 2)``.

    The triangle containing each point (of equals the first): the one whose smallest
    barycentric weight is the largest, which off the mesh (beyond its ghosts, outside the
    unit disk) is the nearest, its negative weights set to 0. Weights below :data:`SNAP` are
    dropped and the rest renormalised. With one direction: label 0, weight 1. The containing
    triangle is looked for among its cell's (:attr:`Mesh.cells`, as the page's shader does),
    then, for a point no listed triangle holds, among all.
    """
    at = np.atleast_2d(np.asarray(at, np.float64))
    labels = np.zeros((len(at), 3), np.int32)
    weights = np.zeros((len(at), 3))
    if len(m.triangles) == 0:
        weights[:, 0] = 1.0
        return labels, weights
    spans, items = m.cells
    table = np.full((GRID * GRID, max(1, int(spans[..., 1].max()))), -1)
    for j in range(table.shape[1]):
        has = spans[..., 1].ravel() > j
        table[has, j] = items[spans[..., 0].ravel()[has] + j]
    for s in range(0, len(at), block):
        p = at[s:s + block]
        cell = np.clip(((p * 0.5 + 0.5) * GRID).astype(int), 0, GRID - 1)
        candidates = table[cell[:, 1] * GRID + cell[:, 0]]  # (n, L), -1: none
        w = _barycentric(m.points, m.triangles[np.maximum(candidates, 0)].reshape(-1, 3),
                         p.repeat(candidates.shape[1], 0), paired=True)
        w = w.reshape(len(p), -1, 3)
        w[candidates < 0] = -np.inf
        pick = np.argmax(w.min(axis=-1), axis=1)
        best = candidates[np.arange(len(p)), pick]
        w = w[np.arange(len(p)), pick]
        outside = w.min(axis=1) < -1e-12  # (or no triangle listed): the nearest of all
        if outside.any():
            every = _barycentric(m.points, m.triangles, p[outside])
            best[outside] = np.argmax(every.min(axis=-1), axis=1)
            w[outside] = every[np.arange(outside.sum()), best[outside]]
        w = np.where(w > SNAP, w, 0.0)  # rounding leaves 1e-17 of the other corners at a corner
        weights[s:s + block] = w / w.sum(axis=1, keepdims=True)
        labels[s:s + block] = m.labels[m.triangles[best]]
    return labels, weights


def blend_weights(m: Mesh, at) -> list[tuple[int, float]]:
    """``[(measured direction, weight), ...]`` of the disk point ``at`` (see :func:`locate`).

    A ghost's weight goes to its hull vertex; directions are listed in the order of the
    triangle's corners, each once, without zero weights. The page's script computes the same.
    """
    labels, weights = locate(m, np.asarray(at, np.float64)[None])
    out: dict[int, float] = {}
    for i, x in zip(labels[0].tolist(), weights[0].tolist(), strict=True):
        if x > 0:
            out[i] = out.get(i, 0.0) + x
    return list(out.items())


def cell_triangles(m: Mesh, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Per cell of a ``size`` x ``size`` grid over ``[-1, 1]^2``, the triangles overlapping it.

    Returns ``spans`` ``(size, size, 2)`` int32 (row ``y`` from -1 up; first item, count) and
    ``items`` (int32 triangle indices, cell after cell). A cell's triangles are those that
    meet it grown by :data:`CELL_MARGIN` (a separating-axis test), so whatever cell a float32
    lookup rounds a point into, the triangle containing the point is among them: the page's
    shader takes, of the cell's triangles, the one :func:`locate` would.
    """
    lists: list[list[int]] = [[] for _ in range(size * size)]
    edges = np.linspace(-1.0, 1.0, size + 1)
    for t, tri in enumerate(m.triangles):
        corners = m.points[tri]
        lo, hi = corners.min(axis=0) - CELL_MARGIN, corners.max(axis=0) + CELL_MARGIN
        x0, y0 = (np.searchsorted(edges, np.maximum(lo, -1.0), side="right") - 1).clip(0, size - 1)
        x1, y1 = (np.searchsorted(edges, np.minimum(hi, 1.0), side="left")).clip(1, size)
        if lo[0] > 1 or lo[1] > 1 or hi[0] < -1 or hi[1] < -1:
            continue
        gx, gy = np.meshgrid(np.arange(x0, x1), np.arange(y0, y1))
        boxes = np.stack([edges[gx] - CELL_MARGIN, edges[gy] - CELL_MARGIN,
                          edges[gx + 1] + CELL_MARGIN, edges[gy + 1] + CELL_MARGIN], -1)
        box_corners = np.stack([boxes[..., [0, 1]], boxes[..., [2, 1]], boxes[..., [0, 3]],
                                boxes[..., [2, 3]]], -2)  # (..., 4, 2)
        meets = np.ones(gx.shape, bool)
        for i in range(3):  # separated if the box lies wholly beyond one of the edges
            a, b, c = corners[i], corners[(i + 1) % 3], corners[(i + 2) % 3]
            normal = np.array([a[1] - b[1], b[0] - a[0]])
            side = np.sign((c - a) @ normal)
            meets &= ((box_corners - a) @ normal * side >= 0).any(axis=-1)
        for y, x in zip(gy[meets].tolist(), gx[meets].tolist(), strict=True):
            lists[y * size + x].append(t)
    counts = np.array([len(c) for c in lists], np.int32)
    spans = np.stack([np.cumsum(counts) - counts, counts], -1).astype(np.int32)
    items = np.array([t for c in lists for t in c], np.int32)
    return spans.reshape(size, size, 2), items


def coefficients(us: np.ndarray, view_weights, light_weights) -> np.ndarray:
    """The blended rows of ``U diag(S)`` ``(channel, k)`` for the given pair weights.

    ``us`` is ``(view, light, channel, k)``; each weight list is ``[(index, weight), ...]``.
    """
    out = np.zeros(us.shape[2:], np.float64)
    for v, wv in view_weights:
        for li, wl in light_weights:
            out += wv * wl * us[v, li]
    return out.astype(np.float32)


def shown_rank(s: np.ndarray, total: float, *, most: int, share: float = ENERGY_KEPT,
               channels: np.ndarray | None = None) -> int:
    """The smallest rank that keeps ``share`` of the energy, overall and in every channel.

    Overall: ``sum S^2`` of the first components against ``total``, the store's ``||A||^2``
    (its stored components and what compression left out); where the stored components cannot
    reach the share, all of them. ``channels`` ``(channel, K)``, each channel's part of every
    component's energy (``S_i^2 |U[..., c, i]|^2``): every channel keeps ``share`` of its
    stored energy too, so that a channel of small values (Bonn's log luminance beside its
    chroma) is not left out because others dominate ``||A||^2``. At most ``most``.
    """
    def first(kept: np.ndarray, goal: float) -> int:
        reached = np.flatnonzero(kept >= goal)
        return int(reached[0]) + 1 if reached.size else len(kept)

    kept = np.cumsum(np.asarray(s, np.float64) ** 2)
    rank = first(kept, share * total)
    for part in ([] if channels is None else np.asarray(channels, np.float64)):
        own = np.cumsum(part)
        rank = max(rank, first(own, share * own[-1]))
    return max(1, min(rank, most))


MIN_DEFAULT_RANK = 8  # below this many components a page shows a coarser level instead


def b64_bytes(raw: int) -> int:
    """Characters of ``raw`` bytes in base64."""
    return 4 * -(-raw // 3)


def page_bytes(texels: int, rank: int, rows: int, fixed: int) -> int:
    """Bytes of a page's data in base64, and ``fixed`` bytes of the rest.

    Half-float ``V`` of ``texels`` texels in layers of four components, and float32
    ``U diag(S)`` of ``rows`` rows at ``rank``.
    """
    return fixed + b64_bytes(texels * -(-rank // 4) * 8) + b64_bytes(rows * rank * 4)


def plan_page(size, *, rows: int, fixed: int, budget: int, wanted: int, least: int,
              levels=range(13)) -> tuple[int, int] | None:
    """The level of detail and rank of a page within ``budget`` bytes (:func:`page_bytes`).

    ``size(level)`` gives the texels the page holds at a level (0: none left) and the bytes it
    adds besides (a roller's index). Of ``levels`` the first at which at least ``least``
    components fit, and there the most up to ``wanted`` (so a coarser level comes before
    fewer components than ``least``); ``None`` where no level holds ``least``.
    """
    for level in levels:
        texels, extra = size(level)
        if texels < 1:
            break
        fits = [k for k in range(1, wanted + 1)
                if page_bytes(texels, k, rows, fixed + extra) <= budget]
        if fits and fits[-1] >= least:
            return level, fits[-1]
    return None


def block_means(a: np.ndarray, factor: int) -> np.ndarray:
    """Means of ``factor x factor`` blocks over the axes ``(-3, -2)`` of ``(..., y, x, k)``.

    A side that is not a multiple of ``factor`` ends in a block of fewer texels, the mean of
    those (nothing is dropped). Sums in float64; float32 out.
    """
    a = np.asarray(a, np.float64)
    if factor == 1:
        return a.astype(np.float32)
    out = a
    for axis in (-3, -2):
        n = a.shape[axis]
        starts = np.arange(0, n, factor)
        counts = np.minimum(starts + factor, n) - starts
        shape = [1] * a.ndim
        shape[axis] = len(starts)
        out = np.add.reduceat(out, starts, axis=axis) / counts.reshape(shape)
    return out.astype(np.float32)


def half_bits(values: np.ndarray) -> np.ndarray:
    """IEEE half-float bit patterns (uint16) of ``values``, rounded to nearest.

    Raises ``ValueError`` if a value is beyond half's range (65504).
    """
    a = np.asarray(values, np.float32)
    if a.size and float(np.abs(a).max()) > 65504.0:
        raise ValueError(f"values up to {float(np.abs(a).max()):.3g} exceed half floats' range")
    return a.astype(np.float16).view(np.uint16)


def pack_eigentextures(v: np.ndarray) -> np.ndarray:
    """Eigentextures ``(y, x, k)`` as half-float layers of four components ``(k/4, y, x, 4)``.

    Components past ``k`` (to a multiple of four) are zero. Half floats keep 11 significant
    bits: about 5e-4 of each value, below an 8-bit display step after the transform (the
    viewer's tests bound the displayed error).
    """
    ny, nx, k = v.shape
    layers = -(-k // 4)
    padded = np.zeros((ny, nx, layers * 4), np.float32)
    padded[..., :k] = v
    return np.ascontiguousarray(half_bits(padded).reshape(ny, nx, layers, 4).transpose(2, 0, 1, 3))


@dataclass(frozen=True)
class Sphere:
    """Per pixel of the page's ``size`` x ``size`` sphere (rows from the top of the picture).

    ``inside``: on the sphere; ``lit``: the light above the local horizon; ``texture``: the
    stereographic coordinates' ``(s, t)`` in ``[0, 1]``, ``s`` along texture columns, ``t``
    down its rows; ``light`` and ``view``: the local directions ``(x, y, z)`` in the tangent
    frame (x along the texture's columns, y towards its top, z the normal), as the store's
    frame has them.
    """

    inside: np.ndarray
    lit: np.ndarray
    texture: np.ndarray
    light: np.ndarray
    view: np.ndarray


def sphere_at(q: np.ndarray, light: tuple[float, float], *,
              distance: float = LIGHT_DISTANCE) -> Sphere:
    """The page's sphere at screen points ``q`` ``(..., 2)`` (``[-1, 1]^2``, y up).

    The normal is ``n = (q, sqrt(1 - |q|^2))``. Its stereographic coordinates from the back
    pole are ``(u, v) = (n_x, n_y) / (1 + n_z)`` (the visible hemisphere is the unit disk, with
    no pole on it); the tangent frame is ``t`` along ``dn/du`` ``(1 - u^2 + v^2, -2uv, -2u)``
    and ``b`` along ``dn/dv`` ``(-2uv, 1 + u^2 - v^2, -2v)`` (orthogonal and of one length
    since the map is conformal; at the centre ``t = +x``, ``b = +y``). The texture runs along
    ``t`` by columns and against ``b`` by rows: ``(s, t) = ((u + 1) / 2, (1 - v) / 2)``. The
    light is at ``distance`` times its direction (theta, phi in degrees); the camera looks
    along ``-z``.
    """
    q = np.asarray(q, np.float64)
    qx, qy = q[..., 0], q[..., 1]
    r2 = qx**2 + qy**2
    inside = r2 < 1.0
    nz = np.sqrt(np.maximum(1.0 - r2, 0.0))
    n = np.stack([qx, qy, nz], -1)
    u, v = qx / (1 + nz), qy / (1 + nz)
    t = np.stack([1 - u * u + v * v, -2 * u * v, -2 * u], -1)
    b = np.stack([-2 * u * v, 1 + u * u - v * v, -2 * v], -1)
    t /= np.linalg.norm(t, axis=-1, keepdims=True)
    b /= np.linalg.norm(b, axis=-1, keepdims=True)
    theta, phi = np.radians(light)
    position = distance * np.array([np.sin(theta) * np.cos(phi),
                                    np.sin(theta) * np.sin(phi), np.cos(theta)])
    lw = position - n
    lw /= np.linalg.norm(lw, axis=-1, keepdims=True)
    local = np.stack([(lw * t).sum(-1), (lw * b).sum(-1), (lw * n).sum(-1)], -1)
    view = np.stack([t[..., 2], b[..., 2], nz], -1)  # the camera's direction, +z
    return Sphere(inside, inside & (local[..., 2] > 0), np.stack([(u + 1) / 2, (1 - v) / 2], -1),
                  local, view)


def screen(size: int) -> np.ndarray:
    """Screen points ``(size, size, 2)`` of the page's sphere pixels, rows from the top."""
    centres = (np.arange(size) + 0.5) / size * 2 - 1
    qx, qy = np.meshgrid(centres, -centres)
    return np.stack([qx, qy], -1)


def sphere(size: int, light: tuple[float, float], *,
           distance: float = LIGHT_DISTANCE) -> Sphere:
    """The page's ``size`` x ``size`` sphere (:func:`sphere_at` of every pixel's centre)."""
    return sphere_at(screen(size), light, distance=distance)


def sphere_texels(geometry: Sphere, shape: tuple[int, int], cells: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows, columns of a ``shape`` texture repeated ``cells`` times across the sphere's disk.

    Also whether each is sure: ``False`` within 1e-3 texel of a texel's border, where the
    page's float32 arithmetic may round to the neighbour.
    """
    h, w = shape
    at = np.mod(geometry.texture * cells, 1.0) * np.array([w, h])
    sure = (np.abs(at - np.round(at)) > 1e-3).all(axis=-1)
    cols, rows = np.clip(at.astype(int), 0, [w - 1, h - 1]).transpose(2, 0, 1)
    return rows, cols, sure


def sphere_values(geometry: Sphere, surface: np.ndarray, us: np.ndarray, light_mesh: Mesh,
                  view_mesh: Mesh, *, cells: float) -> tuple[np.ndarray, np.ndarray]:
    """The values ``(..., channel)`` the page's sphere decodes, and where they are sure.

    ``surface`` ``(y, x, k)`` eigentextures repeated ``cells`` times across the disk (a
    store's ``V``; a tile set's laid cells with ``cells`` 1), ``us`` the rows ``U diag(S)``
    ``(view, light, channel, k)``. Every lit point blends the measured pairs of its own local
    light and view (:func:`locate`) as the page's shader does. Values are 0 off the sphere
    and where unlit; "sure" leaves out texel borders and points within 1e-3 of the local
    horizon or of the sphere's rim, where float32 may round either way.
    """
    shape = geometry.inside.shape
    rows, cols, sure = sphere_texels(geometry, surface.shape[:2], cells)
    lit = geometry.lit.ravel()
    li, lw = locate(light_mesh, geometry.light.reshape(-1, 3)[lit, :2])
    vi, vw = locate(view_mesh, geometry.view.reshape(-1, 3)[lit, :2])
    us = np.asarray(us, np.float64)
    coef = np.zeros((len(li), *us.shape[2:]))
    for i in range(3):
        for j in range(3):
            coef += (vw[:, i] * lw[:, j])[:, None, None] * us[vi[:, i], li[:, j]]
    texels = np.asarray(surface, np.float64)[rows.ravel()[lit], cols.ravel()[lit]]
    values = np.zeros((lit.size, us.shape[2]), np.float32)
    values[lit] = np.einsum("nck,nk->nc", coef, texels)
    rim = 1 - geometry.view[..., 2] ** 2  # |q|^2
    sure &= (np.abs(geometry.light[..., 2]) > 1e-3) & (np.abs(rim - 1) > 1e-3)
    return values.reshape(*shape, -1), sure


def sphere_light_scale(geometry: Sphere, light_mesh: Mesh, scale: np.ndarray) -> np.ndarray:
    """A cosine store's factor at every point of the sphere: the blend of its lights' ``scale``.

    ``scale`` is one per measured light (``1 / cos theta_light``,
    :meth:`tasks.transform.Transform.layer_scale`), blended with the weights of each point's
    own local light, as the page's shader does; 1 where unlit.
    """
    out = np.ones(geometry.inside.shape)
    lit = geometry.lit
    labels, weights = locate(light_mesh, geometry.light[lit][:, :2])
    out[lit] = (weights * np.asarray(scale, np.float64)[labels]).sum(axis=1)
    return out
