"""Corner tile sets from quilting's pieces, every tile's borders checked (paper 003, 2.4).

:mod:`tasks.quilting` places patches; this module plans a whole tile set with them: one corner
patch per corner type, one edge strip per ordered pair of types and direction, then every tile
from its four strips inwards (see :mod:`tasks.quilting` for the geometry).

**Where the joins fall.** A tile's interior must join the four strips planned before it. The
paper fills it row by row from the top-left, so its last row and column of patches must join
a strip on the far side as well as the patches above and beside them. On a structured texture
no sample window fits all three: on scikit-image's brick photo (the three-layer reference of
``btf quilt``, 16 tiles of 240^2, block 32) no first plan of a tile passed the check below,
its far borders standing out 1.2-2.2x from its inside where brick rows met out of phase.
So each plan fills its interior quadrant by quadrant, each from its tile corner inwards
(:func:`fill_order`): every patch along a border is placed while it meets only the strip and
the patches already placed on its way in, and the quadrants close against each other inside
the tile, where the closing joins are the kind every quilted texture has. Only the four
patches where two quadrants meet at a border close there. On the same photo 92% of first plans
pass (72% at block 48, against 34% filling by rows); the whole tile's mean distance to the
photo's patches rose 2% (BENCHMARKS.md, "Quilting on photos").

Strips are planned the same way (:func:`strip_order`): from the corner patches at both
ends inwards, closing in the middle. Planned from one end, a strip's last patch joined the
corner patch at its other end, and with every strip planned left to right and top to bottom
both hard joins of a tile's bottom and right strips met at its bottom-right corner, where
most far-border failures lay (brick, six random crops: 66% of tiles' first plans passed,
90% with strips planned inwards).

**Why a check.** Closing joins may still break the texture's structure. So every tile is
measured once planned (:class:`BorderCheck`: the seam and structure ratios of
:mod:`tasks.seams` on the tile framed by the outer halves of its strips, i.e. what its
neighbours show there), and while its worst border stands out more than ``max_seam`` times
its inside:

1. every tile not yet planned is planned once; where two or more tiles fail at the same
   strip (their worst border), the fault is the strip's: those strips are planned again at
   once from other streams, :data:`STRIP_CANDIDATES` times each, keeping the plan whose
   middle line stands out least on its own (:meth:`_TileSetPlanner.strip_figure`, before
   any tile is filled along it), and every tile along them is planned again in the next
   round (on brick, a draw whose 14 tiles of 16 failed at four strips took 75 interior
   plans when each was first planned four times, 32 this way; the best of four strips
   took two draws of 44 and 34 interior plans to 28 and 25); when such a strip has been planned
   :data:`STRIP_ATTEMPTS` times already, the whole set is planned again at once from new
   corner patches (on brick the tiles along it went on failing at it through all their
   interior plans: the corner patches it joins leave it no good plan);
2. the other tiles beyond the bound have their interiors planned again from other random
   streams, up to :data:`INTERIOR_ATTEMPTS` plans in all, each plan starting with the next
   quadrant so that the closing joins change places; the best is kept (a tile alone beyond
   the bound has its next plans made beside it on the idle threads);
3. the strip along the worst border of each tile still beyond the bound is planned again
   the same way (the corner patches stay), and so is every tile that uses that strip; after
   :data:`STRIP_ATTEMPTS` plans of a strip, the whole set is planned again from new corner
   patches. A round is one pass of these over the tiles not yet planned; at most
   ``attempts`` rounds. A periodic tile (``V = 1``) has no strips of its own: with more than one
   thread, its plans are made ahead, beside each other.

The best plan of a tile is kept; when a tile's best still exceeds the bound, planning stops
with :class:`SeamError` naming the tile, its worst border and the figure. Every stream is
derived from the seed and the piece's name, so the same seed gives the same tile set.
"""

from __future__ import annotations

import itertools
import time
from collections import Counter
from collections.abc import Callable, Iterable
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
from threadpoolctl import threadpool_limits

