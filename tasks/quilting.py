"""Periodic image quilting and corner tile sets, planned on a reference image (paper 003).

Sections 2.1, 2.3 and 2.4 of the paper, with these choices where it is not specific:

- **Grid.** Patches are ``B x B`` windows on a grid of step ``S = B - O`` (``O`` the overlap);
  window ``k`` of a tile starts at ``k S - B/2``, so the first window of every row and column is
  centred on the tile's edge. Tile sizes are multiples of ``S``.
- **Phases as shared pieces.** Phase 1 (corners), 2 (horizontal edges), 3 (vertical edges) and
  4 (interior) become: one corner patch per corner type, centred on the tile corner; one
  horizontal and one vertical edge strip per ordered pair of corner types, the patches centred
  on the edge line between the two corner patches; and per tile an interior filled row by row
  (from one of its corners: :mod:`tasks.corner_tiles`).
  A tile starts as the halves of its four edge strips that lie inside it. With one corner type
  (``V = 1``) the single tile's opposite edges are the two halves of the same strip, so it
  wraps seamlessly: the paper's periodic texture. With ``V`` types, the ``V^4`` tiles share
  corners and edges, so any two that agree on a corner type meet seamlessly (Fig. 10-12).
- **Corner quadrants.** The quarter of a corner patch inside a tile is where a horizontal and a
  vertical strip meet: each blended its first (or last) edge patch into the corner patch's
  overlap band. The tile takes the horizontal strip there and blends the vertical strip's
  edge patches over it again with the weights they had in the vertical strip. Near the tile's
  vertical border the result equals the vertical strip, near its horizontal border the
  horizontal strip, so the four tiles around a corner point agree along both borders, and no
  overlap band is dropped.
- **Candidates** (section 2.3): all ``B x B`` positions of the sample, compared by the sum of
  squared differences over the filled pixels of the target window, in all channels (the
  "monochrome error image"), computed for every position at once by FFT correlation; one of
  the ``K`` best is drawn at random.
- **Boundary cut** (section 2.3, Fig. 6): the minimum-error closed path around the patch's
  inner ``(B - 2O)`` square through the error image (4-connected, edge cost the mean of the two
  pixels' errors), found by Dijkstra's search (:mod:`tasks.quilt_kernels`): the ring is cut by
  a slit above the inner square and the shortest loop crossing it once is kept. Pixels of
  the window that are still empty join the inner region, and the loop may run outside the
  window along them: these are the border flags of Fig. 8, which make the cut enclose the
  empty side instead of cutting through it at no cost. The flags of every placement are recorded.
  The cut never runs along a window pixel whose outside neighbour is not free (filled canvas,
  in the order tiles are filled): there it would leave the patch's outermost row next to
  canvas pixels with no transition.
- **Blending** (Fig. 7): the region inside the cut, blurred with a Gaussian of ``sigma = O/4``
  that sees weight 0 beyond the window (the canvas there, or nothing off the canvas), is the
  patch's weight; it is forced to 1 on the inner square and on empty pixels.
"""

from __future__ import annotations

import copy
import functools
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np
import scipy  # submodules load on first use, not at every btf command (test_layout: HEAVY)

from tasks.canvas import TERMS, Canvas
from tasks.errors import InvalidParameter
from tasks.seams import channel_groups

SIDES = ("left", "top", "right", "bottom")
FEATHER = 4.0  # the blend mask is blurred with sigma = overlap / FEATHER


