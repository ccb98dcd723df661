"""Do the borders of a synthesized texture stand out from its inside? Two measures per border.

A periodic texture's wrap, the borders of a mosaic of corner tiles and the tile grid of a
tiled synthesis are lines the eye finds when they differ from the rest of the texture. Given
an image and its border lines (:class:`Borders`), every line gets two ratios, each against the
image's *inside* (everything farther than ``reach`` from every line), so that 1 means "as
good as the rest of this texture" and a bound holds per line, not on average:

- **seam**: the mean absolute difference of the texel pairs across the line (mean over
  channels) over the mean of all pairs in the same direction that cross no line (a texture
  with vertical lines has large differences across columns and small ones across rows). It
  sees a step or a line of texels that do not continue; it misses a pattern that breaks a
  few texels away from the line, and a feathered blend that hides a break from neighbour
  differences.
- **structure**: patch coherence (the completeness term of bidirectional similarity, Simakov
  et al. 2008; Texture Optimization's energy, Kwatra et al. 2005): the RMS distance of every
  ``p x p`` patch of the image to its nearest patch of the sample. Patches that straddle a
  break of the pattern (rows of bricks that do not continue, a mortar line doubled beside
  another, a blend of two misaligned motifs) do not occur in the sample and lie far from
  it; copied texture lies at 0. A line's figure is the mean over the patches centred within
  ``reach`` of it, over the mean of the patches whose centres are farther than ``reach``
  from every line (a tile's check takes that mean on every other patch of the grid each
  way: :func:`structure_ratios`' ``sparse_inside``). The inside of a quilted texture holds
  its ordinary patch cuts, so a ratio near 1 says the borders are joined as well as the
  patches inside are.

The nearest patches are found on a PCA of the patches (12 dimensions, scipy's k-d tree,
approximate with ``eps = 2``: each candidate within three times the distance of the exact one
in PCA space) and the ``candidates`` (12) nearest are re-ranked at full dimension. Against an
exact brute-force search at full dimension, on 40 checks per texture recorded while planning
tile sets of the brick, moon and gravel photos, this is as close as an exact k-d tree search
re-ranking 8 (a patch's distance on average 2.6%, 8.6% and 6.4% above the exact one, against
2.8%, 9.2% and 6.4%; a check's worst ratio off by 0.015, 0.065 and 0.010 on average, against
0.017, 0.063 and 0.013) and 3.8-6x faster; on a 240^2 tile's check its searches take 0.67x
the time of ``eps = 1`` with 8 candidates (``btf bench quilt --search-checks 40``,
BENCHMARKS.md).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

PATCH = 16  # structure patches: larger than a mortar line or a thread, smaller than a block
STRIDE = 3  # patch grid of the structure measure (texels)
SEARCH_EPS = 2.0  # the k-d tree's approximation (see the module)
SEARCH_CANDIDATES = 12  # nearest in PCA space re-ranked at full dimension (see the module)
_REPEAT_CANDIDATES = 32  # exact nearest patches searched for one not overlapping its query
SPARSE_INSIDE_LEAST = 400  # patches a thinned inside keeps at least (structure_ratios)
_BATCH = 4096  # queries (and sample rows) per batch: bounds the gathered patches' memory
_ONE_THREAD = 1024  # queries searched on the calling thread alone (a tile's check: its own
# threads cost more than they gain there, and tiles may be checked in threads of their own)


def channel_groups(image: np.ndarray) -> np.ndarray:
    """Each channel's group: channels an ``(h, w, c)`` image holds bit for bit alike share one.

    Groups are numbered by their first channels, from 0. A grey photo's BTF repeats one channel
    three times (its reference image too): searches over its patches then compare one channel
    where they compared three (:class:`PatchExemplar`,
    :class:`tasks.quilting.CandidateSearch`).
    """
    firsts: list[int] = []
    group = np.empty(image.shape[-1], np.int64)
    for c in range(image.shape[-1]):
        same = (g for g, f in enumerate(firsts) if np.array_equal(image[..., f], image[..., c]))
        group[c] = next(same, len(firsts))
        if group[c] == len(firsts):
            firsts.append(c)
    return group


@dataclass(frozen=True)
class Borders:
    """Border lines of an image.

    ``rows``: horizontal lines, each between texel rows ``y - 1`` and ``y``; ``cols`` the
    same for vertical lines. With ``wrap`` the image is a torus (a periodic texture): line 0
    is its wrap, between the last row (column) and the first. With ``region``
    ``(y0, y1, x0, x1)`` only that part of the image is judged (a tile framed by its
    neighbours, :meth:`framed`): the lines' segments along it, their sides within it, and its
    inside.
    """

    rows: tuple[int, ...]
    cols: tuple[int, ...]
    wrap: bool = False
    region: tuple[int, int, int, int] | None = None

    @staticmethod
    def periodic() -> Borders:
        """The wrap of a periodic texture."""
        return Borders((0,), (0,), wrap=True)

    @staticmethod
    def framed(tile: tuple[int, int], margin: int) -> Borders:
        """A tile in the middle of a frame of ``margin`` texels: its four borders."""
        th, tw = tile
        return Borders((margin, margin + th), (margin, margin + tw),
                       region=(margin, margin + th, margin, margin + tw))

    def within(self, shape: tuple[int, int]) -> tuple[slice, slice]:
        """The judged part of an image of ``shape``."""
        y0, y1, x0, x1 = self.region or (0, shape[0], 0, shape[1])
        return slice(y0, y1), slice(x0, x1)

    def lines(self) -> list[tuple[str, int]]:
        """Every line as ``("row", y)`` or ``("col", x)``."""
        return [("row", y) for y in self.rows] + [("col", x) for x in self.cols]


@dataclass(frozen=True)
class BorderFigures:
    """Seam and structure ratios of every border line (see the module), and the worst."""

    lines: tuple[tuple[str, int], ...]
    seam: tuple[float, ...]
    structure: tuple[float, ...]

    @property
    def worst_seam(self) -> float:
        """The largest seam ratio over the lines."""
        return max(self.seam)

    @property
    def worst_structure(self) -> float:
        """The largest structure ratio over the lines."""
        return max(self.structure)

    @property
    def worst(self) -> float:
        """The larger of the two worst ratios: what a bound on both must hold."""
        return max(self.worst_seam, self.worst_structure)

    def worst_line(self) -> str:
        """The line with the largest ratio of either kind, e.g. ``"row 0 (structure 1.41)"``."""
        kind, ratios = max((("seam", self.seam), ("structure", self.structure)),
                           key=lambda kr: max(kr[1]))
        k = int(np.argmax(ratios))
        return f"{self.lines[k][0]} {self.lines[k][1]} ({kind} {ratios[k]:.2f})"


def _offsets(centres: np.ndarray, line: int, n: int, wrap: bool) -> np.ndarray:
    """Signed distance of centre lines (positions between texels) from a border line."""
    d = centres - line
    if wrap:
        d = (d + n / 2) % n - n / 2
    return d


def _near(centres: np.ndarray, lines: tuple[int, ...], n: int, wrap: bool, reach: float
          ) -> np.ndarray:
    """Whether each centre lies within ``reach`` of some line."""
    near = np.zeros(centres.shape, bool)
    for line in lines:
        near |= np.abs(_offsets(centres, line, n, wrap)) <= reach
    return near


def seam_ratios(image: np.ndarray, borders: Borders) -> tuple[float, ...]:
    """Per line: mean absolute difference across it over the rest's, in its direction.

    The rest: the pairs of the judged part that cross no line in the same direction
    (horizontal lines: vertical pairs).
    """
    image = np.asarray(image, np.float64)
    if image.ndim == 2:
        image = image[..., None]
    h, w = image.shape[:2]
    if borders.wrap:
        dy = np.abs(image - np.roll(image, 1, axis=0)).mean(-1)  # dy[y]: rows y - 1 and y
        dx = np.abs(image - np.roll(image, 1, axis=1)).mean(-1)
    else:
        dy = np.pad(np.abs(np.diff(image, axis=0)).mean(-1), ((1, 0), (0, 0)),
                    constant_values=np.nan)
        dx = np.pad(np.abs(np.diff(image, axis=1)).mean(-1), ((0, 0), (1, 0)),
                    constant_values=np.nan)
    ys, xs = borders.within((h, w))
    on_row = np.isin(np.arange(h), borders.rows)
    on_col = np.isin(np.arange(w), borders.cols)
    # pairs inside the judged part (dy[y] pairs rows y - 1, y: its first row's reach out),
    # each direction on its own: a line is compared with the pairs that cross it the same way
    inner_dy = dy[ys][1:][~on_row[ys][1:]][:, xs]
    inner_dx = dx[:, xs][:, 1:][ys][:, ~on_col[xs][1:]]
    scale_y, scale_x = (max(float(np.nanmean(p)), 1e-12) for p in (inner_dy, inner_dx))
    return tuple([float(dy[y, xs].mean()) / scale_y for y in borders.rows]
                 + [float(dx[ys, x].mean()) / scale_x for x in borders.cols])


class PatchExemplar:
    """The patches of a sample, searchable for the nearest patch of any image.

    Channels the sample holds bit for bit alike (:func:`channel_groups`: a grey photo's
    three) are searched once, scaled by the square root of their count: the distances over
    every channel, for any query (its spread within each group is added back), up to
    rounding. The rounding of the PCA's coordinates differs, so the approximate k-d tree may
    return other candidates for a few queries (11 of 200 random ones at patch 6).

    Parameters
    ----------
    sample
        ``(h, w[, channels])`` the exemplar (e.g. quilting's reference image).
    patch
        Patch side ``p`` in texels.
    dims
        PCA dimensions of the k-d tree search before re-ranking at full dimension.
    candidates
        Nearest patches in PCA space re-ranked per query.
    eps
        The k-d tree's approximation (:meth:`scipy.spatial.cKDTree.query`): each candidate
        is within ``1 + eps`` times the distance of the exact one in PCA space.
    """

    def __init__(self, sample: np.ndarray, *, patch: int = PATCH, dims: int = 12,
                 candidates: int = SEARCH_CANDIDATES, eps: float = SEARCH_EPS):
        from scipy.linalg import eigh
        from scipy.spatial import cKDTree

        sample = np.ascontiguousarray(sample, np.float32)
        if sample.ndim == 2:
            sample = sample[..., None]
        self.sample = sample
        if min(sample.shape[:2]) < patch:
            raise ValueError(f"the sample ({sample.shape[0]} x {sample.shape[1]}) is smaller "
                             f"than a structure patch ({patch})")
        self.patch, self.candidates = patch, candidates
        self.eps = eps
        self.windows = sliding_window_view(sample, (patch, patch), axis=(0, 1))
        ny, nx = self.windows.shape[:2]
        channels = sample.shape[-1]
        # channels held alike count once, weighted by how many they are: distances over the
        # groups' first channels scaled by sqrt(count) are those over every channel
        self.group = channel_groups(sample)
        firsts = np.unique(self.group, return_index=True)[1]  # each group's first channel
        self._scale = np.sqrt(np.bincount(self.group)).astype(np.float32)
        self._searched = (sample if len(firsts) == channels else
                          np.ascontiguousarray(sample[..., firsts] * self._scale))
        # the PCA basis from an evenly spread subset (deterministic: no random state)
        step = max(1, int(np.sqrt(ny * nx / 4096)))
        subset = self.windows[::step, ::step].reshape(-1, channels, patch * patch)
        self.mean = subset.mean(axis=0).reshape(-1)
        grouped = (subset[:, firsts] * self._scale[:, None]).reshape(len(subset), -1)
        centred = grouped - grouped.mean(axis=0)
        # the leading eigenvectors of the covariance: its right singular vectors (an SVD of
        # the subset takes 1.2 s for 16^2 x 3 patches: an exemplar in 1.9 s against 0.6 s);
        # from a float32 product (float64's takes 0.08 s): the leading 12 lie within 5e-6
        # rad of float64's on brick, moon and gravel. Over the groups: a grey sample's
        # eigenvectors over every channel are these, each group's part divided by its scale
        # and repeated over its channels (0.17 -> 0.09 s for a 256^2 photo's exemplar, in a plan)
        n = centred.shape[1]
        keep = min(dims, n, len(centred))
        _, vectors = eigh(centred.T @ centred, subset_by_index=(n - keep, n - 1))
        vectors = vectors[:, ::-1].reshape(len(firsts), -1, keep) / self._scale[:, None, None]
        self.basis = np.ascontiguousarray(vectors[self.group].reshape(-1, keep), np.float32)
        # the same basis and mean for patches flattened rows first, (p, p, channels): the
        # order sliding windows over all three axes give, and the re-ranking reads
        self._rows_basis = np.ascontiguousarray(
            self.basis.reshape(channels, patch, patch, -1).transpose(1, 2, 0, 3)
            .reshape(-1, self.basis.shape[1]))
        self._rows_mean = np.ascontiguousarray(
            self.mean.reshape(channels, patch, patch).transpose(1, 2, 0).reshape(-1),
            np.float32)
        self.tree = cKDTree(self._project_windows())
        self.width = nx
        contrast = float(np.sqrt(np.mean((sample - sample.mean(axis=(0, 1))) ** 2)))
        self.floor = max(0.02 * contrast, 1e-9)  # below this nothing is visible
        self._repeat = None

    @property
    def own_repeat(self) -> float:
        """How far the sample's patches lie from their nearest other patch (see below)."""
        if self._repeat is None:
            self._repeat = self._own_repeat()
        return self._repeat

    def _own_repeat(self, count: int = 1024) -> float:
        """How far the sample's patches lie from their nearest other patch.

        The median, over evenly spread patches, of the distance to the nearest patch that does
        not overlap it (among the k-d tree's candidates). The distances by
        :func:`tasks.quilt_kernels.nearest_ssd`, with a query's overlapping candidates replaced
        by one that does not: gathering the candidates' patches instead took 0.1-1.1 s on
        photos (1,024 x 32 patches of up to 24^2 x 3 texels), the kernel 0.03-0.2 s.
        """
        ny, nx = self.windows.shape[:2]
        p = self.patch
        step = max(1, int(np.sqrt(ny * nx / count)))
        ys, xs = (g.ravel() for g in np.mgrid[0:ny:step, 0:nx:step])
        patches = self.windows[ys, xs]  # (q, channels, p, p)
        k = min(_REPEAT_CANDIDATES, ny * nx)
        _, found = self.tree.query(self._project(patches.reshape(len(ys), -1)), k=k, workers=-1)
        fy, fx = np.divmod(found.reshape(len(ys), k), self.width)
        apart = (np.abs(fy - ys[:, None]) >= p) | (np.abs(fx - xs[:, None]) >= p)
        some = apart.any(axis=1)
        if not some.any():
            return 0.0
        first = apart.argmax(axis=1)[:, None]
        rows = np.arange(len(ys))[:, None]
        sy = np.where(apart, fy, fy[rows, first])[some]
        sx = np.where(apart, fx, fx[rows, first])[some]
        queries = np.ascontiguousarray(np.moveaxis(patches[some], 1, -1))  # (q, p, p, channels)
        return float(np.median(np.sqrt(self._nearest_ssd(queries, sy, sx)
                                       / patches[0].size)))

    def _nearest_ssd(self, queries: np.ndarray, sy: np.ndarray, sx: np.ndarray) -> np.ndarray:
        """:func:`tasks.quilt_kernels.nearest_ssd` over every channel, by the groups."""
        from tasks.quilt_kernels import grouped_patches, nearest_ssd  # numba

        if self._searched is self.sample:
            return nearest_ssd(self.sample, queries, sy, sx)
        grouped, rest = grouped_patches(queries, self.group, self._scale)
        return nearest_ssd(self._searched, grouped, sy, sx) + rest

    def _project_windows(self) -> np.ndarray:
        """Every window's PCA coordinates, ``(ny * nx, dims)`` float32, row by row.

        By FFT correlation of the sample with each basis patch in turn (25 ms on a 256^2
        photo, against 85 ms for a product with the windows copied out); memory: the
        sample's spectra and one basis patch's.
        """
        from scipy.fft import irfft2, next_fast_len, rfft2

        h, w, channels = self.sample.shape
        ny, nx = h - self.patch + 1, w - self.patch + 1
        # a circular correlation of the sample's size wraps only beyond the last window
        shape = (next_fast_len(h, real=True), next_fast_len(w, real=True))
        sample = rfft2(np.moveaxis(self.sample, -1, 0).astype(np.float64), shape)
        kernels = self.basis.T.reshape(-1, channels, self.patch, self.patch)  # (c, p, p) order
        offsets = self.mean.astype(np.float64) @ self.basis.astype(np.float64)
        out = np.empty((ny, nx, len(kernels)), np.float32)
        for k, kernel in enumerate(kernels):
            spectrum = np.sum(sample * np.conj(rfft2(kernel.astype(np.float64), shape)), axis=0)
            out[..., k] = irfft2(spectrum, shape)[:ny, :nx] - offsets[k]
        return out.reshape(ny * nx, -1)

    def _project(self, flat: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray((flat - self.mean) @ self.basis, np.float32)

    def distances(self, queries: np.ndarray) -> np.ndarray:
        """RMS distance of each ``(p, p, channels)`` query patch to its nearest."""
        out = np.empty(len(queries), np.float64)
        for i in range(0, len(queries), _BATCH):
            q = np.ascontiguousarray(queries[i : i + _BATCH], np.float32)
            flat = q.reshape(len(q), -1)
            k = min(self.candidates, self.tree.n)  # a small sample has fewer patches
            # the mean first: a product first would lose float32 digits to a large mean
            _, found = self.tree.query((flat - self._rows_mean) @ self._rows_basis, k=k,
                                       eps=self.eps,
                                       workers=1 if len(q) <= _ONE_THREAD else -1)
            sy, sx = np.divmod(found.reshape(len(q), k), self.width)
            out[i : i + _BATCH] = self._nearest_ssd(q, sy, sx)
        return np.sqrt(out / queries[0].size) if len(queries) else out

    def distance_map(self, image: np.ndarray, *, wrap: bool, stride: int = STRIDE,
                     within: tuple[slice, slice] | None = None,
                     measure: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Nearest-patch distances of an image's patches on a grid of ``stride``.

        Returns the ``(ny, nx)`` distances and the positions of the patches' centre lines
        (rows, columns: between texel ``c - 1`` and ``c``). With ``wrap`` the image is a
        torus and every position is a patch origin. With ``within`` (rows, columns) only the
        patches of the grid whose centre lines lie in that part (ends included) are measured:
        the rest of the grid is left out of all three. With ``measure``, a function of the
        centre lines ``(cy, cx)`` giving the ``(ny, nx)`` grid points to measure, the others
        are NaN.
        """
        image = np.asarray(image, np.float32)
        if image.ndim == 2:
            image = image[..., None]
        p = self.patch
        h, w = image.shape[:2]
        if wrap:
            image = np.pad(image, ((0, p - 1), (0, p - 1), (0, 0)), mode="wrap")
        # (ny, nx, p, p, channels): each window rows first, as the search reads it
        windows = sliding_window_view(image, (p, p, image.shape[-1]))[::stride, ::stride, 0]
        cy = np.arange(windows.shape[0]) * stride + p / 2
        cx = np.arange(windows.shape[1]) * stride + p / 2
        if wrap:
            cy, cx = cy % h, cx % w
        if within is not None:
            keep = [_kept(c, s) for c, s in zip((cy, cx), within, strict=True)]
            windows, cy, cx = windows[keep[0]][:, keep[1]], cy[keep[0]], cx[keep[1]]
        ny, nx = windows.shape[:2]
        if measure is not None:
            d = np.full((ny, nx), np.nan)
            iy, ix = np.nonzero(measure(cy, cx))
            for i in range(0, len(iy), _BATCH):
                at = iy[i : i + _BATCH], ix[i : i + _BATCH]
                d[at] = self.distances(windows[at])
            return d, cy, cx
        d = np.empty((ny, nx))
        rows = max(1, _BATCH // max(nx, 1))
        for y in range(0, ny, rows):
            block = windows[y : y + rows]
            d[y : y + rows] = self.distances(block.reshape(-1, *block.shape[2:])).reshape(
                block.shape[:2])
        return d, cy, cx


def _kept(centres: np.ndarray, part: slice) -> slice | np.ndarray:
    """The centres within ``part`` (ends included), as a slice where they are consecutive.

    A slice keeps the selected sliding windows a view; an index array would copy them.
    """
    keep = np.flatnonzero((centres >= part.start) & (centres <= part.stop))
    if keep.size and keep[-1] - keep[0] + 1 == keep.size:
        return slice(int(keep[0]), int(keep[-1]) + 1)
    return keep


def structure_ratios(exemplar: PatchExemplar, image: np.ndarray, borders: Borders, *,
                     reach: float, stride: int = STRIDE, sparse_inside: int = 1,
                     thinned: list | None = None) -> tuple[float, ...]:
    """Per line: the worse side's mean nearest-patch distance over the inside's mean.

    A side of a line is the patches centred within ``reach`` of it on that side (one centred
    on the line counts on both); the inside is the patches centred farther than ``reach`` from
    every line. Measuring the sides on their own keeps a break on one side from being averaged
    with a clean other side, and makes a tile's side of its borders depend only on the tile
    and the texels within half a patch beyond them. For a quilted texture ``reach`` is half the
    patch step: a side then holds one seam of patches per step, as the inside does, so equally
    good seams give a ratio of 1. Means below :attr:`PatchExemplar.floor` (2% of the
    sample's contrast, where nothing is visible) count as the floor. An inside that copies
    the sample unchanged (a roller tile: its mean is below the floor) has no seams to compare
    with; there a border is compared with :attr:`PatchExemplar.own_repeat`, how far the
    sample's own patches lie from their nearest other one (how much its periods differ), at
    least the floor.

    ``sparse_inside``: the inside's mean from every ``sparse_inside``-th patch of the grid in
    each direction (the lines' sides keep every patch). A tile's check takes 2: a quarter of
    the inside, 60% fewer searches; on 96 checks of brick, grass and gravel tile sets the
    inside's mean moved by 0.6% (median; at most 2.9%) and no check's verdict changed. An
    inside thinned to fewer than :data:`SPARSE_INSIDE_LEAST` patches is measured whole.
    ``thinned``, a list: True is appended if the inside was thinned, else False.
    """
    h, w = np.shape(image)[:2]
    ys, xs = borders.within((h, w))  # only patches centred within the judged part count

    def inside_of(cy, cx):
        return (~_near(cy, borders.rows, h, borders.wrap, reach)[:, None]
                & ~_near(cx, borders.cols, w, borders.wrap, reach)[None, :])

    def measured(cy, cx):
        inside = inside_of(cy, cx)
        sparse = np.zeros_like(inside)
        sparse[::sparse_inside, ::sparse_inside] = True
        enough = np.count_nonzero(inside & sparse) >= SPARSE_INSIDE_LEAST
        return ~inside | (sparse if enough else inside)

    d, cy, cx = exemplar.distance_map(image, wrap=borders.wrap, stride=stride,
                                      within=(ys, xs),
                                      measure=measured if sparse_inside > 1 else None)
    inside = inside_of(cy, cx)
    if not inside.any():
        raise ValueError(f"no patch of the {h} x {w} image lies farther than {reach} texels "
                         "from every border: nothing to compare the borders with")
    if sparse_inside > 1:
        left_out = inside & ~measured(cy, cx)
        inside[left_out] = False
    if thinned is not None:
        thinned.append(sparse_inside > 1 and bool(left_out.any()))
    scale = float(d[inside].mean())
    if scale <= exemplar.floor:
        scale = max(exemplar.own_repeat, exemplar.floor)
    out = []
    for kind, line in borders.lines():
        sides = line_sides(d, cy, cx, kind, line, (h, w), wrap=borders.wrap, reach=reach)
        out.append(max(max(float(side.mean()), exemplar.floor) for side in sides if side.size)
                   / scale)
    return tuple(out)


def line_sides(d: np.ndarray, cy: np.ndarray, cx: np.ndarray, kind: str, line: int,
               shape: tuple[int, int], *, wrap: bool, reach: float) -> list[np.ndarray]:
    """The distances of a map (:meth:`PatchExemplar.distance_map`) on each side of a line.

    ``kind``: ``"row"`` or ``"col"``; a side is the patches centred within ``reach`` of the
    line on it (one centred on the line counts on both), before it, then after it.
    """
    centres, n, values = (cy, shape[0], d) if kind == "row" else (cx, shape[1], d.T)
    offset = _offsets(centres, line, n, wrap)
    return [values[(offset >= -reach) & (offset <= 0)], values[(offset >= 0) & (offset <= reach)]]


def border_figures(exemplar: PatchExemplar, image: np.ndarray, borders: Borders, *,
                   reach: float, stride: int = STRIDE, sparse_inside: int = 1,
                   thinned: list | None = None) -> BorderFigures:
    """Both measures of every line of ``borders`` (the module; :func:`structure_ratios`)."""
    return BorderFigures(tuple(borders.lines()), seam_ratios(image, borders),
                         structure_ratios(exemplar, image, borders, reach=reach,
                                          stride=stride, sparse_inside=sparse_inside,
                                          thinned=thinned))


def cell_figures(exemplar: PatchExemplar, image: np.ndarray, cells: np.ndarray, *,
                 reach: float, sources: np.ndarray | None = None, stride: int = STRIDE
                 ) -> tuple[float, float]:
    """Seam and structure ratios of the borders between the cells of a tiling.

    For tilings whose borders are not straight lines (the roller's cuts on a sheared
    lattice): ``cells`` ``(h, w, 2)`` names each texel's cell.

    Seam: the mean difference of the pairs whose texels lie in different cells, per
    direction, the larger; over the pairs within a cell, or, with ``sources`` (each texel's
    main sample texel, flat index), over what the sample has at the same place: the pair of
    the first texel's source and its neighbour in that direction. A cut along the texture's
    own edges (the mortar of a tiled floor) then counts as natural, a brightness step across
    it (a gradient-lit sample) does not.

    Structure: the mean nearest-patch distance of the patches centred within ``reach`` of a
    texel of another cell, both sides together, over the larger of the others' mean and
    :attr:`PatchExemplar.own_repeat`: a tiling whose cells copy the sample (the roller's) has
    no seams inside to compare with, and a border as far from the sample as the sample's own
    periods are from each other stands out no more than they do.
    """
    from scipy import ndimage

    image = np.asarray(image, np.float64)
    if image.ndim == 2:
        image = image[..., None]
    seams = []
    sample = exemplar.sample.reshape(-1, exemplar.sample.shape[-1])
    sh, sw = exemplar.sample.shape[:2]
    for axis in (0, 1):
        diff = np.abs(np.diff(image, axis=axis)).mean(-1)
        across = np.any(np.diff(cells, axis=axis) != 0, axis=-1)
        if sources is None:
            natural = diff[~across]
        else:
            first = (sources[:-1] if axis == 0 else sources[:, :-1])[across]
            sy, sx = np.divmod(first, sw)
            ok = (sy + 1 < sh) if axis == 0 else (sx + 1 < sw)
            step = sw if axis == 0 else 1
            natural = np.abs(sample[first[ok] + step] - sample[first[ok]]).mean(-1)
            diff = np.where(across, diff, np.nan)
            across = across.copy()
            across[across] = ok
        seams.append(float(diff[across].mean()) / max(float(natural.mean()), 1e-12))
    edge = np.zeros(cells.shape[:2], bool)
    edge[:-1] |= np.any(cells[1:] != cells[:-1], -1)
    edge[1:] |= np.any(cells[1:] != cells[:-1], -1)
    edge[:, :-1] |= np.any(cells[:, 1:] != cells[:, :-1], -1)
    edge[:, 1:] |= np.any(cells[:, 1:] != cells[:, :-1], -1)
    distance = ndimage.distance_transform_edt(~edge)
    d, cy, cx = exemplar.distance_map(image, wrap=False, stride=stride)
    near = distance[np.ix_(np.minimum(cy.astype(int), image.shape[0] - 1),
                           np.minimum(cx.astype(int), image.shape[1] - 1))] <= reach
    if not near.any():
        raise ValueError("the cells leave no patch near a border")
    inside = float(d[~near].mean()) if not near.all() else 0.0  # small cells: borders only
    scale = max(inside, exemplar.own_repeat, exemplar.floor)
    return max(seams), max(float(d[near].mean()), exemplar.floor) / scale
