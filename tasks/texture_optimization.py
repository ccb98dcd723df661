"""Texture Optimization with a guide (Kwatra et al. 2005; paper 000, section 3.1, eqs. 2-3).

The output ``X`` (target size, ``K`` coefficient channels: the eigentexture coefficients
``Sigma V^T`` of every texel) is optimised so that each of its ``n x n`` neighbourhoods on a
grid of spacing ``n / 4`` looks like some neighbourhood ``z_p`` of the sample::

    E(X) = sum_p || f(X)_p - f(Z)_{z_p} ||^r

alternating an E-step (find the most similar sample neighbourhood of every output
neighbourhood) and an M-step (every texel becomes the weighted mean of the sample texels the
overlapping matches put there; Kwatra's robust weights ``||.||^(r-2)``, ``r = 0.8``, make this
an iteratively reweighted least squares, which never increases ``E``). At the finest level the
last M-step moves each texel ``pick`` of the way to the one candidate texel that fits it best
(:func:`pick_vote`: an extension, issue 57; the mean blurs texels the photos tell apart).

**Guide (the constraint images).** A texel's feature ``f`` is its coefficients stacked with
``sqrt(lambda)`` times its constraint values (log domain): the sample's own constraint images
``C_S`` on the sample side, the target's ``C`` on the output side. The output's constraint
channels are held at ``C``: this is the paper's control term ``lambda E_c`` taken to its
limit (the QP of :mod:`tasks.constrained_blend` enforces the constraints exactly afterwards),
and ``lambda`` is the weight of a constraint value against one value of the texel's ABRDF in
the search. The caller chooses it (paper: 20000 for 22801 textures, "nearly one-to-one").

**Levels.** Synthesis runs coarse to fine on the sample and the guide downsampled by
``2^(levels-1) ... 1`` (block means; paper: 1/4, 1/2, 1); the coarsest output starts from a
search on the guide alone, every finer one from the coarser result upsampled.

**Search.** The distance of two neighbourhoods is computed on the leading principal
components of the coefficients (the components holding ``search_energy`` of the sample's
variance; rotations keep distances, the truncation drops the rest) and the full guide.
Candidates come from an exact search (faiss, flat L2) on a PCA projection of the
neighbourhoods to ``search_dims`` dimensions, or, with ``search="coherent"`` (the default),
by k-coherence (Tong et al. 2002): the current matches of the 3 x 3 neighbouring output
neighbourhoods, shifted so that a copy continues, and each one's ``coherence`` most similar
sample neighbourhoods (a table built once per level), ranked in the same projection: 9 (1 +
k) candidates, however large the sample (the table and the seeds still grow with it: the
table is one exact search of the sample against itself per level). A level's first matches
are seeded by the exact search for a quarter of the output neighbourhoods (every other one a
side), the others continuing their nearest seed's copy. ``search="exact"`` runs the exact
search for every neighbourhood in every E-step (the paper's). Either way the ``candidates``
best distinct ones are re-ranked by their true distance together with the previous match, so
an E-step never returns a worse match than it had and ``E`` never increases. (Measured: the
coherent search ends within 1.1-1.3% of the exact search's energy on smooth random fields,
and at the same eq. (11) error, +2%, and realism on a generated wood BTF. Starting a level
from the coarser level's matches instead of seeds, as appearance-space synthesis does, was
another 15% faster but raised that error by 17% and realism from 1.17 to 1.42: not done. See
BENCHMARKS.md, enlargement.)
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field

import numpy as np

from tasks.errors import InvalidParameter

CHUNK_BYTES = 32 << 20  # neighbourhood vectors built at a time for a projection
PCA_FIT = 4096  # sample neighbourhoods the search basis is fitted to


@dataclass(frozen=True)
class TextureOptimizationParams:
    """Levels, neighbourhood size, EM iterations and search settings."""

    levels: int = 3
    patch: int = 8
    iterations: int = 5
    robust: float = 0.8
    search_energy: float = 0.9999
    search_dims: int = 32
    candidates: int = 2
    search: str = "coherent"  # or "exact": every E-step searches the whole sample
    coherence: int = 4  # k of k-coherence: similar sample neighbourhoods kept per one (0: the
    # coherent search has nothing to look at besides the neighbours' matches; it then runs
    # the exact search instead)
    pick: float = 0.5  # share of the finest level's last vote given to the candidate texel
    # that fits each texel best (:func:`pick_vote`; 0: Kwatra's weighted mean alone)
    pick_lookups: int = 8  # sample texels nearest to a texel's guide added to its candidates

    def __post_init__(self):
        if self.levels < 1:
            raise InvalidParameter("levels", f"levels must be at least 1, got {self.levels}")
        if self.patch < 2:
            raise InvalidParameter("patch", f"patch must be at least 2 texels, got {self.patch}")
        if self.iterations < 1:
            raise InvalidParameter("iterations",
                                   f"iterations must be at least 1, got {self.iterations}")
        if not 0 < self.robust <= 2:
            raise InvalidParameter("robust", f"robust must be in (0, 2], got {self.robust}")
        if not 0 < self.search_energy <= 1:
            raise InvalidParameter("search_energy",
                                   f"search_energy must be in (0, 1], got {self.search_energy}")
        if self.search_dims < 1 or self.candidates < 1:
            raise InvalidParameter("search_dims", "search_dims and candidates must be >= 1")
        if self.search not in ("coherent", "exact"):
            raise InvalidParameter("search", f"search must be 'coherent' or 'exact', got "
                                             f"{self.search!r}")
        if self.coherence < 0:
            raise InvalidParameter("coherence",
                                   f"coherence must be non-negative, got {self.coherence}")
        if not 0 <= self.pick <= 1:
            raise InvalidParameter("pick", f"pick must be in [0, 1], got {self.pick}")
        if self.pick_lookups < 0:
            raise InvalidParameter("pick_lookups",
                                   f"pick_lookups must be non-negative, got {self.pick_lookups}")

    @property
    def spacing(self) -> int:
        """Distance between neighbouring output neighbourhoods (Kwatra: a quarter patch)."""
        return max(1, self.patch // 4)


@dataclass
class TextureOptimizationResult:
    """The synthesized coefficients and how the optimisation went."""

    coefficients: np.ndarray  # (H, W, K) float32
    energy: list[list[float]] = field(default_factory=list)  # per level, after each E-step
    seconds: list[float] = field(default_factory=list)  # per level


def grid(n: int, patch: int, spacing: int) -> np.ndarray:
    """Neighbourhood origins along an axis of ``n`` texels: every ``spacing``, the last flush."""
    last = n - patch
    if last < 0:
        raise ValueError(f"{n} texels are fewer than a neighbourhood of {patch}")
    starts = np.arange(0, last + 1, spacing)
    return starts if starts[-1] == last else np.append(starts, last)


def downsample(image: np.ndarray, factor: int) -> np.ndarray:
    """Block means of ``factor x factor`` texels (a partial last block averages what it has)."""
    image = np.asarray(image, np.float32)
    if factor == 1:
        return image
    h, w, *rest = image.shape
    hh, ww = -(-h // factor), -(-w // factor)
    padded = np.zeros((hh * factor, ww * factor, *rest), np.float64)
    padded[:h, :w] = image
    count = np.zeros((hh * factor, ww * factor), np.float64)
    count[:h, :w] = 1.0
    sums = padded.reshape(hh, factor, ww, factor, *rest).sum(axis=(1, 3))
    n = count.reshape(hh, factor, ww, factor).sum(axis=(1, 3))
    return (sums / n.reshape(hh, ww, *([1] * len(rest)))).astype(np.float32)


def upsample(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Bilinear resampling of ``(h, w, c)`` to ``shape`` (texel centres aligned)."""
    return upsample_region(image, (0, 0), image.shape[:2], shape, (0, 0), shape)