@dataclass(frozen=True)
class QuiltParams:
    """Block size, overlap, candidates, corner types, tile size (pixels) and border check.

    ``max_seam``: the most a tile's borders may stand out from its inside (seam and structure
    ratios, :class:`tasks.corner_tiles.BorderCheck`); ``attempts``: rounds of planning again
    (:func:`tasks.corner_tiles.plan_tiles`); ``lattice``: the sample's periodicity vectors,
    whose phase every corner patch then shares, so that strips between any two corner types
    meet in phase.
    """

    block: int = 32
    overlap: int = 8
    candidates: int = 5
    corners: int = 1
    tile: tuple[int, int] = (256, 256)
    max_seam: float = 1.3
    attempts: int = 12
    # the sample's lattice (u, v), when it has one: corner patches share its phase
    lattice: tuple[tuple[float, float], tuple[float, float]] | None = None

    def __post_init__(self):
        def refuse(name: str, message: str):
            raise InvalidParameter(name, message)

        if self.block < 4 or self.block % 2:
            refuse("block", f"block must be an even number of at least 4, got {self.block}")
        if not 2 <= self.overlap < self.block // 2:  # a cut needs a row off the window's edge
            refuse("overlap", f"overlap must be between 2 and block/2 - 1, got {self.overlap}")
        if self.candidates < 1:
            refuse("candidates", f"candidates must be at least 1, got {self.candidates}")
        if self.corners < 1:
            refuse("corners", f"corners must be at least 1, got {self.corners}")
        if not self.max_seam > 0:
            refuse("max_seam", f"max_seam must be positive, got {self.max_seam}")
        if self.attempts < 1:
            refuse("attempts", f"attempts must be at least 1, got {self.attempts}")
        if self.lattice is not None and abs(np.linalg.det(np.asarray(self.lattice))) < 1:
            refuse("lattice", f"lattice vectors must span a cell, got {self.lattice}")
        for n in self.tile:
            if n < 2 * self.step or n % self.step:
                refuse("tile", f"tile size {self.tile} must be a multiple of block - overlap "
                               f"= {self.step}, at least twice it (one step leaves no room "
                               f"for edge patches)")

    @property
    def step(self) -> int:
        """Distance between neighbouring windows."""
        return self.block - self.overlap

    def plan_bytes(self, sample: tuple[int, int], channels: int) -> int:
        """About how much memory planning and compiling the prescriptions hold at their peak.

        Every tile's canvas (index, weight, value, filled), the candidate search's spectra of
        the sample (its size rounded up to fast transform lengths) and of the masks it keeps,
        and a CSR matrix per tile (about two terms per texel).
        """
        per_texel = TERMS * (4 + 4) + 4 * channels + 1 + 2 * (4 + 4) + 4
        padded = (scipy.fft.next_fast_len(sample[0], real=True)
                  * scipy.fft.next_fast_len(sample[1], real=True))
        search = padded * (4 * channels + 8 * (1 + channels) + 4 * CandidateSearch.MASKS_KEPT)
        return self.corners**4 * self.tile[0] * self.tile[1] * per_texel + search


def border_positions(sample: np.ndarray, block: int) -> dict[str, np.ndarray]:
    """Sample positions fit to carry a tile border through a patch's middle (see the module).

    A tile border runs between rows (columns) ``block/2 - 1`` and ``block/2`` of the corner
    and edge patches, so its neighbour pairs are that pair of sample lines, copied whole. On a
    structured texture a random position often puts a mortar line or a thread edge there, and
    the edge strip's matching then continues it along the whole border: a border rougher than
    the interior. A position is fit when the mean difference across its middle pair of rows
    (``"row"``), columns (``"col"``) or both (``"both"``) is at most the sample's mean over all
    neighbour pairs in that direction. Masks have the candidate search's ``valid`` shape.
    """
    sample = np.asarray(sample, np.float64)
    h, w = sample.shape[:2]
    half = block // 2
    vh, vw = h - block + 1, w - block + 1
    dy = np.abs(np.diff(sample, axis=0)).reshape(h - 1, w, -1).mean(-1)
    dx = np.abs(np.diff(sample, axis=1)).reshape(h, w - 1, -1).mean(-1)
    across_rows = np.cumsum(np.pad(dy, ((0, 0), (1, 0))), axis=1)  # sums along x
    across_cols = np.cumsum(np.pad(dx, ((1, 0), (0, 0))), axis=0)  # sums along y
    line = half - 1
    row = (across_rows[line : line + vh, block : block + vw] - across_rows[line : line + vh, :vw])
    col = (across_cols[block : block + vh, line : line + vw] - across_cols[:vh, line : line + vw])
    fit = {"row": row / block <= dy.mean(), "col": col / block <= dx.mean()}
    fit["both"] = fit["row"] & fit["col"]
    return {k: (m if m.any() else np.ones((vh, vw), bool)) for k, m in fit.items()}


