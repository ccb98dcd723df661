"""Block, overlap and tile size for quilting a sample: what a user who gives none gets.

**Block.** A periodic sample gets blocks of one lattice period (the longer reduced periodicity
vector, rounded to an even size, within 16-96 texels and at most half the sample), so every
patch holds a whole cell and overlaps compare like with like; the overlap is a quarter of the
block. Without a clear lattice the block is 32; when no plan of it keeps the borders within
the bound (a structured texture whose long lines cannot close at that scale, such as
scikit-image's brick photo), :data:`LARGER_BLOCKS` are tried in turn (:func:`layouts`).

**Tile size.** A tile of a periodic texture must be a whole number of periods along both
axes: otherwise the pattern arrives at the tile's far border out of phase with its near one,
and the last row of patches, which must join both, breaks the pattern along the border
(fabric, period 11.3 texels, in a 252-texel tile: every plan did; BENCHMARKS.md). Without a
given size the tile is the size nearest the sample's that is a multiple of the patch step and
within :data:`PHASE_TOLERANCE` of a lattice vector along each axis; a given size that is not
is planned as asked, with a warning naming sizes that are.

The lattice is detected (:func:`tasks.periodicity.detect_lattice`) on the luminance of the
central 512 x 512 texels at most.
"""

from __future__ import annotations

import functools
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from tasks.periodicity import Lattice

DEFAULT_BLOCK = 32
BLOCK_RANGE = (16, 96)
LARGER_BLOCKS = (48, 64, 96)  # tried in turn when the default block's plans fail the check
PHASE_TOLERANCE = 1.0  # texels: a tile side this close to a lattice vector closes in phase
# texels: the farthest the texel nearest a lattice point lies from it. Sample positions in
# phase with another are this close to a lattice vector from it: on a strictly periodic
# sample a position one texel off (within PHASE_TOLERANCE) breaks the pattern by a texel
PHASE_ROUNDING = 0.5**0.5
MIN_CONFIDENCE = 0.5


def overlap_for(block: int) -> int:
    """The default overlap of a block: a quarter of it, even, at least 2."""
    return max(2, 2 * round(block / 8))