from tasks.canvas import Canvas
from tasks.periodicity import Lattice
from tasks.quilt_layout import in_phase
from tasks.quilting import Blend, Placement, Planner, QuiltParams
from tasks.seams import (
    PATCH,
    BorderFigures,
    Borders,
    PatchExemplar,
    border_figures,
    line_sides,
)

HORIZONTAL, VERTICAL = "horizontal", "vertical"
# a tile's check measures its inside on every other patch of the grid each way (the borders'
# sides on every patch): :func:`tasks.seams.structure_ratios`
SPARSE_INSIDE = 2
# a thinned check that passes within this share under the bound is measured again with the
# whole inside, whose verdict counts: thinning moved an inside's mean by up to 2.9%, and a
# brick draw passed at the bound thinned while its mosaic stood at 1.307 (test_quilt's photo
# draw, crop (154, 172), seed 2056478575)
THIN_MARGIN = 0.05


@dataclass(frozen=True)
class TileCheck:
    """How a tile's borders compare with its inside, and the interiors planned until then."""

    tile: str
    plans: int
    figures: BorderFigures
    bound: float

    @property
    def passed(self) -> bool:
        """Whether both ratios of every border are within the bound."""
        return self.figures.worst <= self.bound

    def to_dict(self) -> dict:
        """JSON-able record (store attrs)."""
        f = self.figures
        return {"tile": self.tile, "plans": self.plans, "seam": round(f.worst_seam, 4),
                "structure": round(f.worst_structure, 4), "worst": f.worst_line()}


class SeamError(ValueError):
    """No plan of a tile kept its borders within the bound."""

    def __init__(self, check: TileCheck, bound: float):
        super().__init__(
            f"{check.tile}: after {check.plans} plans of its interior, its best border still "
            f"stands out {check.figures.worst:.2f}x from its inside (worst: "
            f"{check.figures.worst_line()}; bound {bound}); try another seed, more "
            "candidates or another block size, or allow more with a larger bound")
        self.check = check


class BorderCheck:
    """Seam and structure ratios of a planned tile's borders (:mod:`tasks.seams`).

    A periodic tile (``V = 1``) is measured as the torus it is. A tile of a larger set is
    measured framed by the halves of its four edge strips that lie beyond its borders: its
    side of every border sees the tile and, within half a structure patch beyond, the strip
    its neighbours share; their sides are theirs to pass. Either way each side of a border is
    compared with the tile's inside, the patches whose centres lie more than half a step
    from every border (every other one of them each way, :data:`SPARSE_INSIDE`). Structure
    patches are ``min(16, block)`` texels, compared with the
    reference image's own.
    """

    def __init__(self, reference: np.ndarray, params: QuiltParams,
                 exemplar: PatchExemplar | None = None):
        self.half = params.block // 2
        self.reach = params.step / 2
        self.periodic = params.corners == 1
        self.bound = params.max_seam
        self.exemplar = exemplar or PatchExemplar(reference, patch=self.patch(params))

    @staticmethod
    def patch(params: QuiltParams) -> int:
        """The structure patch's side for ``params``' block."""
        return min(PATCH, params.block)

    def frame(self, tile: Canvas, top: Canvas, bottom: Canvas, left: Canvas, right: Canvas
              ) -> np.ndarray:
        """The tile's values framed by the outer halves of its edge strips."""
        h = self.half
        th, tw = tile.shape
        out = np.empty((th + 2 * h, tw + 2 * h, tile.value.shape[-1]), np.float32)
        out[:h] = top.value[:h]  # horizontal strips span the corner patches at both ends
        out[h + th :] = bottom.value[h:]
        out[h : h + th, :h] = left.value[h : h + th, :h]
        out[h : h + th, h + tw :] = right.value[h : h + th, h:]
        out[h : h + th, h : h + tw] = tile.value
        return out

    def figures(self, tile: Canvas, top: Canvas, bottom: Canvas, left: Canvas,
                right: Canvas) -> BorderFigures:
        """Both ratios of the tile's borders (periodic: its wrap, rows then columns).

        On a thinned inside (:data:`SPARSE_INSIDE`); a tile that passes by less than
        :data:`THIN_MARGIN` on a thinned inside is measured again on its whole inside, which
        decides (an inside too small to thin was measured whole already).
        """
        if self.periodic:
            values, borders = tile.value, Borders.periodic()
        else:
            values = self.frame(tile, top, bottom, left, right)
            borders = Borders.framed(tile.shape, self.half)
        thinned: list[bool] = []
        figures = border_figures(self.exemplar, values, borders, reach=self.reach,
                                 sparse_inside=SPARSE_INSIDE, thinned=thinned)
        if thinned[0] and (1 - THIN_MARGIN) * self.bound < figures.worst <= self.bound:
            figures = border_figures(self.exemplar, values, borders, reach=self.reach,
                                     sparse_inside=1)
        return figures