_ANYWHERE = np.ones((1, 1), bool)  # CandidateSearch.choose: no mask, every position allowed


class CandidateSearch:
    """Masked SSD of a target window against every window of the sample, by FFT.

    ``SSD(s) = sum_u M(u) |S(s + u) - T(u)|^2 = corr(|S|^2, M) - 2 corr(S, M T) + sum M |T|^2``;
    the spectra of the sample and of its squared norm are computed once. Per target the
    ``1 + groups`` kernel spectra (channel groups: see below) are summed in the frequency
    domain, so one inverse FFT gives the whole error image, and the kernels' transforms skip
    their all-zero rows.

    In float32 (complex64 spectra): an error is off by about 3e-7 of the masked target's
    squared norm (1e-4 on brick's 32 x 32 blocks, whose best candidates lie at about 4),
    far below what tells candidates apart; an error image takes 0.99 ms instead of float64's
    1.43 ms (brick, block 32, one thread).

    The first term depends on the mask alone, and a plan's masks are few (the overlap bands
    of the neighbours placed before: 9 in four 240^2 tiles' 324 windows), so its spectrum
    is kept per mask (:data:`MASKS_KEPT` of them); the error image is the same, bit for bit.

    Channels the sample holds bit for bit alike (a grey photo's BTF: its reference repeats
    one channel three times) share one term: ``sum_c corr(S_c, M T_c) = corr(S_g, M sum_c
    T_c)`` over a group's channels, exact for any target. A grey sample's error image then
    transforms one kernel instead of three (0.72 -> 0.40 ms on a 256^2 photo, block 32, one
    thread).
    """

    MASKS_KEPT = 16

    def __init__(self, sample: np.ndarray, block: int):
        self.sample = np.asarray(sample, np.float32)
        self.block = block
        h, w, _ = self.sample.shape
        # a circular correlation of the sample's own size: the window at (sy, sx) reads rows
        # sy .. sy + block - 1 < h, so only positions past the last valid one wrap
        self.shape = (scipy.fft.next_fast_len(h, real=True),
                      scipy.fft.next_fast_len(w, real=True))
        self.valid = (h - block + 1, w - block + 1)
        self.group = channel_groups(self.sample)  # channels held alike share a term
        firsts = np.unique(self.group, return_index=True)[1]  # each group's first channel
        planes = [np.sum(self.sample**2, axis=-1)]
        planes += [-2.0 * self.sample[..., f] for f in firsts]
        self.spectra = scipy.fft.rfft2(np.stack(planes), self.shape)
        # the first term's spectrum per mask, oldest first (shared by the planners' threads:
        # each of its calls is atomic, and a race only computes one twice)
        self._masks: OrderedDict[tuple, np.ndarray] = OrderedDict()

    def _spectra(self, kernels: np.ndarray, planes: slice) -> np.ndarray:
        """The kernels' spectra times the sample's ``planes``.

        Only the ``B`` non-zero rows of the kernels are transformed along the rows.
        """
        rows = scipy.fft.rfft(kernels[planes], n=self.shape[1], axis=-1)
        spectrum = scipy.fft.fft(rows, n=self.shape[0], axis=-2)
        spectrum *= self.spectra[planes]
        return spectrum

    def errors(self, target: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """SSD of ``target`` over ``mask`` at every sample position ``(sy, sx)``."""
        from tasks.quilt_kernels import clipped_errors, search_kernels  # numba

        # flipped: the correlation's kernels
        kernels, norm = search_kernels(target, mask, self.group, len(self.spectra) - 1)
        key = (mask.shape, mask.dtype.str, mask.tobytes())
        first = self._masks.get(key)
        if first is None:
            first = self._spectra(kernels, slice(0, 1))[0]
            while len(self._masks) >= self.MASKS_KEPT:  # the oldest go
                try:
                    self._masks.popitem(last=False)
                except KeyError:  # another thread emptied it meanwhile
                    break
            self._masks[key] = first
        # the kernels summed in the frequency domain, the first term first: one inverse
        spectrum = self._spectra(kernels, slice(1, None))
        total = first + spectrum[0]
        for term in spectrum[1:]:
            total += term
        full = scipy.fft.irfft2(total, self.shape)
        return clipped_errors(full, self.block - 1, *self.valid, norm)

    def choose(self, target: np.ndarray, mask: np.ndarray, k: int,
               rng: np.random.Generator, allowed: np.ndarray | None = None) -> tuple[int, int]:
        """One of the ``k`` best positions, at random; any position if nothing is masked in.

        The ``k`` best by error, of equal errors the first in row-major order (a periodic
        sample has many).

        ``allowed``: a ``valid``-shaped mask of the positions that may be chosen at all.
        """
        if not mask.any():
            if allowed is None:
                return (int(rng.integers(self.valid[0])), int(rng.integers(self.valid[1])))
            positions = np.flatnonzero(allowed)
            return divmod(int(positions[rng.integers(positions.size)]), self.valid[1])
        from tasks.quilt_kernels import smallest  # numba: not loaded by `btf --help`

        err = self.errors(target, mask)
        k = min(k, err.size if allowed is None else int(allowed.sum()))
        best = smallest(err, _ANYWHERE if allowed is None else np.ascontiguousarray(allowed),
                        allowed is not None, k)  # by error, ties by position
        pick = int(best[rng.integers(best.size)])
        return divmod(pick, self.valid[1])


def boundary_cut(error: np.ndarray, keep: np.ndarray, *, outside_free: np.ndarray
                 ) -> np.ndarray:
    """Region of a window enclosed by the minimum-error closed cut around ``keep``.

    Parameters
    ----------
    error
        ``(B, B)`` error image (squared differences between patch and canvas).
    keep
        ``(B, B)`` pixels the patch must take (inner square and empty pixels); the cut may not
        cross them.
    outside_free
        ``(B + 2, B + 2)`` ring of positions just outside the window that the cut may use at no
        cost: next to empty pixels (the border flags) or off the canvas. Elsewhere outside is
        forbidden, and so is the window pixel next to it.

    Returns
    -------
    numpy.ndarray
        ``(B, B)`` bool: the pixels inside the cut (including the cut itself and ``keep``).
    """
    from tasks.quilt_kernels import cheapest_loop, cut_costs, filled_holes  # numba

    b = error.shape[0]
    cost, top = cut_costs(error, keep, outside_free)
    # the slit: rows above the keep region, between the middle column and the next
    loop, found = cheapest_loop(cost, (b + 2) // 2, top)
    if not found:
        return np.ones((b, b), bool)
    loop[1:-1, 1:-1] |= keep
    return filled_holes(loop)[1:-1, 1:-1]


def blend_weights(region: np.ndarray, keep: np.ndarray, overlap: int) -> np.ndarray:
    """Patch weight: the region inside the cut, Gaussian-blurred, 1 on ``keep`` (Fig. 7).

    Beyond the window the blur sees weight 0 (the canvas), so a region reaching the window's
    edge still fades out instead of ending in a hard edge.
    """
    from tasks.quilt_kernels import feathered  # numba: not loaded by `btf --help`

    return feathered(region, keep, _feather_kernel(max(overlap / FEATHER, 0.5)))


@functools.cache
def _feather_kernel(sigma: float) -> np.ndarray:
    """The Gaussian weights ``scipy.ndimage.gaussian_filter`` blurs with (radius 4 sigma)."""
    radius = int(4.0 * sigma + 0.5)
    x = np.arange(-radius, radius + 1)
    weights = np.exp(-0.5 / sigma**2 * x**2)
    return weights / weights.sum()


@dataclass
class Placement:
    """One patch transfer: where it went, where it came from, and the border flags used."""

    canvas: str
    window: tuple[int, int]
    source: tuple[int, int]
    flags: tuple[str, ...]


@dataclass(frozen=True, eq=False)
class Blend:
    """A patch as it was blended into a canvas: sample indices, values, weights, window."""

    index: np.ndarray
    value: np.ndarray
    alpha: np.ndarray
    y0: int
    x0: int

    def again(self, canvas: Canvas, dy: int, dx: int, rows: np.ndarray) -> None:
        """Blend it into another canvas, shifted by ``(dy, dx)``, only on the canvas ``rows``."""
        ys = self.y0 + dy + np.arange(self.alpha.shape[0])
        alpha = np.where(np.isin(ys, rows)[:, None], self.alpha, 0.0)
        canvas.place(self.index, self.value, alpha, self.y0 + dy, self.x0 + dx)


@dataclass
class Planner:
    """Plans patch transfers from one sample (reference image) with a seeded generator."""

    reference: np.ndarray
    params: QuiltParams
    rng: np.random.Generator
    placements: list[Placement] = field(default_factory=list)

    def __post_init__(self):
        self.reference = np.asarray(self.reference, np.float32)
        h, w, _ = self.reference.shape
        b = self.params.block
        if h < b or w < b:
            raise ValueError(f"the reference image ({h} x {w}) is smaller than a block ({b})")
        if h * w >= 2**31:
            raise ValueError(f"the reference image ({h} x {w}) has 2**31 texels or more")
        self.search = CandidateSearch(self.reference, b)
        self.flat = np.arange(h * w, dtype=np.int32).reshape(h, w)
        self.borders = border_positions(self.reference, b)

    def with_stream(self, rng: np.random.Generator) -> Planner:
        """A copy with its own generator and no placements, sharing the search.

        Pieces planned by such copies in different threads do not share any state they
        change, so each piece is the same whichever thread plans it.
        """
        planner = copy.copy(self)
        planner.rng, planner.placements = rng, []
        return planner

    def _patch(self, source: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        sy, sx = source
        b = self.params.block
        return (self.flat[sy : sy + b, sx : sx + b],
                self.reference[sy : sy + b, sx : sx + b])

    def place(self, canvas: Canvas, name: str, y0: int, x0: int, border: str | None = None,
              allowed: np.ndarray | None = None) -> Blend:
        """Choose a patch for the window at ``(y0, x0)`` and blend it in along its best cut.

        ``border``: ``"row"``, ``"col"`` or ``"both"`` when a tile border will run through the
        patch's middle row, column or both (see :func:`border_positions`); ``allowed``: a mask
        of the sample positions that may be chosen (all if none of them may).
        """
        from tasks.quilt_kernels import window_state  # numba: not loaded by `btf --help`

        b, o = self.params.block, self.params.overlap
        # on the canvas, filled, the canvas values; and where the cut may run just outside the
        # window: next to empty pixels, and off the canvas
        inside, filled, target, outside_free = window_state(canvas.filled, canvas.value, y0,
                                                            x0, b)
        mask = None if border is None else self.borders[border]
        if allowed is not None:
            both = allowed if mask is None else mask & allowed
            mask = both if both.any() else mask
        source = self.search.choose(target, filled, self.params.candidates, self.rng, mask)
        index, value = self._patch(source)
        inner = np.zeros((b, b), bool)
        inner[o : b - o, o : b - o] = True
        empty = inside & ~filled
        keep = inner | empty
        # border flags: sides whose band is (partly) empty or off the canvas
        flags = tuple(side for side, band in zip(SIDES, (
            (slice(None), slice(0, o)), (slice(0, o), slice(None)),
            (slice(None), slice(b - o, b)), (slice(b - o, b), slice(None))), strict=True)
            if not (filled[band].all()))
        error = np.sum((value - target) ** 2, axis=-1)
        error[~filled] = 0.0
        region = boundary_cut(error, keep, outside_free=outside_free)
        alpha = blend_weights(region, keep, o)
        alpha[~inside] = 0.0
        alpha[empty] = 1.0
        canvas.place(index, value, alpha, y0, x0)
        self.placements.append(Placement(name, (y0, x0), source, flags))
        return Blend(index, value, alpha, y0, x0)