def coarse_rows(fine0: int, fine1: int, coarse: int, fine: int) -> tuple[int, int]:
    """The coarse rows (or columns) that bilinear upsampling of fine ``[fine0, fine1)`` reads."""
    pos = (np.array([fine0, fine1 - 1]) + 0.5) * coarse / fine - 0.5
    pos = np.clip(pos, 0, coarse - 1)
    return int(np.floor(pos[0])), min(coarse, int(np.floor(pos[1])) + 2)


def upsample_region(block: np.ndarray, block_origin: tuple[int, int],
                    coarse_shape: tuple[int, int], fine_shape: tuple[int, int],
                    origin: tuple[int, int], size: tuple[int, int]) -> np.ndarray:
    """Texels ``origin .. origin + size`` of a coarse image bilinearly upsampled to ``fine_shape``.

    ``block`` holds the coarse texels from ``block_origin`` on (at least :func:`coarse_rows` of
    the region): a region computes exactly what the whole image's upsampling has there.
    """
    from scipy import ndimage

    (h, w), (hf, wf) = coarse_shape, fine_shape
    ys = np.clip((np.arange(origin[0], origin[0] + size[0]) + 0.5) * h / hf - 0.5, 0, h - 1)
    xs = np.clip((np.arange(origin[1], origin[1] + size[1]) + 0.5) * w / wf - 0.5, 0, w - 1)
    yy, xx = np.meshgrid(ys - block_origin[0], xs - block_origin[1], indexing="ij")
    return np.stack([ndimage.map_coordinates(block[..., c], [yy, xx], order=1)
                     for c in range(block.shape[-1])], axis=-1).astype(np.float32)