@dataclass
class TileSet:
    """A planned tile set: one canvas per tile and the corner types of each."""

    tiles: list[Canvas]
    corners: np.ndarray  # (tiles, 4) corner types: top-left, top-right, bottom-left, bottom-right
    placements: list[Placement]
    sample_shape: tuple[int, int]
    # the edge strips by ("horizontal" | "vertical", first corner type, last corner type)
    strips: dict[tuple[str, int, int], Canvas] = field(default_factory=dict)
    checks: list[TileCheck] = field(default_factory=list)  # per tile

    @property
    def worst(self) -> float:
        """The largest border ratio over the tiles."""
        return max(c.figures.worst for c in self.checks)


@dataclass
class _Piece:
    """A planned canvas and the placements that made it."""

    canvas: Canvas
    placements: list[Placement]
    blends: list[Blend] = field(default_factory=list)


@dataclass
class _Tile:
    """A tile's best plan so far and its check."""

    piece: _Piece
    check: TileCheck

    @property
    def passed(self) -> bool:
        return self.check.passed


class _TileSetPlanner:
    """The pieces of one tile set, each planned from a random stream of its own.

    A piece's stream is ``(seed, kind, its key, generation)``: planning a piece again takes
    the next generation, so a retry never repeats a plan and the same seed repeats them all.
    """

    KINDS: ClassVar[dict[str, int]] = {"corner": 0, HORIZONTAL: 1, VERTICAL: 2, "tile": 3}

    def __init__(self, reference: np.ndarray, params: QuiltParams, seed: int,
                 exemplar: PatchExemplar | None = None):
        self.params, self.seed = params, seed
        self.planner = Planner(reference, params, np.random.default_rng(seed))
        self.channels = reference.shape[-1]
        self.reference_shape = reference.shape[:2]
        self.check = BorderCheck(reference, params, exemplar)
        v = range(params.corners)
        self.types = list(itertools.product(v, repeat=4))
        self.strip_keys = [(d, a, z) for d in (HORIZONTAL, VERTICAL) for a in v for z in v]
        self.generation: dict[tuple, int] = {}
        self.plans = [0] * len(self.types)  # interiors planned, per tile
        self.corners: list[_Piece] = []
        self.strips: dict[tuple[str, int, int], _Piece] = {}
        self.tiles: dict[int, _Tile] = {}

    def _plan(self, key: tuple, place, canvas: Canvas, generation: int | None = None
              ) -> _Piece:
        """Plan one piece on ``canvas`` with stream ``generation`` of ``key`` (default: next).

        ``place(planner, canvas)`` places the piece's patches with a planner of its own (its
        stream and placements), so pieces may be planned in threads.
        """
        if generation is None:
            generation = self.generation.get(key, 0)
            self.generation[key] = generation + 1
        planner = self.planner.with_stream(np.random.default_rng(
            (self.seed, self.KINDS[key[0]], *key[1:], generation)))
        blends = place(planner, canvas)
        return _Piece(canvas, planner.placements, blends or [])

    def plan_all(self, pool: Executor | None = None) -> None:
        """Corner patches (phase 1) and edge strips (phases 2, 3), all of them again."""
        b = self.params.block
        self.corners, phase = [], None
        for c in range(self.params.corners):
            def place(planner, canvas, c=c, phase=phase):
                return [planner.place(canvas, f"corner {c}", 0, 0, border="both",
                                      allowed=phase)]

            self.corners.append(self._plan(("corner", c), place,
                                           Canvas.empty(b, b, self.channels)))
            if self.params.lattice is not None and phase is None:
                u, v = self.params.lattice
                phase = in_phase(self.planner.search.valid,
                                 self.corners[0].placements[0].source, Lattice(u, v, 1.0))
        self.plan_strips(self.strip_keys, pool)
        self.tiles = {}

    def plan_strips(self, keys: list[tuple[str, int, int]], pool: Executor | None = None,
                    candidates: int = 1) -> None:
        """:meth:`plan_strip` for each of ``keys``, at once on ``pool`` if given.

        Each strip depends only on the corner patches and its own stream. With
        ``candidates`` > 1 each strip is planned that many times (from its next streams) and
        the plan whose border line stands out least (:meth:`strip_figure`) is kept.
        """
        jobs = []
        for key in keys:
            first = self.generation.get(key, 0)
            self.generation[key] = first + candidates
            jobs += [(key, g) for g in range(first, first + candidates)]

        def planned(job):
            piece = self._strip(*job)
            return piece, self.strip_figure(job[0], piece) if candidates > 1 else 0.0

        results = list((pool.map if pool is not None else map)(planned, jobs))  # all of them
        for key in keys:
            mine = [r for (k, _), r in zip(jobs, results, strict=True) if k == key]
            self._keep_strip(key, min(mine, key=lambda r: r[1])[0])  # the first of equals

    def plan_strip(self, key: tuple[str, int, int]) -> None:
        """Edge strip ``key`` (phases 2 and 3) again; the tiles along it must be planned again."""
        self.plan_strips([key])

    def _keep_strip(self, key: tuple[str, int, int], piece: _Piece) -> None:
        self.strips[key] = piece
        for number, types in enumerate(self.types):
            if key in self.tile_strips(types):
                self.tiles.pop(number, None)

    def _strip(self, key: tuple[str, int, int], generation: int) -> _Piece:
        """Plan ``generation`` of edge strip ``key`` (phases 2 and 3)."""
        direction, a, z = key
        b, s = self.params.block, self.params.step
        horizontal = direction == HORIZONTAL
        length = self.params.tile[1] if horizontal else self.params.tile[0]
        canvas = Canvas.empty(*((b, length + b) if horizontal else (length + b, b)),
                              self.channels)
        ends = [(0, 0), (0, length)] if horizontal else [(0, 0), (length, 0)]
        for (y, x), c in zip(ends, (a, z), strict=True):
            canvas.copy_from(self.corners[c].canvas, slice(y, y + b), slice(x, x + b),
                             slice(None), slice(None))
        name = f"{direction} edge {a}{z}"
        steps = strip_order(length // s, generation)

        def place(planner, canvas):
            return [planner.place(canvas, name, *((0, k * s) if horizontal else (k * s, 0)),
                                  border="row" if horizontal else "col")
                    for k in steps]

        return self._plan(key, place, canvas, generation)

    def strip_figure(self, key: tuple[str, int, int], piece: _Piece) -> float:
        """How far a strip's border line stands out, to choose between plans of one strip.

        The mean nearest-patch distance (:class:`BorderCheck`'s structure patches) of the
        patches centred within the check's reach of the line through the strip's middle,
        the worse of its two sides: what the tiles on either side will see there.
        """
        value = piece.canvas.value
        d, cy, cx = self.check.exemplar.distance_map(value, wrap=False)
        sides = line_sides(d, cy, cx, "row" if key[0] == HORIZONTAL else "col",
                           self.params.block // 2, value.shape[:2], wrap=False,
                           reach=self.check.reach)
        return max(float(side.mean()) for side in sides if side.size)

    def tile_strips(self, types: tuple[int, int, int, int]) -> list[tuple[str, int, int]]:
        """The strips along a tile's top, bottom, left and right borders."""
        tl, tr, bl, br = types
        return [(HORIZONTAL, tl, tr), (HORIZONTAL, bl, br), (VERTICAL, tl, bl),
                (VERTICAL, tr, br)]

    def fill(self, number: int, generation: int | None = None) -> _Piece:
        """Phase 4: tile ``number`` from its edge strips inwards, from the corner of its plan.

        ``generation``: which plan of the tile; by default the next one, counted.
        """
        key = ("tile", number)
        if generation is None:
            generation = self.generation.get(key, 0)
            self.generation[key] = generation + 1
            self.plans[number] += 1
        b, s = self.params.block, self.params.step
        th, tw = self.params.tile
        half = b // 2
        types = self.types[number]
        top, bottom, left, right = (self.strips[k] for k in self.tile_strips(types))
        canvas = Canvas.empty(th, tw, self.channels)
        canvas.copy_from(top.canvas, slice(0, half), slice(0, tw), slice(half, b),
                         slice(half, half + tw))
        canvas.copy_from(bottom.canvas, slice(th - half, th), slice(0, tw), slice(0, half),
                         slice(half, half + tw))
        canvas.copy_from(left.canvas, slice(half, th - half), slice(0, half), slice(b, th),
                         slice(half, b))
        canvas.copy_from(right.canvas, slice(half, th - half), slice(tw - half, tw),
                         slice(b, th), slice(0, half))
        # the corner quadrants: vertical edge patches blended again (see tasks.quilting)
        quadrants = np.r_[0:half, th - half : th]
        for blend in left.blends:
            blend.again(canvas, -half, -half, quadrants)
        for blend in right.blends:
            blend.again(canvas, -half, tw - half, quadrants)
        name = "tile " + "".join(map(str, types))
        order = fill_order(th // s, tw // s, generation)

        def place(planner, canvas):
            for i, j in order:
                planner.place(canvas, name, i * s - half, j * s - half)
            if not canvas.filled.all():
                raise AssertionError("a tile was left with empty pixels")

        return self._plan(key, place, canvas, generation)

    def plan_tile(self, number: int, attempts: int, spare: Executor | None = None,
                  ahead: int = 0, best: _Tile | None = None) -> _Tile:
        """A tile's interior, planned until its borders pass, at most ``attempts`` times.

        With a ``spare`` pool, the ``ahead`` plans after each are made beside it in case it
        fails; the tile and its count of plans are the same as without. ``best``: a plan of
        the tile made before along the same strips, kept if none of these is better.
        """
        key = ("tile", number)
        first = self.generation.get(key, 0)
        strips = [self.strips[k].canvas for k in self.tile_strips(self.types[number])]

        def attempt(generation: int) -> tuple[_Piece, BorderFigures]:
            piece = self.fill(number, generation)
            return piece, self.check.figures(piece.canvas, *strips)

        early: dict[int, Future] = {}
        best = None if best is None else (best.piece, best.check.figures)
        used = 0
        for generation in range(first, first + attempts):
            if spare is not None:
                for g in range(generation + 1, min(generation + 1 + ahead, first + attempts)):
                    if g not in early:
                        early[g] = spare.submit(attempt, g)
            piece, figures = (early.pop(generation).result() if generation in early
                              else attempt(generation))
            used += 1
            if best is None or figures.worst < best[1].worst:
                best = (piece, figures)
            if figures.worst <= self.params.max_seam:
                break
        for future in early.values():  # not needed (one already running ends unused)
            future.cancel()
        self.generation[key] = first + used
        self.plans[number] += used
        name = "tile " + "".join(map(str, self.types[number]))
        check = TileCheck(name, self.plans[number], best[1], self.params.max_seam)
        return _Tile(best[0], check)

    def worst_strip(self, number: int) -> tuple[str, int, int]:
        """The strip along the tile's border with the largest ratio of either kind."""
        figures = self.tiles[number].check.figures
        worst = int(np.argmax(np.maximum(figures.seam, figures.structure)))
        strips = self.tile_strips(self.types[number])
        # a periodic tile's lines are its wrap: rows (its top = bottom strip), columns
        return strips[2 * worst] if len(figures.lines) == 2 else strips[worst]

    def result(self) -> TileSet:
        """The tile set as planned (every tile planned)."""
        n = len(self.types)
        placements = [p for c in self.corners for p in c.placements]
        placements += [p for k in self.strip_keys for p in self.strips[k].placements]
        placements += [p for i in range(n) for p in self.tiles[i].piece.placements]
        return TileSet([self.tiles[i].piece.canvas for i in range(n)],
                       np.array(self.types, np.int64), placements, self.reference_shape,
                       {k: self.strips[k].canvas for k in self.strip_keys},
                       [self.tiles[i].check for i in range(n)])


INTERIOR_ATTEMPTS = 4  # plans of a tile's interior along one set of strips
# the quadrants of an interior in the order each plan fills them, by its generation: top-left,
# top-right, bottom-left, bottom-right, then the same turned by one each plan
QUADRANTS = ((False, False), (False, True), (True, False), (True, True))


def strip_order(count: int, generation: int) -> list[int]:
    """A strip's patch positions ``1 .. count - 1`` in order: from both ends inwards.

    Each half from the corner patch at its end, so that the join that closes a strip (its
    last patch, between two placed ones) falls in its middle, not beside a corner patch where
    the tiles' corners are; every second plan starts with the other half.
    """
    near = list(range(1, count // 2 + 1))
    far = list(range(count - 1, count // 2, -1))
    return far + near if generation % 2 else near + far


def fill_order(rows: int, cols: int, generation: int) -> list[tuple[int, int]]:
    """The interior's patch positions ``(i, j)``, ``1 <= i < rows, 1 <= j < cols``, in order.

    Quadrant by quadrant, each from its tile corner inwards (see the module); the first
    quadrant is :data:`QUADRANTS` turned by ``generation``.
    """
    halves = []
    for n in (rows, cols):
        near = list(range(1, n // 2 + 1))
        halves.append((near, list(range(n - 1, n // 2, -1))))
    k = generation % len(QUADRANTS)
    return [(i, j) for far_row, far_col in QUADRANTS[k:] + QUADRANTS[:k]
            for i in halves[0][far_row] for j in halves[1][far_col]]


STRIP_ATTEMPTS = 2  # plans of a strip before the whole tile set is planned again
STRIP_CANDIDATES = 4  # plans of a strip planned again, the best kept (see plan_strips)


def plan_tiles(reference: np.ndarray, params: QuiltParams, *, seed: int,
               exemplar: PatchExemplar | None = None,
               progress: Callable[[str], None] | None = None, threads: int = 1) -> TileSet:
    """Plan a corner tile set (``V^4`` tiles; one periodic tile for ``V = 1``), see the module.

    Parameters
    ----------
    reference
        Reference image ``(h, w, channels)`` (float).
    params
        Block, overlap, candidates, corner types, tile size and the border check's bound
        (``max_seam``) and budget (``attempts``: rounds of planning again).
    seed
        Seed of every random choice: the same seed gives the same plan.
    exemplar
        The border check's patches of ``reference`` (:class:`BorderCheck`), when made
        already for another plan with the same structure patch.
    progress
        Called with a line after every round that leaves tiles beyond the bound (and the
        round that ends it), and within a round of many tiles every
        :data:`PROGRESS_SECONDS`.
    threads
        Tiles planned at once within a round. Each tile's plans depend only on its strips
        and its own streams, so the tile set is the same for any number.

    Raises
    ------
    SeamError
        When no round kept every tile within ``params.max_seam`` (see the module).
    """
    reference = np.asarray(reference, np.float32)
    if reference.ndim == 2:
        reference = reference[..., None]
    plan = _TileSetPlanner(reference, params, seed, exemplar)
    pool = ThreadPoolExecutor(max(1, threads))
    try:
        # one BLAS thread: the planner's products are small, and OpenBLAS's own threads spent
        # a core spinning beside them (half the CPU time of a plan; BENCHMARKS.md, "Quilting")
        with threadpool_limits(1, user_api="blas"):
            return _rounds(plan, _Progress(plan, progress), pool, max(1, threads))
    finally:  # a plan made ahead and not needed is not waited for
        pool.shutdown(wait=False, cancel_futures=True)


def _rounds(plan: _TileSetPlanner, report: _Progress, pool: Executor, threads: int) -> TileSet:
    """:func:`plan_tiles`' rounds, each tile of a round planned on ``pool``."""
    params = plan.params
    best: TileSet | None = None
    strip_plans: dict[tuple, int] = {}
    plan.plan_all(pool)
    for round_ in range(params.attempts):
        pending = [n for n in range(len(plan.types)) if n not in plan.tiles]
        if len(pending) == 1 and threads > 1:  # a periodic tile: its next plans beside it
            plan.tiles[pending[0]] = plan.plan_tile(pending[0], INTERIOR_ATTEMPTS, spare=pool,
                                                    ahead=threads - 1)
        elif pending:
            # one plan of each tile first: where tiles along one strip fail at it, the strip
            # is planned again at once (planning their interiors again would not help)
            for number, tile in zip(pending, pool.map(lambda n: plan.plan_tile(n, 1), pending),
                                    strict=True):
                plan.tiles[number] = tile
                report.tile(round_)
            failed = [n for n in pending if not plan.tiles[n].passed]
            blamed = Counter(plan.worst_strip(n) for n in failed)
            shared = sorted(k for k, count in blamed.items() if count >= 2)
            if shared and round_ + 1 < params.attempts:
                result = plan.result()
                if best is None or result.worst < best.worst:
                    best = result
                anew = any(strip_plans.get(k, 1) >= STRIP_ATTEMPTS for k in shared)
                report.round(round_, failed, shared=len(shared), anew=anew)
                if anew:
                    # tiles still failing at a strip planned that often: its corner patches
                    # are the fault (planning those tiles' interiors again did not help)
                    plan.plan_all(pool)
                    strip_plans = {}
                    continue
                plan.plan_strips(shared, pool, STRIP_CANDIDATES)
                for key in shared:
                    strip_plans[key] = strip_plans.get(key, 1) + 1
                continue
            # the others: the rest of their plans, the first kept if none is better; one
            # alone has its next plans made beside it on the idle threads
            if len(failed) == 1 and threads > 1:
                plan.tiles[failed[0]] = plan.plan_tile(
                    failed[0], INTERIOR_ATTEMPTS - 1, spare=pool, ahead=threads - 1,
                    best=plan.tiles[failed[0]])
            else:
                again = pool.map(lambda n: plan.plan_tile(n, INTERIOR_ATTEMPTS - 1,
                                                          best=plan.tiles[n]), failed)
                for number, tile in zip(failed, again, strict=True):
                    plan.tiles[number] = tile
        result = plan.result()
        if best is None or result.worst < best.worst:
            best = result
        failed = [n for n, t in plan.tiles.items() if not t.passed]
        # plan again the strip along each failed tile's worst border (and the tiles along
        # it); a strip planned too often: the whole set, from new corner patches
        offending = sorted({plan.worst_strip(n) for n in failed})
        anew = any(strip_plans.get(k, 1) >= STRIP_ATTEMPTS for k in offending)
        report.round(round_, failed, anew=anew)
        if not failed:
            return result
        if round_ + 1 == params.attempts:
            break
        if anew:
            plan.plan_all(pool)
            strip_plans = {}
            continue
        plan.plan_strips(offending, pool, STRIP_CANDIDATES)
        for key in offending:
            strip_plans[key] = strip_plans.get(key, 1) + 1
    worst = max(best.checks, key=lambda c: c.figures.worst)
    raise SeamError(worst, params.max_seam)


PROGRESS_SECONDS = 10.0  # the most time between two progress lines within a round


class _Progress:
    """Progress lines of :func:`plan_tiles` (none without a callback)."""

    def __init__(self, plan: _TileSetPlanner, callback: Callable[[str], None] | None):
        self.plan, self.callback = plan, callback
        self.last = time.monotonic()
        qp = plan.params
        self.what = (f"block {qp.block}, {len(plan.types)} tile(s) of {qp.tile[0]} x "
                     f"{qp.tile[1]}")

    def _say(self, line: str) -> None:
        self.callback(f"{self.what}: {line} ({sum(self.plan.plans)} interior plan(s) so far)")
        self.last = time.monotonic()

    def tile(self, round_: int) -> None:
        """A tile planned: a line if the round has run long without one."""
        if self.callback is not None and time.monotonic() - self.last >= PROGRESS_SECONDS:
            self._say(f"round {round_ + 1}: {len(self.plan.tiles)} of "
                      f"{len(self.plan.types)} tile(s) planned")

    def round(self, round_: int, failed: list[int], shared: int = 0, anew: bool = False
              ) -> None:
        """A round ended with ``failed`` tiles beyond the bound.

        ``shared``: strips that two or more of them failed at, planned again after one plan
        of each tile; ``anew``: the whole set is planned again instead (a strip at fault
        was planned :data:`STRIP_ATTEMPTS` times).
        """
        if self.callback is None:
            return
        n = len(self.plan.types)
        if not failed:
            if round_ > 0:  # a first round that passes needs no line
                self._say(f"round {round_ + 1}: every tile within the bound")
        else:
            last = round_ + 1 == self.plan.params.attempts
            worst = max((self.plan.tiles[k].check for k in failed),
                        key=lambda c: c.figures.worst)
            if last:
                then = ""
            elif anew:
                then = (f"; a strip at fault planned {STRIP_ATTEMPTS} times: the whole set "
                        "planned again from new corner patches")
            elif shared:
                then = f"; {shared} strip(s) along which two or more tiles fail planned again"
            else:
                then = "; planning the worst borders' strips again"
            self._say(f"round {round_ + 1} of at most {self.plan.params.attempts}: "
                      f"{n - len(failed)} of {n} tile(s) within the bound (worst: "
                      f"{worst.tile}, {worst.figures.worst_line()}){then}")


def plan_first(reference: np.ndarray, params: Iterable[QuiltParams], *, seed: int,
               on_failure=None, progress: Callable[[str], None] | None = None,
               threads: int = 1) -> tuple[TileSet, QuiltParams]:
    """The first of ``params`` (e.g. :func:`tasks.quilt_layout.layouts`) whose plan passes.

    ``on_failure(error)`` is called with the :class:`SeamError` of each one that does not;
    when none passes, the last error is raised. ``progress`` and ``threads`` as for
    :func:`plan_tiles`. The border check's patches are made once per structure patch size.
    """
    failure = None
    exemplars: dict[int, PatchExemplar] = {}
    for qp in params:
        patch = BorderCheck.patch(qp)
        if patch not in exemplars:
            exemplars[patch] = PatchExemplar(np.asarray(reference, np.float32), patch=patch)
        try:
            return plan_tiles(reference, qp, seed=seed, exemplar=exemplars[patch],
                              progress=progress, threads=threads), qp
        except SeamError as exc:
            failure = exc
            if on_failure is not None:
                on_failure(exc)
    if failure is None:
        raise ValueError("no layout to plan with")
    raise failure
