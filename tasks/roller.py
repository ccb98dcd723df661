"""Double toroidal tiles on a (possibly sheared) lattice: the generalized roller (paper 004).

Given the periodicity vectors ``u``, ``v`` (:mod:`tasks.periodicity`), the tile is spanned by
``U = a u`` and ``V = b v`` rounded to whole pixels, so it repeats by exact integer shifts.
Choices where the paper is not specific:

- **Tile size**: by default ``a, b`` whose rhomboid covers at most a quarter of the sample (the
  paper reports about 1:4), fits with its cut bands (and, for several tiles, with room for the
  other tiles' positions), and is large without being elongated (:func:`period_candidates`).
- **Overlap errors** (eq. 1): ``psi_u(r) = |Y(r) - Y(r + U)|^2`` and ``psi_v(r) = |Y(r) -
  Y(r + V)|^2`` on the reference image (all channels).
- **Optimal vertex** ``r*``: the admissible origin with the smallest ``psi_u + psi_v`` summed
  over a 5 x 5 neighbourhood.
- **Optimal cuts**: each cut runs from ``r*`` to ``r* + V`` (the ``U`` cut) or ``r* + U``, in a
  band of ``+-band`` pixels around the rhomboid's edge, on a grid of one step per pixel along
  the edge and one pixel across it (a move changes the offset by at most one pixel per step);
  the cheapest path through the overlap error is found with scipy's Dijkstra. A cut is an
  offset ``f(t)`` of the edge in lattice coordinates, periodic because it starts and ends at
  the vertices, so the two cuts combine into one tile without special cases at the corners.
- **Tile content**: every residue class of the tile lattice (one texel of the tile) takes the
  sample texel of the rhomboid, moved by ``U`` and/or ``V`` to the side of the cuts it belongs
  to; within about ``2 sigma`` of a cut it is blended with the texel on the other side
  (Gaussian profile, ``sigma`` = 1 px by default), as quilting blends its cuts.
- **Multiple tiles** (paper: "identical tile borders but different content"): tile ``k > 0``
  takes its interior from the rhomboid moved by a small lattice vector ``i u + j v`` (the most
  similar positions first, by SSD on the reference image), and its border, the texels less
  than ``border`` pixels (Euclidean, to the nearest texel next to another cell) from the cut
  tile's edge, from tile 0; a linear ramp of ``ramp`` pixels joins the two. (Simpler than the
  paper's joint optimal cut of the stacked rhomboids.) Borders are therefore identical, and
  any tile may follow any other.
- **Storage**: a tile is stored as its lattice's Hermite normal form rectangle ``h x w`` (the
  lattice has the basis ``(h, s)``, ``(0, w)``), so every tile is a plain array and rendering
  is slice copies (one tile) or a per-texel gather (several); ``representative`` gives, for
  every stored texel, its position in the cut tile relative to ``r*``, which decides the
  lattice cell a surface texel belongs to.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import scipy  # submodules load on first use, not at every btf command (test_layout: HEAVY)

from tasks.errors import InvalidParameter
from tasks.lattice import hermite, lattice_cells, lattice_coordinates
from tasks.prescription import to_csr

TERMS = 8


@dataclass(frozen=True)
class RollerParams:
    """Tile count, periods per tile edge (``None``: automatic), cut band, blend, border."""

    tiles: int = 1
    periods: tuple[int, int] | None = None
    band: int = 4
    sigma: float = 1.0
    border: int = 4
    ramp: int = 4
    max_seam: float = 1.3
    attempts: int = 16

    def __post_init__(self):
        def refuse(name: str, message: str):
            raise InvalidParameter(name, message)

        if self.tiles < 1:
            refuse("tiles", f"tiles must be at least 1, got {self.tiles}")
        if self.periods is not None and min(self.periods) < 1:
            refuse("periods", f"periods must be at least 1, got {self.periods}")
        if self.band < 1:
            refuse("band", f"band must be at least 1, got {self.band}")
        if not 0.25 <= self.sigma <= 8:
            refuse("sigma", f"sigma must be between 0.25 and 8, got {self.sigma}")
        if not self.max_seam > 0 or self.attempts < 1:
            refuse("max_seam", f"max_seam must be positive and attempts at least 1, got "
                               f"{self.max_seam} and {self.attempts}")
        if self.border < 3 * self.sigma or self.ramp < 1:
            refuse("border", f"border must be at least 3 sigma = {3 * self.sigma:g} (the blend "
                             "across a cut stays inside it) and ramp at least 1")


@dataclass
class RollerPlan:
    """A planned tile set: lattice, layout, cuts and one prescription per tile."""

    U: tuple[int, int]
    V: tuple[int, int]
    hnf: tuple[int, int, int]  # h, w, shear s: basis (h, s), (0, w)
    origin: tuple[int, int]
    offsets: list[tuple[int, int]]  # per tile: its interior's shift from tile 0's
    cut_u: np.ndarray  # offsets (px across the edge) of the U cut at each step along V
    cut_v: np.ndarray
    index: np.ndarray  # (tiles, h * w, TERMS) int32, -1 unused
    weight: np.ndarray  # (tiles, h * w, TERMS) float32
    representative: np.ndarray  # (h, w, 2) int64, position in the cut tile relative to origin
    periods: tuple[int, int] = (1, 1)
    check: tuple[float, float] | None = None  # seam and structure of its borders (see below)

    @property
    def tile_shape(self) -> tuple[int, int]:
        """Stored tile size ``(h, w)``."""
        return self.hnf[0], self.hnf[1]

    @property
    def area(self) -> int:
        """Texels per tile (the lattice's determinant)."""
        return self.hnf[0] * self.hnf[1]


def _extent(U, V, margin_s: float, margin_t: float) -> tuple[np.ndarray, np.ndarray]:
    """Min and max ``(dy, dx)`` of the rhomboid extended by the margins (lattice units)."""
    corners = np.array([[s, t] for s in (-margin_s, 1 + margin_s)
                        for t in (-margin_t, 1 + margin_t)])
    pts = corners @ np.array([U, V], float)
    return np.floor(pts.min(axis=0)).astype(int), np.ceil(pts.max(axis=0)).astype(int)


def _margins(U, V, params: RollerParams) -> tuple[float, float, float, float]:
    det = abs(U[0] * V[1] - U[1] * V[0])
    width_u = det / math.hypot(*V)  # tile width across the cut along V
    width_v = det / math.hypot(*U)
    reach = params.band + 3 * params.sigma + 2
    return reach / width_u, reach / width_v, width_u, width_v


def _admissible(shape, U, V, params: RollerParams, shifts=((0, 0),)) -> tuple[range, range]:
    """Origins for which the extended rhomboid (at every shift) lies inside the sample."""
    ms, mt, _, _ = _margins(U, V, params)
    lo, hi = _extent(U, V, ms, mt)
    sh = np.asarray(shifts)
    lo = lo + sh.min(axis=0)
    hi = hi + sh.max(axis=0)
    return range(-lo[0], shape[0] - hi[0]), range(-lo[1], shape[1] - hi[1])


def _lattice_shifts(u, v, reach: int = 6) -> list[tuple[int, int]]:
    """Small lattice vectors ``i u + j v`` (rounded), shortest first, excluding 0."""
    out = {}
    for i in range(-reach, reach + 1):
        for j in range(-reach, reach + 1):
            if (i, j) != (0, 0):
                d = tuple(int(c) for c in np.rint(i * np.asarray(u) + j * np.asarray(v)))
                out.setdefault(d, math.hypot(*d))
    return sorted(out, key=lambda d: (out[d], d))


DRIFT = 0.2  # texels: tile vectors this close to whole periods leave no visible jog


def period_candidates(shape, u, v, params: RollerParams) -> list[tuple[int, int]]:
    """``(a, b)`` for large rhomboids, at most a quarter of the sample, that fit, best first.

    The tile vectors are ``a u``, ``b v`` rounded to whole texels; the rounding is the drift
    the cuts must absorb each tile (a jog in every line of a noiseless pattern: a checkerboard
    at 0.5 texel measured 3.7x its sample's own period-to-period distance along the cuts).
    Among those that fit and are at least a quarter the size of the largest (by ``area *
    sqrt(short side / long side)``: large but not elongated), the ones whose drift is at most
    :data:`DRIFT` texels (else the least drift), and among those the largest.
    """
    lu, lv = math.hypot(*u), math.hypot(*v)
    limit = shape[0] * shape[1] / 4.0
    shifts = [(0, 0), *_lattice_shifts(u, v)[: 4 * (params.tiles - 1)]]
    candidates = []
    for a in range(1, int(max(shape) / lu) + 2):
        for b in range(1, int(max(shape) / lv) + 2):
            U = tuple(int(c) for c in np.rint(a * np.asarray(u)))
            V = tuple(int(c) for c in np.rint(b * np.asarray(v)))
            area = abs(U[0] * V[1] - U[1] * V[0])
            if area == 0 or (area > limit and (a, b) != (1, 1)):
                continue
            ys, xs = _admissible(shape, U, V, params, shifts)
            if len(ys) == 0 or len(xs) == 0:
                continue
            sides = sorted((math.hypot(*U), math.hypot(*V)))
            drift = max(math.hypot(*(np.asarray(U) - a * np.asarray(u))),
                        math.hypot(*(np.asarray(V) - b * np.asarray(v))))
            candidates.append((area * math.sqrt(sides[0] / sides[1]), area, drift, (a, b)))
    if not candidates:
        raise ValueError(f"the sample ({shape[0]} x {shape[1]}) is too small for one period "
                         f"u = {tuple(round(c, 1) for c in u)}, v = "
                         f"{tuple(round(c, 1) for c in v)} plus the cut bands")
    largest = max(c[0] for c in candidates)
    ranked = sorted((c for c in candidates if c[0] >= largest / 4),
                    key=lambda c: (max(c[2] - DRIFT, 0.0), -c[0], -c[1]))
    # then the smaller ones, largest first: a gradient-lit sample's periods differ less nearby
    ranked += sorted((c for c in candidates if c[0] < largest / 4), key=lambda c: -c[0])
    return [c[3] for c in ranked]


def _overlap_error(img: np.ndarray, shift) -> np.ndarray:
    """``|Y(r) - Y(r + shift)|^2`` summed over channels (inf where ``r + shift`` is outside)."""
    h, w = img.shape[:2]
    dy, dx = shift
    out = np.full((h, w), np.inf)
    ys = slice(max(0, -dy), min(h, h - dy))
    xs = slice(max(0, -dx), min(w, w - dx))
    ys2 = slice(ys.start + dy, ys.stop + dy)
    xs2 = slice(xs.start + dx, xs.stop + dx)
    out[ys, xs] = np.sum((img[ys, xs] - img[ys2, xs2]) ** 2, axis=-1)
    return out


def _cut(error: np.ndarray, origin, along, across_unit, steps: int, band: int) -> np.ndarray:
    """Offsets (pixels across the edge) of the cheapest path along an edge of the tile.

    The path runs from ``origin`` to ``origin + along`` in ``steps + 1`` rows, with offset 0 at
    both ends, changing by at most one pixel per row.
    """
    rows = np.arange(steps + 1)[:, None] / steps
    offs = np.arange(-band, band + 1)[None, :]
    pts = (np.asarray(origin)[None, None, :] + rows[..., None] * np.asarray(along)
           + offs[..., None] * np.asarray(across_unit))
    iy = np.clip(np.rint(pts[..., 0]).astype(int), 0, error.shape[0] - 1)
    ix = np.clip(np.rint(pts[..., 1]).astype(int), 0, error.shape[1] - 1)
    cost = error[iy, ix] + 1e-9
    n_off = 2 * band + 1
    ids = np.arange((steps + 1) * n_off).reshape(steps + 1, n_off)
    src, dst, wts = [], [], []
    for d in (-1, 0, 1):
        a = ids[:-1, max(0, -d) : n_off - max(0, d)]
        b = ids[1:, max(0, d) : n_off - max(0, -d)]
        c = cost[1:, max(0, d) : n_off - max(0, -d)]
        ok = np.isfinite(c)
        src.append(a[ok])
        dst.append(b[ok])
        wts.append(c[ok])
    edges = (np.concatenate(wts), (np.concatenate(src), np.concatenate(dst)))
    graph = scipy.sparse.coo_matrix(edges, shape=(ids.size, ids.size)).tocsr()
    start, end = ids[0, band], ids[-1, band]
    _, pred = scipy.sparse.csgraph.dijkstra(graph, indices=start, return_predecessors=True)
    path = np.zeros(steps + 1, int)
    node = end
    if pred[node] < 0:
        return path.astype(float)  # no finite path (should not happen inside the sample)
    while node >= 0:
        i, j = divmod(int(node), n_off)
        path[i] = j - band
        node = pred[node]
    return path.astype(float)


def _feather(frac: np.ndarray, cut: np.ndarray, along: np.ndarray, width: float,
             sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Main and neighbour shifts across a cut, and the neighbour's weight.

    ``frac`` is the texel's coordinate across the cut (lattice units, ``[0, 1)``), ``along`` its
    coordinate along it; ``cut`` the cut's offsets in pixels at ``len(cut)`` steps.
    """
    f = np.interp(along, np.linspace(0.0, 1.0, cut.size), cut) / width
    rel = frac - f
    main = -np.floor(rel)
    inside = (rel + main) * width  # pixels from the tile's first edge, [0, width)
    near_first = inside <= width - inside
    dist = np.where(near_first, inside, width - inside)
    other = np.where(near_first, main + 1, main - 1)
    alpha = 0.5 * scipy.special.erfc((dist + 0.5) / (sigma * math.sqrt(2.0)))
    alpha = np.where(alpha < 1e-3, 0.0, alpha)
    return main.astype(np.int64), other.astype(np.int64), alpha


class RollerSeamError(ValueError):
    """No tile of the periods tried kept its borders within the bound."""


def plan_roller(image: np.ndarray, u, v, params: RollerParams) -> RollerPlan:
    """Plan the tile set on ``image`` (``(y, x, channel)``) for periodicity vectors ``u``, ``v``.

    Every tile planned is checked (:func:`border_check`); while its borders stand out more
    than ``params.max_seam`` times what the sample has there (seam) or its own
    period-to-period variation (structure), the next periods of :func:`period_candidates`
    are tried, at most ``params.attempts`` (given ``periods``: only those). The first that
    passes is returned; when none does, :class:`RollerSeamError` names the best and its
    figures.
    """
    from tasks.seams import PatchExemplar

    img = np.asarray(image, np.float64)
    if img.ndim == 2:
        img = img[..., None]
    if min(math.hypot(*u), math.hypot(*v)) < 2.0:
        raise ValueError(f"the periodicity vectors {tuple(u)} and {tuple(v)} must be at least "
                         "2 texels long")
    periods = ([params.periods] if params.periods else
               period_candidates(img.shape[:2], u, v, params)[: params.attempts])
    exemplar = PatchExemplar(img.astype(np.float32))
    best = None
    for ab in periods:
        plan = _plan(img, u, v, ab, params)
        plan = replace(plan, check=border_check(img, plan, exemplar))
        if best is None or max(plan.check) < max(best.check):
            best = plan
        if max(plan.check) <= params.max_seam:
            return plan
    raise RollerSeamError(
        f"after {len(periods)} tile size(s), the best tile ({best.periods[0]} x "
        f"{best.periods[1]} periods) still has borders standing out {max(best.check):.2f}x "
        f"from the sample's own variation (seam {best.check[0]:.2f}, structure "
        f"{best.check[1]:.2f}; bound {params.max_seam}): the sample may not be periodic "
        "enough (an illumination gradient, a drifting lattice); try btf quilt, other "
        "--periods, or allow more with a larger --max-seam")


CHECK_REGION = (128, 512)  # texels per side of the surface a tile is checked on


def border_check(image: np.ndarray, plan: RollerPlan, exemplar) -> tuple[float, float]:
    """Seam and structure of a tile set's borders (:func:`tasks.seams.cell_figures`).

    Tile 0 (every tile has its borders) is laid over a surface of about two tiles per side
    and the borders of its lattice cells measured: the seam against the sample's pairs at
    the same places, the structure against its own period-to-period variation.
    """
    from tasks.placement import lattice_gather
    from tasks.seams import PATCH, cell_figures

    flat = image.reshape(-1, image.shape[-1])
    stored = np.einsum("nk,nkc->nc", plan.weight[0], flat[np.maximum(plan.index[0], 0)])
    stored = stored.reshape(1, *plan.tile_shape, image.shape[-1])
    main = plan.index[0][np.arange(plan.index.shape[1]), np.argmax(plan.weight[0], axis=1)]
    extent = 2 * (max(abs(c) for c in plan.U) + max(abs(c) for c in plan.V)) + 2 * PATCH
    n = int(np.clip(extent, *CHECK_REGION))
    basis = (plan.U, plan.V)
    surface = lattice_gather(stored, 0, 0, n, n, hnf=plan.hnf, basis=basis,
                             representative=plan.representative)
    cells = lattice_cells(0, 0, n, n, hnf=plan.hnf, basis=basis,
                          representative=plan.representative)
    sources = lattice_gather(main.reshape(1, *plan.tile_shape, 1), 0, 0, n, n, hnf=plan.hnf,
                             basis=basis, representative=plan.representative)[..., 0]
    return cell_figures(exemplar, surface, cells, reach=PATCH / 2, sources=sources)


def _tile_vectors(u, v, periods: tuple[int, int]
                  ) -> tuple[tuple[int, int], tuple[int, int], tuple[int, int]]:
    """The tile vectors ``U = a u``, ``V = b v`` rounded, ordered positively, and ``(a, b)``."""
    a, b = periods
    U = tuple(int(c) for c in np.rint(a * np.asarray(u)))
    V = tuple(int(c) for c in np.rint(b * np.asarray(v)))
    if U[0] * V[1] - U[1] * V[0] == 0:
        raise ValueError(f"the tile vectors {U} and {V} are parallel")
    if U[0] * V[1] - U[1] * V[0] < 0:
        U, V = V, U
        a, b = b, a
    return U, V, (a, b)


def _optimal_vertex(img: np.ndarray, U, V, params: RollerParams
                    ) -> tuple[tuple[int, int], np.ndarray, np.ndarray]:
    """The admissible origin ``r*`` of least overlap error, and the errors ``psi_u, psi_v``."""
    shape = img.shape[:2]
    ys, xs = _admissible(shape, U, V, params)
    if len(ys) == 0 or len(xs) == 0:
        raise ValueError(f"the sample ({shape[0]} x {shape[1]}) is too small for a tile "
                         f"spanned by {U} and {V} plus its cut bands")
    psi_u, psi_v = _overlap_error(img, U), _overlap_error(img, V)
    score = scipy.ndimage.uniform_filter(np.where(np.isfinite(psi_u + psi_v), psi_u + psi_v, 1e30),
                                   size=5)
    sub = score[ys.start : ys.stop, xs.start : xs.stop]
    oy, ox = np.unravel_index(int(np.argmin(sub)), sub.shape)
    return (ys.start + int(oy), xs.start + int(ox)), psi_u, psi_v


def _optimal_cuts(psi_u: np.ndarray, psi_v: np.ndarray, origin, U, V, band: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The ``U`` cut (along ``V``) and the ``V`` cut (along ``U``) through the overlap errors."""
    det = U[0] * V[1] - U[1] * V[0]
    across_u = np.array([V[1], -V[0]], float) * (det / abs(det)) / math.hypot(*V)
    across_v = np.array([-U[1], U[0]], float) * (det / abs(det)) / math.hypot(*U)
    # unit normals pointing into the tile from its U-cut edge (t axis) and V-cut edge (s axis)
    cut_u = _cut(psi_u, origin, V, across_u, max(1, round(math.hypot(*V))), band)
    cut_v = _cut(psi_v, origin, U, across_v, max(1, round(math.hypot(*U))), band)
    return cut_u, cut_v


def _blend_terms(frac: np.ndarray, cut_u: np.ndarray, cut_v: np.ndarray, width_u: float,
                 width_v: float, sigma: float) -> tuple[np.ndarray, np.ndarray, list]:
    """The main shifts ``mu, mv`` of every texel and its four blend terms across the cuts.

    A term is ``(shift along U, shift along V, weight)``.
    """
    mu, ou, alpha = _feather(frac[:, 0], cut_u, frac[:, 1], width_u, sigma)
    mv, ov, beta = _feather(frac[:, 1], cut_v, frac[:, 0], width_v, sigma)
    terms = [(mu, mv, (1 - alpha) * (1 - beta)), (ou, mv, alpha * (1 - beta)),
             (mu, ov, (1 - alpha) * beta), (ou, ov, alpha * beta)]
    return mu, mv, terms


def _prescriptions(terms: list, gamma: np.ndarray, offsets, origin, base: np.ndarray, Ua, Va,
                   shape: tuple[int, int], tiles: int, texels: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Index and weight of every tile's texels: tile 0's terms, and others' interiors blended.

    Tile ``k > 0`` takes ``1 - gamma`` of tile 0's terms and ``gamma`` of its own, moved by
    its offset; duplicates are summed (:func:`_compact`).
    """
    index = np.full((tiles, texels, TERMS), -1, np.int32)
    weight = np.zeros((tiles, texels, TERMS), np.float32)
    for k, off in enumerate(offsets):
        parts = [(terms, 1.0 - gamma if k else np.ones_like(gamma), (0, 0))]
        if k:
            parts.append((terms, gamma, off))
        col = 0
        for group, scale, shift in parts:
            for su, sv, wt in group:
                pos = (np.asarray(origin) + base + su[:, None] * Ua + sv[:, None] * Va
                       + np.asarray(shift))
                index[k, :, col] = pos[:, 0] * shape[1] + pos[:, 1]
                weight[k, :, col] = wt * scale
                col += 1
        unused = weight[k] == 0
        index[k][unused] = -1
    _compact(index, weight, shape[0] * shape[1])
    return index, weight


def _plan(img: np.ndarray, u, v, periods: tuple[int, int], params: RollerParams
          ) -> RollerPlan:
    """The tile set of ``periods`` ``(a, b)`` (see the module)."""
    shape = img.shape[:2]
    U, V, (a, b) = _tile_vectors(u, v, periods)
    shifts = _lattice_shifts(u, v)
    origin, psi_u, psi_v = _optimal_vertex(img, U, V, params)
    _, _, width_u, width_v = _margins(U, V, params)
    cut_u, cut_v = _optimal_cuts(psi_u, psi_v, origin, U, V, params.band)

    h, w, s = hermite(U, V)
    yy, xx = np.mgrid[0:h, 0:w]
    stored = np.stack([yy, xx], -1).reshape(-1, 2)
    cell, frac = lattice_coordinates(stored, U, V)
    base = stored - cell @ np.array([U, V])  # the texel of the rhomboid, relative to origin
    mu, mv, terms = _blend_terms(frac, cut_u, cut_v, width_u, width_v, params.sigma)
    Ua, Va = np.array(U), np.array(V)
    representative = (base + mu[:, None] * Ua + mv[:, None] * Va).reshape(h, w, 2)
    edge = _edge_distance(representative, U, V, (h, w, s))

    offsets = [(0, 0)]
    if params.tiles > 1:
        offsets += _similar_shifts(img, origin, base, mu, mv, Ua, Va, shape, U, V, params,
                                   shifts)
    gamma = np.clip((edge - params.border) / params.ramp, 0.0, 1.0)
    index, weight = _prescriptions(terms, gamma, offsets, origin, base, Ua, Va, shape,
                                   params.tiles, h * w)
    return RollerPlan(U=U, V=V, hnf=(h, w, s), origin=origin, offsets=offsets, cut_u=cut_u,
                      cut_v=cut_v, index=index, weight=weight, representative=representative,
                      periods=(a, b))


def _edge_distance(representative: np.ndarray, U, V, hnf) -> np.ndarray:
    """Per stored texel, the distance (pixels) from its place in the cut tile to the edge.

    That is the Euclidean distance to the nearest texel with a 4-neighbour in another cell.
    """
    rep = representative.reshape(-1, 2)
    lo, hi = rep.min(axis=0) - 2, rep.max(axis=0) + 3
    cells = lattice_cells(int(lo[0]), int(lo[1]), int(hi[0] - lo[0]), int(hi[1] - lo[1]),
                          hnf=hnf, basis=(U, V), representative=representative)
    other = np.zeros(cells.shape[:2], bool)
    for axis in (0, 1):
        step = np.any(np.diff(cells, axis=axis) != 0, axis=-1)
        lead = [slice(None)] * 2
        lead[axis] = slice(1, None)
        other[tuple(lead)] |= step
        lead[axis] = slice(None, -1)
        other[tuple(lead)] |= step
    dist = scipy.ndimage.distance_transform_edt(~other)
    return dist[rep[:, 0] - lo[0], rep[:, 1] - lo[1]]


def _similar_shifts(img, origin, base, mu, mv, Ua, Va, shape, U, V, params, shifts):
    """The ``tiles - 1`` lattice shifts whose rhomboid is most like tile 0's (SSD)."""
    pos = np.asarray(origin) + base + mu[:, None] * Ua + mv[:, None] * Va
    ref = img[pos[:, 0], pos[:, 1]]
    ranked = []
    for d in shifts:
        ys, xs = _admissible(shape, U, V, params, [(0, 0), d])
        if origin[0] in ys and origin[1] in xs:
            moved = img[pos[:, 0] + d[0], pos[:, 1] + d[1]]
            ranked.append((float(np.sum((moved - ref) ** 2)), d))
    ranked.sort()
    if len(ranked) < params.tiles - 1:
        raise ValueError(f"only {len(ranked)} other tile position(s) fit in the sample; ask for "
                         f"at most {len(ranked) + 1} tiles or smaller ones (--periods)")
    return [d for _, d in ranked[: params.tiles - 1]]


def _compact(index: np.ndarray, weight: np.ndarray, samples: int) -> None:
    """Sum duplicate indices within each row, drop zero weights, pad last (in place)."""
    for k in range(index.shape[0]):
        m = to_csr(index[k], weight[k], samples)
        m.sum_duplicates()
        m.eliminate_zeros()
        counts = np.diff(m.indptr)
        rows = np.repeat(np.arange(counts.size), counts)
        cols = np.arange(m.nnz) - np.repeat(m.indptr[:-1], counts)
        index[k] = -1
        weight[k] = 0.0
        index[k][rows, cols] = m.indices
        weight[k][rows, cols] = m.data