def _patches(features: np.ndarray, ys: np.ndarray, xs: np.ndarray, patch: int) -> np.ndarray:
    """Neighbourhood vectors ``(len(ys) * len(xs), patch^2 * C)`` at a grid of origins."""
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    return _patches_at(features, yy.ravel(), xx.ravel(), patch)


def _patches_at(features: np.ndarray, ys: np.ndarray, xs: np.ndarray, patch: int
                ) -> np.ndarray:
    """Neighbourhood vectors ``(len(ys), patch^2 * C)`` at the origins ``(ys[i], xs[i])``."""
    from numpy.lib.stride_tricks import sliding_window_view

    windows = sliding_window_view(features, (patch, patch), axis=(0, 1))  # (h', w', C, p, p)
    return windows[ys, xs].reshape(len(ys), -1)


def _project(features: np.ndarray, ys: np.ndarray, xs: np.ndarray, patch: int,
             basis: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """Neighbourhoods at the origins projected on ``basis``, built a chunk of rows at a time."""
    per_row = len(xs) * patch * patch * features.shape[-1] * 4
    rows = max(1, CHUNK_BYTES // max(per_row, 1))
    out = np.empty((len(ys) * len(xs), basis.shape[1]), np.float32)
    for k in range(0, len(ys), rows):
        block = _patches(features, ys[k : k + rows], xs, patch)
        out[k * len(xs) : k * len(xs) + len(block)] = (block - mean) @ basis
    return out


class SampleLevel:
    """One level's sample side: features, search basis and projections, voting source.

    Built once per level (the PCA basis is fitted to neighbourhoods drawn with the caller's
    generator) and then usable for any part of the output: it pickles without its search
    index, which every process rebuilds from the projections on first use. ``table(projected,
    k)`` makes the k-coherence table (default :func:`coherence`; a caller with workers gives
    one that computes the same parts in parallel).
    """

    def __init__(self, coefficients, guide, rotation, guide_weight, params, rng, *,
                 table=None):
        p = params.patch
        self.patch = p
        self.rotation = rotation
        self.guide_weight = float(guide_weight)
        self.coefficients = np.ascontiguousarray(coefficients, np.float32)
        self.guide = None if guide is None else np.asarray(guide, np.float32)
        self.features = _features(coefficients, guide, rotation, guide_weight)
        h, w = self.features.shape[:2]
        if min(h, w) < p:
            raise ValueError(f"the sample at this level ({h} x {w}) is smaller than a "
                             f"neighbourhood of {p} texels: use fewer levels or a smaller patch")
        self.ys, self.xs = np.arange(h - p + 1), np.arange(w - p + 1)
        self.width = len(self.xs)
        count = len(self.ys) * self.width
        pick = np.sort(rng.choice(count, min(count, PCA_FIT), replace=False))
        sample = _patches_at(self.features, *self.origin(pick), p).astype(np.float64)
        mean = sample.mean(axis=0)
        self.basis = _principal_axes(sample - mean, params.search_dims, rng)
        self.mean = mean.astype(np.float32)
        self.projected = _project(self.features, self.ys, self.xs, p, self.basis, self.mean)
        self._index = None
        self._guide_tree = None
        self.coherence = ((table or coherence)(self.projected, params.coherence)
                          if params.search == "coherent" and params.coherence else None)

    def __getstate__(self):
        return {**self.__dict__, "_index": None, "_guide_tree": None}

    @property
    def guide_tree(self):
        """A k-d tree over the sample texels' weighted guide values (built on first use)."""
        if self._guide_tree is None:
            from scipy.spatial import cKDTree

            lead = self.rotation.shape[1]
            self._guide_tree = cKDTree(
                self.features.reshape(-1, self.features.shape[-1])[:, lead:])
        return self._guide_tree

    @property
    def index(self):
        """The exact L2 index over the sample's projected neighbourhoods (built on first use)."""
        if self._index is None:
            self._index = _flat_index(self.projected)
        return self._index

    def origin(self, flat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sample origins (row, column) of flat neighbourhood indices."""
        return flat // self.width, flat % self.width


COHERENCE_QUERIES = 4096  # sample neighbourhoods a part of the k-coherence table searches for


def coherence_parts(count: int) -> list[tuple[int, int]]:
    """The parts of the k-coherence table of ``count`` neighbourhoods: ranges of queries.

    Whole blocks of faiss's own query batch (4096), the last one with the rest, so that the
    parts, searched apart (in parallel), give the bits of one search of all the queries (a
    search of fewer than 20 queries would take another path, without BLAS).
    """
    bounds = [k * COHERENCE_QUERIES for k in range(max(1, count // COHERENCE_QUERIES))]
    bounds.append(count)
    return [(a, b) for a, b in itertools.pairwise(bounds) if b > a]


def coherence_rows(projected: np.ndarray, k: int, start: int, stop: int) -> np.ndarray:
    """Rows ``start:stop`` of the k-coherence table of ``projected`` (:func:`coherence`)."""
    k = min(k, len(projected) - 1)
    if k < 1:
        return np.zeros((stop - start, 0), np.int32)
    _, found = _flat_index(projected).search(np.ascontiguousarray(projected[start:stop]), k + 1)
    own = np.arange(start, stop)[:, None]
    # drop each one's own entry (or, when exact duplicates hide it, the last)
    keep = np.where((found == own).any(axis=1, keepdims=True), found != own,
                    np.arange(k + 1) < k)
    return found[keep].reshape(stop - start, k).astype(np.int32)


def coherence(projected: np.ndarray, k: int) -> np.ndarray:
    """For every sample neighbourhood, its ``k`` most similar others (k-coherence's table).

    Exact in the search projection (faiss, flat L2); ``(n, k)`` flat indices, int32. Part by
    part (:func:`coherence_parts`); a caller with workers may compute the parts in parallel
    with :func:`coherence_rows` (:class:`SampleLevel`'s ``table``): faiss releases the GIL.
    """
    parts = [coherence_rows(projected, k, a, b) for a, b in coherence_parts(len(projected))]
    return np.concatenate(parts) if parts else coherence_rows(projected, k, 0, 0)


def coherent_candidates(source: SampleLevel, match: np.ndarray, gy: np.ndarray,
                        gx: np.ndarray) -> np.ndarray:
    """Candidate sample neighbourhoods of every output one from its neighbours' matches.

    k-coherence (Tong et al. 2002) on the grid of output neighbourhoods: each of the 3 x 3
    grid neighbours' current matches, shifted by the offset between the two output
    neighbourhoods (so a coherent copy continues), and each of those's ``k`` most similar
    sample neighbourhoods (:func:`coherence`). ``(Q, 9 (1 + k))`` flat indices, in the
    order of ``match`` (row-major over ``gy x gx``); their number does not grow with the
    sample.
    """
    ny, nx = len(gy), len(gx)
    my, mx = source.origin(match.reshape(ny, nx))
    last_y, last_x = len(source.ys) - 1, source.width - 1
    shifted = []
    for dy in (-1, 0, 1):
        iy = np.clip(np.arange(ny) + dy, 0, ny - 1)
        for dx in (-1, 0, 1):
            ix = np.clip(np.arange(nx) + dx, 0, nx - 1)
            cy = np.clip(my[np.ix_(iy, ix)] - (gy[iy] - gy)[:, None], 0, last_y)
            cx = np.clip(mx[np.ix_(iy, ix)] - (gx[ix] - gx)[None, :], 0, last_x)
            shifted.append((cy * source.width + cx).ravel())
    base = np.stack(shifted, axis=1).astype(np.int32)  # (Q, 45) candidates: keep them small
    if source.coherence is None or source.coherence.shape[1] == 0:
        return base
    similar = source.coherence[base].reshape(len(base), -1)
    return np.concatenate([base, similar], axis=1)


def _nearest_candidates(projected: np.ndarray, source: SampleLevel, candidates: np.ndarray,
                        count: int) -> np.ndarray:
    """The ``count`` distinct candidates nearest to each query in the search projection.

    Neighbours continuing one copy propose the same sample neighbourhood many times; each is
    counted once (a row with fewer distinct candidates repeats its best).
    """
    count = min(count, candidates.shape[1])
    out = np.empty((len(candidates), count), candidates.dtype)
    step = max(1, CHUNK_BYTES // (candidates.shape[1] * projected.shape[1] * 4))
    for k in range(0, len(candidates), step):
        c = np.sort(candidates[k : k + step], axis=1)
        d = source.projected[c] - projected[k : k + step, None, :]
        dist = np.einsum("qkc,qkc->qk", d, d)
        dist[:, 1:][c[:, 1:] == c[:, :-1]] = np.inf  # repeats of the one before
        best = np.argsort(dist, axis=1, kind="stable")[:, :count]
        out[k : k + step] = np.take_along_axis(c, best, axis=1)
    return out


def _seeds(source: SampleLevel, query: np.ndarray, projected: np.ndarray, gy: np.ndarray,
           gx: np.ndarray, params: TextureOptimizationParams) -> np.ndarray:
    """A level's first matches: an exact search for every other output neighbourhood a side.

    Each output neighbourhood at even grid indices (a quarter of them) gets its best match by
    the exact search (re-ranked at full dimension); the others start from the nearest such
    one's match, shifted so the copy continues. The coherent E-step that follows looks
    around these, so a level's search costs a quarter of an exact one.
    """
    ny, nx = len(gy), len(gx)
    iy, ix = np.arange(0, ny, 2), np.arange(0, nx, 2)
    picked = (iy[:, None] * nx + ix[None, :]).ravel()
    _, found = source.index.search(np.ascontiguousarray(projected[picked]), params.candidates)
    found = np.where(found < 0, 0, found)
    cy, cx = source.origin(found)
    qy, qx = (a.ravel() for a in np.meshgrid(gy[iy], gx[ix], indexing="ij"))
    dist = _distances(query, qy, qx, source.features, cy, cx, params.patch)
    best = found[np.arange(len(found)), np.argmin(dist, axis=1)].reshape(len(iy), len(ix))
    my, mx = source.origin(best)
    near_y, near_x = np.arange(ny) // 2, np.arange(nx) // 2
    sy = my[np.ix_(near_y, near_x)] + (gy - gy[iy][near_y])[:, None]
    sx = mx[np.ix_(near_y, near_x)] + (gx - gx[ix][near_x])[None, :]
    sy = np.clip(sy, 0, len(source.ys) - 1)
    sx = np.clip(sx, 0, source.width - 1)
    return (sy * source.width + sx).ravel()


def _principal_axes(centred: np.ndarray, dims: int, rng) -> np.ndarray:
    """The ``dims`` leading right singular vectors of ``centred`` (columns, float32).

    A randomized range finder with two power iterations (Halko et al. 2011): the exact SVD of
    thousands of neighbourhoods of thousands of values took seconds per level.
    """
    dims = min(dims, *centred.shape)
    omega = rng.standard_normal((centred.shape[1], dims + 10))
    y = centred @ omega
    for _ in range(2):
        y, _ = np.linalg.qr(y)
        y = centred @ (centred.T @ y)
    q, _ = np.linalg.qr(y)
    _, _, vt = np.linalg.svd(q.T @ centred, full_matrices=False)
    return np.ascontiguousarray(vt[:dims].T, np.float32)


def _features(coefficients, guide, rotation, guide_weight) -> np.ndarray:
    """Search features: the leading rotated coefficients and the weighted guide."""
    lead = np.asarray(coefficients, np.float32) @ rotation
    if guide is None or guide.shape[-1] == 0:
        return np.ascontiguousarray(lead)
    return np.ascontiguousarray(np.concatenate(
        [lead, np.float32(guide_weight) * np.asarray(guide, np.float32)], axis=-1))


def _flat_index(vectors: np.ndarray):
    """An exact L2 index over ``vectors`` (faiss IndexFlatL2)."""
    import faiss

    index = faiss.IndexFlatL2(vectors.shape[1])
    index.add(np.ascontiguousarray(vectors, np.float32))
    return index


def _distances(query: np.ndarray, qy, qx, sample: np.ndarray, cy, cx, patch: int
               ) -> np.ndarray:
    """Squared distances between output neighbourhoods and candidate sample ones.

    ``qy, qx`` (Q,) are output origins, ``cy, cx`` (Q, k) candidate sample origins.
    """
    w, c = query.shape[1:]
    sw = sample.shape[1]
    qflat, sflat = query.reshape(-1, c), sample.reshape(-1, c)
    qbase, sbase = qy * w + qx, cy * sw + cx
    out = np.zeros(sbase.shape, np.float32)
    for dy in range(patch):
        for dx in range(patch):
            d = sflat[sbase + dy * sw + dx] - qflat[qbase + dy * w + dx][:, None, :]
            out += np.einsum("qkc,qkc->qk", d, d)
    return out


def _vote(sample: np.ndarray, shape, qy, qx, my, mx, weights, patch: int) -> np.ndarray:
    """Every texel: the weighted mean of what the overlapping matches put there.

    Sums in float32 (at most ``patch^2`` terms per texel, weights normalised per texel).
    On a dense grid (origins at every texel, spacing 1) the sums go to shifted slices.
    """
    h, w = shape
    sw, k = sample.shape[1:]
    sflat = np.ascontiguousarray(sample.reshape(-1, k), np.float32)
    sbase = my * sw + mx
    wt = (weights / max(float(weights.max()), 1e-30)).astype(np.float32)
    ny, nx = h - patch + 1, w - patch + 1
    if len(qy) == ny * nx and np.array_equal(qy, np.repeat(np.arange(ny), nx)) and \
            np.array_equal(qx, np.tile(np.arange(nx), ny)):
        total = np.zeros((h, w, k), np.float32)
        norm = np.zeros((h, w), np.float32)
        grid_wt = wt.reshape(ny, nx)
        weighted = grid_wt[..., None]
        for dy in range(patch):
            for dx in range(patch):
                values = sflat[sbase + dy * sw + dx].reshape(ny, nx, k)
                values *= weighted
                total[dy : dy + ny, dx : dx + nx] += values
                norm[dy : dy + ny, dx : dx + nx] += grid_wt
        return total / np.maximum(norm, 1e-30)[..., None]
    total = np.zeros((h * w, k), np.float32)
    norm = np.zeros(h * w, np.float32)
    qbase = qy * w + qx
    for dy in range(patch):
        for dx in range(patch):
            target = qbase + dy * w + dx  # distinct within one offset: plain indexing adds
            total[target] += wt[:, None] * sflat[sbase + dy * sw + dx]
            norm[target] += wt
    return (total / np.maximum(norm, 1e-30)[:, None]).reshape(h, w, k)


def _robust_weights(dist: np.ndarray, r: float) -> np.ndarray:
    """Kwatra's IRLS weights ``||d||^(r-2)`` from squared distances (floored: exact matches)."""
    if r == 2:
        return np.ones_like(dist)
    return np.maximum(dist, 1e-6) ** ((r - 2) / 2)


def _energy(dist: np.ndarray, r: float) -> float:
    return float(np.sum(dist.astype(np.float64) ** (r / 2)))


def texture_optimization(sample: np.ndarray, sample_guide: np.ndarray | None,
                         target_guide: np.ndarray | None, *, shape: tuple[int, int],
                         params: TextureOptimizationParams, guide_weight: float = 1.0,
                         seed: int = 0) -> TextureOptimizationResult:
    """Synthesize ``shape`` texels of ``K`` coefficient channels from a sample (see module).

    Parameters
    ----------
    sample
        ``(h, w, K)`` coefficients of the sample (float32).
    sample_guide, target_guide
        ``(h, w, G)`` and ``(*shape, G)`` constraint values of the sample and of the target
        (log domain), or None for unguided synthesis.
    guide_weight
        ``sqrt(lambda)``: the weight of a constraint value in the neighbourhood distance.
    seed
        Seeds the choice of neighbourhoods the PCA bases are fitted to (and, unguided, the
        initial output).
    """
    sample = np.asarray(sample, np.float32)
    guided = sample_guide is not None and target_guide is not None and sample_guide.shape[-1]
    rng = np.random.default_rng(seed)
    rotation = leading_components(sample, params.search_energy)
    result = TextureOptimizationResult(np.empty(0, np.float32))
    x = None
    for level in range(params.levels - 1, -1, -1):
        start = time.perf_counter()
        factor = 2**level
        level_shape = (-(-shape[0] // factor), -(-shape[1] // factor))
        source = SampleLevel(downsample(sample, factor),
                             downsample(sample_guide, factor) if guided else None,
                             rotation, guide_weight, params, rng)
        target_l = downsample(target_guide, factor) if guided else None
        x = (initial(source, target_l, level_shape, params, rng) if x is None
             else upsample(x, level_shape))
        x, energies = optimize(source, x, target_l, params, final=level == 0)
        result.energy.append(energies)
        result.seconds.append(time.perf_counter() - start)
    result.coefficients = x
    return result


def optimize(source: SampleLevel, x: np.ndarray, target_guide: np.ndarray | None,
             params: TextureOptimizationParams, *, final: bool = False
             ) -> tuple[np.ndarray, list[float]]:
    """EM iterations of one level from the coefficients ``x`` (``(H, W, K)``).

    Returns the optimised coefficients and the energy after each E-step (never increasing).
    ``final`` (the finest level): the last M-step also gives ``params.pick`` of each texel to
    its best candidate (:func:`pick_vote`); the energies are those of the matches, before it.
    """
    p, s, r = params.patch, params.spacing, params.robust
    shape = x.shape[:2]
    gy, gx = grid(shape[0], p, s), grid(shape[1], p, s)
    qy, qx = (a.ravel() for a in np.meshgrid(gy, gx, indexing="ij"))
    match, energies = None, []
    for _ in range(params.iterations):
        query = _features(x, target_guide, source.rotation, source.guide_weight)
        projected = _project(query, gy, gx, p, source.basis, source.mean)
        if source.coherence is None:
            _, found = source.index.search(projected, params.candidates)
            found = np.where(found < 0, 0, found)  # fewer sample neighbourhoods than asked
        else:  # k-coherence from the previous E-step's matches (first: from seeds)
            if match is None:
                match = _seeds(source, query, projected, gy, gx, params)
            found = _nearest_candidates(projected, source,
                                        coherent_candidates(source, match, gy, gx),
                                        params.candidates)
        if match is not None:
            found = np.concatenate([match[:, None], found], axis=1)
        cy, cx = source.origin(found)
        dist = _distances(query, qy, qx, source.features, cy, cx, p)
        best = np.argmin(dist, axis=1)  # ties keep the earliest: the previous match
        match = found[np.arange(len(found)), best]
        d = dist[np.arange(len(found)), best]
        energies.append(_energy(d, r))
        my, mx = source.origin(match)
        x = _vote(source.coefficients, shape, qy, qx, my, mx, _robust_weights(d, r), p)
        if len(energies) > 1 and energies[-1] >= energies[-2] * (1 - 1e-7):
            break  # no neighbourhood found a better match: converged
    if (final and params.pick > 0 and target_guide is not None and source.guide is not None
            and target_guide.shape[-1] > 0):
        x = pick_vote(source, x, target_guide, qy, qx, match, params)
    return x, energies


PICK_QUERIES = 1 << 15  # texels whose nearest sample guides are searched at a time
PICK_EPS = 1.0  # the lookups' k-d tree search: within 2x the true distances (the pick is exact
# among the candidates; eps 0 and 2 picked the same on stone: error 0.0202 either way)


def pick_vote(source: SampleLevel, x: np.ndarray, target_guide: np.ndarray, qy: np.ndarray,
              qx: np.ndarray, match: np.ndarray, params: TextureOptimizationParams
              ) -> np.ndarray:
    """The finest level's last M-step, moved ``params.pick`` of the way to each texel's pick.

    Kwatra's M-step makes every texel the weighted mean of what the overlapping matches put
    there. Where the photos say more than a neighbourhood does (several photos under
    different lights pin down a texel's slope and albedo), that mean blurs texels that each
    fit the photos into one that fits none of them. A texel's candidates are the sample texels
    its ``patch^2`` overlapping matches put there and the ``params.pick_lookups`` sample texels
    whose constraint values are nearest to its own (approximately: a k-d tree searched with
    ``eps = PICK_EPS``, within 2x the true distances; a texel the sample holds exactly is always
    found); its pick is the one nearest in the search's own feature space, to the mean's
    leading coefficients and to the target's weighted constraint values (ties: the first,
    matches before lookups, in offset order). Returns ``(1 - pick) * mean + pick * picked``:
    half and half measured best over one and ten photos on rendered materials (BENCHMARKS.md,
    issue 57), since where one photo leaves a texel's slope open the mean of the plausible
    candidates is the better guess.
    Memory is a few arrays of the output's size and differences of :data:`PICK_QUERIES`
    texels at a time; the same bits for the same inputs.
    """
    h, w, k = x.shape
    p, sw = params.patch, source.features.shape[1]
    query = _features(x, target_guide, source.rotation, source.guide_weight).reshape(h * w, -1)
    features = source.features.reshape(-1, source.features.shape[-1])
    best = np.zeros(h * w, np.int64)
    best_d = np.full(h * w, np.inf, np.float32)

    def offer(texels: np.ndarray, candidates: np.ndarray) -> None:
        # ``texels`` are distinct within a call (one offset of the grid's distinct origins, or
        # a range), so plain indexing keeps each one's minimum; ties keep the earlier offer.
        # PICK_QUERIES at a time: the differences are (texels, features) floats
        for a in range(0, len(texels), PICK_QUERIES):
            t, c = texels[a : a + PICK_QUERIES], candidates[a : a + PICK_QUERIES]
            d = features[c] - query[t]
            d = np.einsum("qc,qc->q", d, d)
            better = d < best_d[t]
            best_d[t[better]] = d[better]
            best[t[better]] = c[better]

    my, mx = source.origin(match)
    for dy in range(p):
        for dx in range(p):
            offer((qy + dy) * w + qx + dx, (my + dy) * sw + mx + dx)
    lookups = min(params.pick_lookups, len(features))
    if lookups:
        lead = source.rotation.shape[1]
        tree = source.guide_tree
        for start in range(0, h * w, PICK_QUERIES):
            texels = np.arange(start, min(start + PICK_QUERIES, h * w))
            _, found = tree.query(query[texels, lead:], k=lookups, eps=PICK_EPS)
            for column in found.reshape(len(texels), lookups).T:
                offer(texels, column)
    picked = source.coefficients.reshape(-1, k)[best].reshape(h, w, k)
    pick = np.float32(params.pick)
    return ((np.float32(1) - pick) * x + pick * picked).astype(np.float32)


def leading_components(sample: np.ndarray, energy: float) -> np.ndarray:
    """Orthonormal ``(K, k)`` basis of the directions holding ``energy`` of the sample's variance.

    Distances between texels are kept up to the dropped share.
    """
    flat = sample.reshape(-1, sample.shape[-1]).astype(np.float64)
    flat = flat - flat.mean(axis=0)
    _, sv, vt = np.linalg.svd(flat, full_matrices=False)
    share = np.cumsum(sv**2) / max(np.sum(sv**2), 1e-300)
    k = int(np.searchsorted(share, energy) + 1) if share[-1] > 0 else 1
    return np.ascontiguousarray(vt[: min(k, len(sv))].T, np.float32)


def initial(source: SampleLevel, target_guide: np.ndarray | None, shape: tuple[int, int],
            params: TextureOptimizationParams, rng) -> np.ndarray:
    """The coarsest level's start: each neighbourhood matched by its guide alone (or random)."""
    p = params.patch
    gy, gx = grid(shape[0], p, params.spacing), grid(shape[1], p, params.spacing)
    qy, qx = (a.ravel() for a in np.meshgrid(gy, gx, indexing="ij"))
    if target_guide is None:
        found = rng.integers(0, len(source.ys) * source.width, len(qy))
    else:
        query_guide = np.float32(source.guide_weight) * np.asarray(target_guide, np.float32)
        sample_guide = np.float32(source.guide_weight) * source.guide
        index = _flat_index(_patches(sample_guide, source.ys, source.xs, p))
        _, found = index.search(np.ascontiguousarray(_patches(query_guide, gy, gx, p)), 1)
        found = found[:, 0]
    my, mx = source.origin(found)
    return _vote(source.coefficients, shape, qy, qx, my, mx, np.ones(len(qy), np.float32), p)