def sample_lattice(reference: np.ndarray, min_confidence: float = MIN_CONFIDENCE
                   ) -> Lattice | None:
    """The sample's lattice, or ``None`` without a clear one (or below 32 texels)."""
    from tasks.reference import luminance

    reference = np.asarray(reference, np.float64)
    gray = luminance(reference) if reference.ndim == 3 and reference.shape[-1] == 3 else (
        reference.mean(axis=-1) if reference.ndim == 3 else reference)
    if min(gray.shape) < 32:
        return None
    crop = tuple(slice(max(0, (n - 512) // 2), max(0, (n - 512) // 2) + 512) for n in gray.shape)
    gray = gray[crop]
    lattice = _detected(gray.shape, np.ascontiguousarray(gray, np.float64).tobytes())
    return lattice if lattice.confidence >= min_confidence else None


@functools.lru_cache(maxsize=4)
def _detected(shape: tuple[int, int], gray: bytes) -> Lattice:
    """The lattice of a float64 grey image given by its bytes, for the last few images.

    The quilt stage asks twice of a sample without a clear lattice (for the lattice, then for
    the confidence that choose_block reports): 0.1 s of a 2 s plan on a 256^2 photo.
    """
    from tasks.periodicity import detect_lattice

    return detect_lattice(np.frombuffer(gray, np.float64).reshape(shape))


def lattice_mismatch(vectors, lattice: Lattice) -> np.ndarray | float:
    """Distance (texels) from each ``(dy, dx)`` of ``vectors`` to the nearest lattice point."""
    vectors = np.asarray(vectors, np.float64)
    basis = np.array([lattice.u, lattice.v], np.float64).T
    coords = np.rint(vectors @ np.linalg.inv(basis).T)
    best = np.full(vectors.shape[:-1], np.inf)
    for da in (-1, 0, 1):  # rounding is exact only for orthogonal bases: try the neighbours
        for db in (-1, 0, 1):
            points = (coords + np.array([da, db])) @ basis.T
            best = np.minimum(best, np.hypot(*np.moveaxis(points - vectors, -1, 0)))
    return float(best) if best.ndim == 0 else best


def in_phase(shape: tuple[int, int], origin: tuple[int, int], lattice: Lattice) -> np.ndarray:
    """Positions of a ``shape`` grid a lattice vector away from ``origin``, to the texel.

    The offset must lie within :data:`PHASE_ROUNDING` of a lattice point: on an integer
    lattice exactly on one.
    """
    ys, xs = np.indices(shape)
    offsets = np.stack([ys - origin[0], xs - origin[1]], axis=-1)
    return lattice_mismatch(offsets, lattice) <= PHASE_ROUNDING + 1e-9


def tile_mismatch(tile: tuple[int, int], lattice: Lattice | None) -> tuple[float, float]:
    """Phase mismatch of a tile's height and width against the lattice (0 without one)."""
    if lattice is None:
        return (0.0, 0.0)
    return (lattice_mismatch((tile[0], 0), lattice), lattice_mismatch((0, tile[1]), lattice))


def commensurate_sizes(wanted: int, step: int, axis: int, lattice: Lattice, *,
                       count: int = 3) -> list[int]:
    """Tile sides in phase with the lattice along ``axis``, nearest ``wanted`` first.

    Multiples of ``step``, at least two steps and at most twice ``wanted``.
    """
    sizes = []
    for n in range(2 * step, 2 * max(wanted, 2 * step) + 1, step):
        vector = (n, 0) if axis == 0 else (0, n)
        if lattice_mismatch(vector, lattice) <= PHASE_TOLERANCE:
            sizes.append(n)
    return sorted(sizes, key=lambda n: (abs(n - wanted), n))[:count]


def phase_lattice(lattice: Lattice | None, sample: tuple[int, int]
                  ) -> tuple[tuple[float, float], tuple[float, float]] | None:
    """The lattice whose phase corner patches share.

    The axis-aligned lattice a tile's sides are whole periods of, when both its periods fit in
    half the sample, else the sample's own. The detected lattice can be finer than the
    texture's repeat (a plain weave's crossings look alike at half a cell, but the threads on
    top alternate): patches one detected period apart then differ, and strips between them
    cannot meet. Tile sides are whole periods of
    the axis-aligned lattice, so patches a whole axis-aligned cell apart always can.
    """
    if lattice is None:
        return None
    periods = []
    for axis, n in enumerate(sample):
        found = [p for p in range(2, n // 2 + 1)
                 if lattice_mismatch((p, 0) if axis == 0 else (0, p), lattice)
                 <= PHASE_TOLERANCE / 2]
        periods.append(found[0] if found else None)
    if None in periods:
        return (lattice.u, lattice.v)
    return ((float(periods[0]), 0.0), (0.0, float(periods[1])))


def default_tile(sample: tuple[int, int], step: int, lattice: Lattice | None
                 ) -> tuple[int, int]:
    """The tile size when none is given: the sample's size, as close as it can (see module)."""
    shape = []
    for axis, n in enumerate(sample):
        plain = max(2 * step, (n // step) * step)
        sizes = [] if lattice is None else commensurate_sizes(n, step, axis, lattice, count=1)
        shape.append(sizes[0] if sizes else plain)
    return tuple(shape)


def choose_block(reference: np.ndarray, min_confidence: float = MIN_CONFIDENCE,
                 tile: tuple[int, int] | None = None, lattice: Lattice | None = None
                 ) -> tuple[int, int, str]:
    """Block and overlap for a reference image, and why (when the user gave no block size).

    See the module. With a given ``tile`` size, the block nearest the period whose step
    divides the tile is taken (within a quarter of the period), else the default. ``lattice``:
    the sample's, when already detected (:func:`sample_lattice`).
    """
    default = (DEFAULT_BLOCK, overlap_for(DEFAULT_BLOCK))
    reference = np.asarray(reference)
    if min(reference.shape[:2]) < 32:
        return (*default, "the sample is too small to detect a lattice: the default")
    if lattice is None:
        found = sample_lattice(reference, 0.0)
        if found is None or found.confidence < min_confidence:
            confidence = 0.0 if found is None else found.confidence
            return (*default, f"no clear lattice (confidence {confidence:.2f}): the default")
        lattice = found
    period = max(lattice.lengths_px)
    low, high = BLOCK_RANGE[0], min(BLOCK_RANGE[1], min(reference.shape[:2]) // 2)
    wanted = int(np.clip(2 * round(period / 2), low, high))
    wanted -= wanted % 2
    why = f"one period of the detected lattice ({period:.1f} px, confidence " \
          f"{lattice.confidence:.2f})"
    if tile is None:
        return wanted, overlap_for(wanted), why
    reach = max(2, int(period / 4))
    first = max(low, wanted - reach)
    first += first % 2  # even blocks, as the wanted one is (an odd reach gave odd ones only)
    for block in sorted(range(first, min(high, wanted + reach) + 1, 2),
                        key=lambda b: (abs(b - wanted), b)):
        step = block - overlap_for(block)
        if all(n % step == 0 and n >= 2 * step for n in tile):
            return block, overlap_for(block), why + (
                f", the nearest whose step divides the tile {tile[0]} x {tile[1]}"
                if block != wanted else "")
    return (*default, why + f", but no block near it divides the tile {tile[0]} x {tile[1]}: "
                            "the default")


@dataclass(frozen=True)
class Layout:
    """A block, overlap and tile size to plan with, and why they were chosen."""

    block: int
    overlap: int
    tile: tuple[int, int]
    why: str

    @property
    def step(self) -> int:
        """Distance between neighbouring windows."""
        return self.block - self.overlap


def layouts(reference: np.ndarray, *, block: int | None, overlap: int | None,
            tile: tuple[int, int] | None, lattice: Lattice | None) -> Iterator[Layout]:
    """The layouts to plan with, in order (see the module).

    The given or automatic one, then, for an automatic block on a sample without a lattice,
    :data:`LARGER_BLOCKS` that fit the sample and the tile.
    """
    sample = np.shape(reference)[:2]
    if block is not None:
        o = overlap_for(block) if overlap is None else overlap
        yield Layout(block, o, tile or default_tile(sample, block - o, lattice), "given")
        return
    auto, auto_overlap, why = choose_block(reference, tile=tile, lattice=lattice)
    o = auto_overlap if overlap is None else overlap
    yield Layout(auto, o, tile or default_tile(sample, auto - o, lattice), why)
    if lattice is not None:
        return
    for larger in LARGER_BLOCKS:
        o = overlap_for(larger) if overlap is None else overlap
        if larger <= auto or larger > min(sample) // 2 or o >= larger // 2:
            continue
        step = larger - o
        if tile is not None and not all(n % step == 0 and n >= 2 * step for n in tile):
            continue
        yield Layout(larger, o, tile or default_tile(sample, step, None),
                     f"block {auto}'s borders did not close: the next larger")
