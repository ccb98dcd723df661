"""Seams of quilted textures, seed by seed: what a user who quilts one seed gets.

A texture (scikit-image's ``brick``, ``gravel``, ``grass`` and ``moon`` photos, their top-left
256 x 256 texels; a random lattice of :mod:`benchmarks.lattices`; generated materials by name)
becomes a three-layer reference image through three tone curves (``g``, ``sqrt g``, ``g^2``),
as a user quilting a photo would, and is quilted as ``btf quilt`` does (the automatic block or
a given one, the sample's lattice, the border check; :func:`tasks.corner_tiles.plan_first`).
For every seed:

- **V = 1**: the periodic texture as the torus it is;
- **V = 2**: a 4 x 4 mosaic of corner-compatible tiles laid by random corner types, itself
  periodic, every tile measured framed by what its neighbours put within half a block of it;

each border line's seam and structure ratios (:mod:`tasks.seams`, with the reach of the
planner's check, half a patch step), the worst line of the texture or of any tile; and the
sharpness, the texture's mean neighbour difference over the photo's (1 = as sharp). A seed
whose plan fails the check (:class:`tasks.corner_tiles.SeamError`) is counted as failed.
Per texture and setting the table gives the worst seed's figure, the median and which seed
was worst: a pooled mean would say nothing about the texture a user gets.

:func:`search_accuracy` compares the border check's nearest-patch search with an exact
brute-force one on checks recorded while planning (``btf bench quilt --search-checks N``).
"""

from __future__ import annotations

import time

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

PHOTOS = ("brick", "gravel", "grass", "moon")
SEEDS = 20


def photo(name: str) -> np.ndarray:
    """A scikit-image photo as luminance in [0, 1] (float32), whole."""
    from skimage import data

    g = getattr(data, name)().astype(np.float32) / 255.0
    if g.ndim == 3:
        g = g[..., :3] @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    return g


def reference_of(name: str, size: int = 256) -> np.ndarray:
    """The three-tone-curve reference image of a texture (see the module), ``size^2``."""
    if name in PHOTOS:
        g = photo(name)
    elif name == "lattice":  # an oblique lattice of blobs with noise: nothing tuned on it
        from benchmarks.lattices import random_lattice_texture

        rng = np.random.default_rng(11)
        case = random_lattice_texture(rng, motif="blobs", noise=0.1, gradient=0.0, low=20,
                                      high=36)
        while min(case.image.shape) < size:  # the first oblique lattice drawn that is large
            case = random_lattice_texture(rng, motif="blobs", noise=0.1, gradient=0.0,
                                          low=20, high=36)
        g = case.image.astype(np.float32)
        g = (g - g.min()) / max(float(np.ptp(g)), 1e-6)
    else:
        from tasks.materials import Material

        albedo = Material(name, seed=1).fields(0, 0, size, size).albedo
        g = (albedo @ np.array([0.2126, 0.7152, 0.0722])).astype(np.float32)
        g = (g - g.min()) / max(float(np.ptp(g)), 1e-6)
    if min(g.shape) < size:
        raise ValueError(f"{name} is smaller than {size} x {size}")
    g = g[:size, :size]
    return np.stack([g, np.sqrt(g), g * g], axis=-1)


def neighbour_difference(img: np.ndarray) -> float:
    """Mean absolute difference of horizontal and vertical neighbour pairs."""
    dx = np.abs(np.diff(img, axis=1)).mean(axis=-1)
    dy = np.abs(np.diff(img, axis=0)).mean(axis=-1)
    return float((dx.sum() + dy.sum()) / (dx.size + dy.size))


def mosaic(plan, count: int, rng: np.random.Generator) -> np.ndarray:
    """A periodic ``count x count`` mosaic of corner-compatible tiles (random corner types)."""
    types = int(plan.corners.max()) + 1
    lookup = {tuple(c): k for k, c in enumerate(plan.corners.tolist())}
    grid = rng.integers(types, size=(count, count))
    grid = np.pad(grid, ((0, 1), (0, 1)), mode="wrap")  # the mosaic wraps: every tile framed
    rows = [np.concatenate([plan.tiles[lookup[(grid[i, j], grid[i, j + 1], grid[i + 1, j],
                                                grid[i + 1, j + 1])]].value
                            for j in range(count)], axis=1) for i in range(count)]
    return np.concatenate(rows, axis=0)


def mosaic_figures(exemplar, image: np.ndarray, tile: tuple[int, int], margin: int,
                   reach: float):
    """Figures of every tile of a periodic mosaic, framed by ``margin`` texels of neighbours."""
    from tasks.seams import Borders, border_figures

    th, tw = tile
    wrapped = np.pad(image, ((margin, margin), (margin, margin), (0, 0)), mode="wrap")
    borders = Borders.framed(tile, margin)
    out = []
    for y in range(0, image.shape[0], th):
        for x in range(0, image.shape[1], tw):
            frame = wrapped[y : y + th + 2 * margin, x : x + tw + 2 * margin]
            out.append(((y // th, x // tw), border_figures(exemplar, frame, borders,
                                                           reach=reach)))
    return out


def seed_figures(name: str, reference: np.ndarray, lattice, *, block: int | None,
                 overlap: int | None, corners: int, seed: int, candidates: int = 5,
                 threads: int = 1, default_tiles: bool = False, max_seam: float = 1.3) -> dict:
    """One seed of one texture and setting quilted and measured (see the module).

    ``default_tiles``: tiles of ``btf quilt``'s default size (the sample's, rounded down to
    whole steps) instead of three steps; ``max_seam``: the border check's bound.
    """
    from tasks.corner_tiles import BorderCheck, SeamError, plan_first
    from tasks.quilt_layout import commensurate_sizes, layouts, phase_lattice
    from tasks.quilting import QuiltParams
    from tasks.seams import Borders, border_figures

    phase = phase_lattice(lattice, reference.shape[:2])

    def params():
        for layout in layouts(reference, block=block, overlap=overlap, tile=None,
                              lattice=lattice):
            tile = layout.tile
            if corners > 1 and not default_tiles:  # small tiles: three steps, or periods
                side = 3 * layout.step
                if lattice is not None:
                    sizes = [commensurate_sizes(side, layout.step, a, lattice, count=1)
                             for a in (0, 1)]
                    tile = tuple(s[0] if s else side for s in sizes)
                else:
                    tile = (side, side)
            yield QuiltParams(layout.block, layout.overlap, candidates, corners, tile,
                              lattice=phase, max_seam=max_seam)

    start = time.perf_counter()
    try:
        plan, qp = plan_first(reference, params(), seed=seed, threads=threads)
    except SeamError as exc:
        return {"seed": seed, "failed": str(exc), "seconds": time.perf_counter() - start}
    seconds = time.perf_counter() - start
    exemplar = BorderCheck(reference, qp).exemplar
    reach = qp.step / 2
    if corners == 1:
        image = plan.tiles[0].value
        figures = [((0, 0), border_figures(exemplar, image, Borders.periodic(), reach=reach))]
    else:
        image = mosaic(plan, 4, np.random.default_rng(seed))
        figures = mosaic_figures(exemplar, image, qp.tile, qp.block // 2, reach)
    where, worst = max(figures, key=lambda f: f[1].worst)
    return {"seed": seed, "failed": None, "block": qp.block, "overlap": qp.overlap,
            "tile": list(qp.tile), "seconds": seconds,
            "seam": max(f.worst_seam for _, f in figures),
            "structure": max(f.worst_structure for _, f in figures),
            "worst": f"tile {where}: {worst.worst_line()}" if corners > 1 else worst.worst_line(),
            "plans": max(c.plans for c in plan.checks),
            "interior_plans": sum(c.plans for c in plan.checks),
            "sharpness": neighbour_difference(image) / neighbour_difference(reference)}


def texture_seams(name: str, *, block: int | None, seeds, corners: int = 1,
                  candidates: int = 5, threads: int = 1, log=None) -> dict:
    """Every seed of one texture and setting (see the module), and the summary."""
    from tasks.quilt_layout import sample_lattice

    reference = reference_of(name)
    lattice = sample_lattice(reference)
    overlap = None if block is None else block // 4
    rows = []
    for seed in seeds:
        rows.append(seed_figures(name, reference, lattice, block=block, overlap=overlap,
                                 corners=corners, seed=seed, candidates=candidates,
                                 threads=threads))
        if log is not None:
            r = rows[-1]
            log(f"seams {name} block {block or 'auto'} V {corners} seed {seed}: "
                + (f"FAILED {r['failed']}" if r["failed"] else
                   f"seam {r['seam']:.2f} structure {r['structure']:.2f} ({r['worst']}), "
                   f"{r['seconds']:.1f} s"))
    ok = [r for r in rows if not r["failed"]]
    return {"texture": name, "given_block": block, "corners": corners, "seeds": rows,
            "blocks": sorted({(r["block"], r["overlap"], tuple(r["tile"])) for r in ok}),
            **summary(rows)}


LOWER_IS_WORSE = ("sharpness",)


def summary(rows: list[dict], keys=("seam", "structure", "sharpness", "seconds")) -> dict:
    """Worst, median and worst seed of each figure over the seeds that did not fail."""
    ok = [r for r in rows if not r["failed"]]
    out = {"failed": [(r["seed"], r["failed"]) for r in rows if r["failed"]]}
    for key in keys:
        if not ok:
            out[key] = None
            continue
        values = [r[key] for r in ok]
        worst = min if key in LOWER_IS_WORSE else max
        pick = worst(range(len(ok)), key=lambda i: values[i])
        out[key] = {"worst": values[pick], "median": float(np.median(values)),
                    "worst_seed": ok[pick]["seed"]}
    return out


def seams_report(rows: list[dict]) -> list[str]:
    """Markdown table of :func:`texture_seams` results."""
    lines = ["| texture | block | V | seeds | failed | seam: worst (seed) / median | "
             "structure: worst (seed) / median | sharpness: lowest / median | "
             "plan s: worst / median |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        blocks = ", ".join(f"{b}/{o} ({t[0]}x{t[1]})" for b, o, t in r["blocks"])
        given = "given" if r["given_block"] else "auto"

        def cell(key, r=r):
            s = r[key]
            return "-" if s is None else (f"{s['worst']:.2f} ({s['worst_seed']}) / "
                                          f"{s['median']:.2f}")

        sharp = r["sharpness"]
        lines.append(
            f"| {r['texture']} | {blocks} {given} | {r['corners']} | {len(r['seeds'])} | "
            f"{len(r['failed'])} | {cell('seam')} | {cell('structure')} | "
            + ("-" if sharp is None else f"{sharp['worst']:.2f} / {sharp['median']:.2f}")
            + " | " + ("-" if r["seconds"] is None else
                       f"{r['seconds']['worst']:.1f} / {r['seconds']['median']:.1f}") + " |")
    return lines


ROLLER_REGION = 384  # texels per side of the rendered roller surface


def roller_seed(seed: int, *, tiles: int = 3) -> dict:
    """A random lattice (benchmarks.lattices, drawn from ``seed``) rolled and measured.

    The texture's own lattice is detected and ``tiles`` double toroidal tiles planned on it as
    ``btf roller`` does (:func:`tasks.roller.plan_roller`: other tile sizes while the borders
    stand out); the figures are those of its border check (:func:`tasks.roller.border_check`:
    tile 0 laid over about two tiles per side, the borders of its lattice cells against the
    sample's own period-to-period variation), and the sharpness is that of a
    ``ROLLER_REGION^2`` surface of all tiles laid with the seed. A sample that is not
    periodic, or that no tile size tried closes, counts as failed, with the message.
    """
    from benchmarks.lattices import random_lattice_texture
    from tasks.periodicity import detect_lattice
    from tasks.placement import lattice_gather
    from tasks.reference import luminance
    from tasks.roller import RollerParams, plan_roller

    case = random_lattice_texture(np.random.default_rng(seed))
    g = case.image.astype(np.float32)
    g = (g - g.min()) / max(float(np.ptp(g)), 1e-6)
    image = np.stack([g, np.sqrt(g), g * g], axis=-1)
    lattice = detect_lattice(luminance(image.astype(np.float64)))
    row = {"seed": seed, "case": case.describe(), "confidence": lattice.confidence}
    if lattice.confidence < 0.5:
        return {**row, "failed": "not periodic (confidence below 0.5)"}
    start = time.perf_counter()
    try:
        plan = plan_roller(image, lattice.u, lattice.v, RollerParams(tiles=tiles))
    except ValueError as exc:  # RollerSeamError too: the bound not met
        return {**row, "failed": str(exc)}
    seconds = time.perf_counter() - start
    flat = image.reshape(-1, 3)
    stored = np.einsum("tnk,tnkc->tnc", plan.weight, flat[np.maximum(plan.index, 0)])
    stored = stored.reshape(tiles, *plan.tile_shape, 3)
    n = ROLLER_REGION
    surface = lattice_gather(stored, 0, 0, n, n, hnf=plan.hnf, basis=(plan.U, plan.V),
                             representative=plan.representative, seed=seed)
    return {**row, "failed": None, "seam": plan.check[0], "structure": plan.check[1],
            "seconds": seconds, "periods": list(plan.periods),
            "sharpness": neighbour_difference(surface) / neighbour_difference(image)}


def roller_seams(seeds, *, tiles: int = 3, log=None) -> dict:
    """:func:`roller_seed` for every seed, and the summary (seeds whose lattice is not found
    count as failed, with the reason)."""
    rows = []
    for seed in seeds:
        rows.append(roller_seed(seed, tiles=tiles))
        if log is not None:
            r = rows[-1]
            log(f"roller seed {seed} ({r['case']}): " + (
                f"FAILED {r['failed']}" if r["failed"] else
                f"seam {r['seam']:.2f} structure {r['structure']:.2f}"))
    worst = summary(rows, keys=("seam", "structure", "sharpness"))
    for key in ("seam", "structure", "sharpness"):
        if worst[key] is not None:
            worst[key]["worst_case"] = next(r["case"] for r in rows
                                            if r["seed"] == worst[key]["worst_seed"])
    return {"tiles": tiles, "seeds": rows, **worst}


# the border check's nearest-patch searches compared by search_accuracy: (eps, candidates)
SEARCHES = {"exact k-d tree, 8 re-ranked": (0.0, 8), "eps 1, 8 re-ranked": (1.0, 8),
            "eps 1, 16 re-ranked": (1.0, 16), "eps 2, 8 re-ranked": (2.0, 8),
            "eps 2, 12 re-ranked": (2.0, 12)}


def _recorded_checks(name: str, reference: np.ndarray, seeds, count: int) -> list:
    """Every other border check made while planning V = 2 tile sets, up to ``count``.

    Each as the framed tile, its borders, its reach and its structure patch.
    """
    from tasks import corner_tiles
    from tasks.quilt_layout import sample_lattice

    recorded, calls = [], [0]
    figures = corner_tiles.BorderCheck.figures

    def recording(check, tile, top, bottom, left, right):
        calls[0] += 1
        if calls[0] % 2 == 0 and len(recorded) < count and not check.periodic:
            recorded.append((check.frame(tile, top, bottom, left, right),
                             corner_tiles.Borders.framed(tile.shape, check.half), check.reach,
                             check.exemplar.patch))
        return figures(check, tile, top, bottom, left, right)

    corner_tiles.BorderCheck.figures = recording
    try:
        lattice = sample_lattice(reference)
        for seed in seeds:
            if len(recorded) >= count:
                break
            seed_figures(name, reference, lattice, block=None, overlap=None, corners=2,
                         seed=seed)
    finally:
        corner_tiles.BorderCheck.figures = figures
    return recorded


def search_accuracy(name: str, *, checks: int = 16, seeds=range(20)) -> dict:
    """The border check's nearest-patch search against an exact brute-force one.

    ``checks`` border checks recorded while planning V = 2 tile sets of the texture (the first
    seeds) are measured again with each setting of :data:`SEARCHES` (k-d tree approximation,
    candidates re-ranked) and with the exact nearest patch at full dimension: per setting the
    time of the checks' searches, how far each patch's distance lies above the exact one (mean
    and 99th percentile of ``d / d_exact - 1``), and how far each check's worst structure ratio
    lies from the exact search's (mean and largest).
    """
    from tasks.seams import PatchExemplar, structure_ratios

    class Exact(PatchExemplar):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.known = {}  # each check's map is asked for twice
            # every sample patch rows first, as the search's queries are (made once)
            p, c = self.patch, self.sample.shape[-1]
            rows_first = sliding_window_view(self.sample, (p, p, c))[:, :, 0]
            self.flat = rows_first.reshape(-1, p * p * c).astype(np.float64)
            self.norms = np.einsum("ij,ij->i", self.flat, self.flat)

        def distances(self, queries):
            key = hash(np.ascontiguousarray(queries).tobytes())
            if key not in self.known:
                self.known[key] = self._distances(queries)
            return self.known[key]

        def _distances(self, queries):  # (n, p, p, channels) patches, as the search's
            queries = np.asarray(queries).reshape(len(queries), -1)
            out = np.empty(len(queries))
            for i in range(0, len(queries), 256):
                q = np.asarray(queries[i : i + 256], np.float64)
                d = self.norms - 2 * q @ self.flat.T + np.einsum("ij,ij->i", q, q)[:, None]
                out[i : i + 256] = np.maximum(d.min(axis=1), 0.0)
            return np.sqrt(out / queries.shape[1])

    reference = reference_of(name)
    recorded = _recorded_checks(name, reference, seeds, checks)
    exemplars: dict = {}

    def exemplar(kind, patch):
        if (kind, patch) not in exemplars:
            if kind == "exact":
                exemplars[kind, patch] = Exact(reference, patch=patch)
            else:
                eps, candidates = SEARCHES[kind]
                exemplars[kind, patch] = PatchExemplar(reference, patch=patch, eps=eps,
                                                       candidates=candidates)
        return exemplars[kind, patch]

    def measured(kind):
        maps, worst, seconds = [], [], 0.0
        for image, borders, reach, patch in recorded:
            ex = exemplar(kind, patch)
            ex.own_repeat  # noqa: B018 (computed once, outside the timing)
            start = time.perf_counter()
            maps.append(ex.distance_map(image, wrap=False,
                                        within=borders.within(image.shape[:2]))[0].ravel())
            seconds += time.perf_counter() - start
            worst.append(max(structure_ratios(ex, image, borders, reach=reach)))
        return np.concatenate(maps), np.array(worst), seconds

    exact, exact_worst, _ = measured("exact")
    rows = []
    for kind in SEARCHES:
        d, worst, seconds = measured(kind)
        excess = d / np.maximum(exact, 1e-9) - 1
        moved = np.abs(worst - exact_worst)
        rows.append({"texture": name, "search": kind, "checks": len(recorded),
                     "ms_per_check": 1e3 * seconds / max(len(recorded), 1),
                     "excess_mean": float(excess.mean()),
                     "excess_p99": float(np.percentile(excess, 99)),
                     "worst_error_mean": float(moved.mean()),
                     "worst_error_max": float(moved.max())})
    return {"texture": name, "rows": rows}


def search_report(results: list[dict]) -> list[str]:
    """Markdown table of :func:`search_accuracy` results."""
    lines = ["| texture | search | checks | search ms a check | patch distance over the exact: "
             "mean / p99 | check's worst ratio off the exact: mean / max |",
             "|---|---|---|---|---|---|"]
    for result in results:
        for r in result["rows"]:
            lines.append(f"| {r['texture']} | {r['search']} | {r['checks']} | "
                         f"{r['ms_per_check']:.0f} | +{100 * r['excess_mean']:.1f}% / "
                         f"+{100 * r['excess_p99']:.0f}% | {r['worst_error_mean']:.3f} / "
                         f"{r['worst_error_max']:.3f} |")
    return lines
