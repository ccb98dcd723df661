"""Enlargement as dask graphs: constraint photos read by region, levels synthesized in tiles.

A target too large for one in-memory image is synthesized level by level (paper 000, coarse to
fine). A level that fits in one tile is one task; a larger one is cut into tiles of ``tile``
texels, each optimised on itself plus a halo of :data:`HALO` neighbourhoods from the same
starting point (the coarser level upsampled, or at the coarsest a search on the guide alone:
the same values wherever two tiles overlap) and the same guide, keeping only its interior.
Neighbouring tiles therefore start alike and see the same photos across their common border;
what differs is how far the EM iterations carry each from that start, which the halo keeps
away from the interior. At the finest level the statistics and QP rounds follow in each tile;
histogram matching is not local, so two tiles map their common texels a little differently:
there the grown tiles are blended with linear ramps across their overlap
(:func:`blend_task`; measured: a 1.5x rougher tile border without, none with). The finest
level's tiles also run the statistics and QP rounds. Results go to scratch arrays of the
output store (one chunk per tile: no two tasks write the same file), then the coefficients are
re-factorised from their Gram matrix (a sum over tiles) and written as ``V`` tile by tile.

Every task computes from its region of the inputs, the shared sample side and the seed alone,
so the store is the same on every scheduler; memory is bounded by a tile and its halo.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np

from pipeline import storage
from pipeline.errors import BTFError
from pipeline.stores.base import RADIANCE
from pipeline.stores.radiance import as_float32
from tasks.photo_regression import ValueRange
from tasks.svd import BlockCheck, check_block
from tasks.texture_optimization import (
    coarse_rows,
    downsample,
    initial,
    optimize,
    upsample_region,
)
from tasks.transform import Transform

WHOLE_TEXELS = 1 << 20  # targets up to 1024^2 texels are synthesized whole by default
HALO = 4  # neighbourhoods of halo around a tile


@dataclass(frozen=True)
class Guide:
    """Where the constraint values come from: layers of the photos store, encoded.

    Values are in the sample's domain (its transform's :meth:`~tasks.transform.Transform.encode`).
    """

    store: str  # absolute path of the constraints store
    layers: tuple[tuple[int, int], ...]  # (view, light) of every constraint layer
    offsets: tuple[float, ...]  # subtracted per value (a mean colour's Jensen offset)
    transform: Transform
    shape: tuple[int, int]  # full-resolution size of the photos
    # per layer, what multiplies the photo's radiance before it is encoded: cos(theta_light)
    # for a cosine sample, whose values are radiance x cos (None: 1)
    scales: tuple[float, ...] | None = None

    def region(self, factor: int, y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
        """Constraint values of level texels ``[y0, y1) x [x0, x1)`` at ``1 / factor`` scale.

        Block means of the full-resolution values (a last partial block averages what it
        has), so a region computes what downsampling the whole image gives there.
        """
        import zarr

        array = zarr.open_array(storage.store(self.store), path=RADIANCE, mode="r")
        h, w = self.shape
        cols = slice(x0 * factor, min(x1 * factor, w))
        # level rows a strip at a time: a few dozen MiB of full-resolution values at most
        per_row = factor * (cols.stop - cols.start) * len(self.offsets) * 16
        step = max(1, (64 << 20) // max(per_row, 1))
        out = []
        for a in range(y0, y1, step):
            rows = slice(a * factor, min(min(a + step, y1) * factor, h))
            values = np.concatenate([self.transform.encode(
                as_float32(array[v, li, rows, cols]) * np.float32(1.0 if self.scales is None
                                                      else self.scales[k]))
                for k, (v, li) in enumerate(self.layers)], axis=-1)
            values -= np.asarray(self.offsets, np.float32)
            out.append(downsample(values, factor))
        return np.concatenate(out, axis=0)


def check_photos(guide: Guide, block: int = 1024) -> list:
    """Delayed checks of every constraint layer, a block of texels at a time."""
    import dask

    h, w = guide.shape
    return [dask.delayed(_check_block, pure=True)(guide.store, k, v, li, y, x, block)
            for k, (v, li) in enumerate(guide.layers)
            for y in range(0, h, block) for x in range(0, w, block)]


def _check_block(store: str, k: int, v: int, li: int, y: int, x: int, block: int):
    import zarr

    layer = zarr.open_array(storage.store(store), path=RADIANCE, mode="r")[v, li, y : y + block,
                                                            x : x + block]
    return k, check_block(layer, (y, x, 0))


def raise_on_bad_photos(checks: list, path: str, guide: Guide) -> None:
    """One error for the first layer with NaN/Inf or negative values (layer, count, place)."""
    by_layer: dict[int, BlockCheck] = {}
    for k, found in checks:
        by_layer[k] = by_layer.get(k, BlockCheck()).merge(found)
    for k in sorted(by_layer):
        found, (v, li) = by_layer[k], guide.layers[k]
        if found.nonfinite:
            y, x, c = found.first_nonfinite
            raise BTFError(f"{path}: variable 'radiance' has {found.nonfinite} NaN or Inf "
                           f"value(s) in layer {k} (view {v}, light {li}), the first at y={y}, "
                           f"x={x}, channel={c}")
        if found.negative:
            y, x, c = found.first_negative
            raise BTFError(f"{path}: variable 'radiance' has negative values in layer {k} "
                           f"(view {v}, light {li}), the first at y={y}, x={x}, channel={c}; "
                           "log(radiance + eps) needs radiance >= 0")


def tiles(shape: tuple[int, int], tile: int) -> list[tuple[int, int, int, int]]:
    """``(y0, y1, x0, x1)`` of the tiles covering ``shape``, in C order."""
    from dask.array.core import normalize_chunks, slices_from_chunks

    return [(ys.start, ys.stop, xs.start, xs.stop) for ys, xs in
            slices_from_chunks(normalize_chunks((tile, tile), shape))]


def _grown(region, halo: int, shape) -> tuple[int, int, int, int]:
    y0, y1, x0, x1 = region
    return max(0, y0 - halo), min(shape[0], y1 + halo), max(0, x0 - halo), min(shape[1],
                                                                               x1 + halo)


def _start(out: str, coarse: str | None, coarse_shape, shape, grown) -> np.ndarray:
    """The coarser level upsampled over ``grown`` (read from the scratch array)."""
    import zarr

    y0, y1, x0, x1 = grown
    cy, cx = (coarse_rows(y0, y1, coarse_shape[0], shape[0]),
              coarse_rows(x0, x1, coarse_shape[1], shape[1]))
    block = zarr.open_array(storage.store(out), path=coarse, mode="r")[cy[0] : cy[1], cx[0] : cx[1]]
    return upsample_region(block, (cy[0], cx[0]), coarse_shape, shape, (y0, x0),
                           (y1 - y0, x1 - x0))


def level_task(out: str, name: str, region, *, shape, factor: int, coarse: str | None,
               coarse_shape, source, guide: Guide, params, halo: int, finish=None,
               slot: int | None = None):
    """Optimise one tile of a level (with its halo) and write its interior to ``name``.

    ``finish`` (the finest level): ``(projector, noise, enlargement params, statistics,
    bounds)``: the tile then also runs the rounds of statistics and QP, and the photos'
    regression within ``bounds`` with its QP (:func:`tasks.enlargement.regressed`), and the
    move toward the photos' mean with its QP (:func:`tasks.enlargement.shrunk`). With
    ``slot``, the whole grown tile goes to slot ``slot`` of ``name`` instead, for
    :func:`blend_task`. Returns the EM energies and, with ``finish``, the rounds' changes and
    damping and the tile's squared residual.
    """
    import zarr

    from tasks.enlargement import refine, regressed, shrunk

    grown = _grown(region, halo, shape)
    target = guide.region(factor, *grown)
    if coarse is None:  # the coarsest level starts from a search on the guide alone
        x = initial(source, target, (grown[1] - grown[0], grown[3] - grown[2]), params, None)
    else:
        x = _start(out, coarse, coarse_shape, shape, grown)
    x, energies = optimize(source, x, target, params, final=finish is not None)
    report = {"energy": energies}
    if finish is not None:
        projector, noise, enlargement, statistics, bounds = finish
        rounds = refine(x, target, projector, noise=noise, params=enlargement,
                        statistics=statistics)
        x = regressed(rounds.coefficients, source.coefficients, source.guide, target,
                      projector, noise=noise, params=enlargement, bounds=bounds)
        x = shrunk(x, source.coefficients, source.guide, target, projector, noise=noise,
                   params=enlargement)
        report.update(changes=rounds.changes, damping=rounds.damping)
    y0, y1, x0, x1 = region
    inner = x[y0 - grown[0] : y1 - grown[0], x0 - grown[2] : x1 - grown[2]]
    if finish is not None:
        d = inner.astype(np.float64) @ projector.a.T - target[
            y0 - grown[0] : y1 - grown[0], x0 - grown[2] : x1 - grown[2]]
        report.update(residual2=float(np.sum(d**2)), values=int(d.size))
    if slot is None:
        zarr.open_array(storage.store(out), path=name, mode="r+")[y0:y1, x0:x1] = inner
    else:
        target = zarr.open_array(storage.store(out), path=name, mode="r+")
        target[slot, : x.shape[0], : x.shape[1]] = x
    return report


def _ramp(start: int, stop: int, lo: int, hi: int, extent: int, width: int) -> np.ndarray:
    """Weights of a grown tile ``[lo, hi)`` along ``[start, stop)``.

    They rise over ``width`` texels from the tile's edges, except at the image's own edges
    (0 and ``extent``), where there is no neighbour to share with.
    """
    t = np.arange(start, stop) + 0.5
    w = np.ones(stop - start)
    if lo > 0:
        w = np.minimum(w, (t - lo) / width)
    if hi < extent:
        w = np.minimum(w, (hi - t) / width)
    return np.clip(w, 0.0, 1.0)


def blend_task(out: str, grown_name: str, name: str, region, boxes, *, shape,
               halo: int) -> None:
    """Write a tile's interior as the blend of every grown tile that covers it.

    ``boxes`` are the grown regions ``(y0, y1, x0, x1)`` of all tiles, by slot. Linear ramps
    over the ``2 halo`` texels where two grown tiles overlap sum to one, so the texels pass
    from one tile's result to its neighbour's without a step.
    """
    import zarr

    grown = zarr.open_array(storage.store(out), path=grown_name, mode="r")
    y0, y1, x0, x1 = region
    total = np.zeros((y1 - y0, x1 - x0, grown.shape[-1]), np.float64)
    norm = np.zeros((y1 - y0, x1 - x0, 1), np.float64)
    for slot, (gy0, gy1, gx0, gx1) in enumerate(boxes):
        a, b, c, d = max(y0, gy0), min(y1, gy1), max(x0, gx0), min(x1, gx1)
        if a >= b or c >= d:
            continue
        weight = np.outer(_ramp(a, b, gy0, gy1, shape[0], 2 * halo),
                          _ramp(c, d, gx0, gx1, shape[1], 2 * halo))[..., None]
        part = grown[slot, a - gy0 : b - gy0, c - gx0 : d - gx0]
        total[a - y0 : b - y0, c - x0 : d - x0] += weight * part
        norm[a - y0 : b - y0, c - x0 : d - x0] += weight
    zarr.open_array(storage.store(out), path=name, mode="r+")[y0:y1, x0:x1] = (total / norm).astype(
        np.float32)


def grown_boxes(regions, halo: int, shape) -> list[tuple[int, int, int, int]]:
    """The grown region of every tile (its interior plus the halo, inside the image)."""
    return [_grown(r, halo, shape) for r in regions]


def gram_task(out: str, name: str, region) -> np.ndarray:
    """``C^T C`` (float64) of a tile of coefficients."""
    import zarr

    y0, y1, x0, x1 = region
    c = zarr.open_array(storage.store(out), path=name, mode="r")[y0:y1, x0:x1]
    c = np.asarray(c, np.float64).reshape(-1, c.shape[-1])
    return c.T @ c


def factor_task(out: str, name: str, region, w: np.ndarray, s: np.ndarray) -> None:
    """Write ``V = C W / s`` of a tile (components with ``s = 0`` get 0)."""
    import zarr

    y0, y1, x0, x1 = region
    c = zarr.open_array(storage.store(out), path=name, mode="r")[y0:y1, x0:x1]
    c = np.asarray(c, np.float64)
    kept = s > (s[0] * 1e-12 if s.size else 0.0)
    v = c @ w
    v[..., kept] /= s[kept]
    v[..., ~kept] = 0.0
    zarr.open_array(storage.store(out), path="V", mode="r+")[y0:y1, x0:x1] = v.astype(np.float32)


def synthesize(out, path, guide: Guide, rows: np.ndarray, sample: np.ndarray,
               sample_values: np.ndarray, *, params, guide_weight: float, seed: int, tile: int,
               session, basis: np.ndarray | None = None) -> dict:
    """Synthesize the target level by level into the scratch array ``_coefficients``.

    ``out`` is the output group (at ``path``), ``sample`` the sample's coefficients and
    ``sample_values`` its constraint values, ``params`` the
    :class:`tasks.enlargement.EnlargementParams`, ``basis`` the rows of ``U_S`` that bound the
    regression's move (as :func:`tasks.enlargement.enlarge`'s). Computes on ``session``, one
    level at a time; returns the report for the store's attrs. Every tile task is a unit of
    :class:`pipeline.resume.Progress`: a rerun after a kill runs only the tiles not finished
    (the client's random state is replayed level by level, so the result is the same).
    """
    import time

    from pipeline.resume import Progress
    from pipeline.stores.base import location
    from tasks.enlargement import qp_projector
    from tasks.texture_optimization import SampleLevel, leading_components

    to = params.texture
    rng = np.random.default_rng(seed)
    rotation = leading_components(sample, to.search_energy)
    projector = qp_projector(rows, sample, params)
    noise = 0.0 if params.exact else projector.rms_residual(sample, sample_values)
    big_h, big_w = guide.shape
    halo = HALO * to.patch
    statistics = _tile_statistics(sample, guide.shape, tile, halo, params)
    bounds = None if basis is None or not params.regress else ValueRange.of(sample, basis)
    report = {"tile": tile, "halo": halo, "levels": [], "seconds": {}}
    coarse, coarse_shape, here = None, None, location(path)
    progress = Progress(path)
    for level in range(to.levels - 1, -1, -1):
        start = time.perf_counter()
        factor = 2**level
        shape = (-(-big_h // factor), -(-big_w // factor))
        whole, regions = _level_regions(shape, tile)
        # a level whose tiles a killed run all finished needs no coherence table (7 s for a
        # 256^2 sample's finest level on one core); the rest of its source is made again,
        # as it draws from the client's random state
        kept = len(progress.finished(_tile_names(level, regions))) == len(regions)
        source = SampleLevel(downsample(sample, factor), downsample(sample_values, factor),
                             rotation, guide_weight, to, rng,
                             table=_no_table if kept else partial(_coherence_table,
                                                                  session=session))
        name = "_coefficients" if level == 0 else f"_level{level}"
        blend = level == 0 and not whole  # the finest level's tiles are blended
        _level_arrays(out, name, shape, sample.shape[-1], tile, len(regions) if blend else 0,
                      halo)
        tasks = _level_tasks(
            here, name, regions, level=level, blend=blend, shape=shape, factor=factor,
            coarse=coarse, coarse_shape=coarse_shape, source=session.share(source),
            guide=guide, params=to, halo=0 if whole else halo,
            finish=None if level else session.share((projector, noise, params, statistics,
                                                     bounds)))
        reports = _run_level(tasks, progress, session, factor=factor, shape=shape)
        if blend:
            _blend_level(out, here, name, regions, progress, session, shape=shape, halo=halo)
        report["levels"].append({"factor": factor, "tasks": len(tasks),
                                 "energy": [r["energy"] for r in reports]})
        report["seconds"][f"level_1/{factor}"] = time.perf_counter() - start
        if coarse is not None and coarse in out:
            del out[coarse]
        coarse, coarse_shape = name, shape
    return {**report, **_finest_report(reports), "sample_constraint_residual_rms": noise,
            "constraint_rank": projector.rank}


def _coherence_table(projected: np.ndarray, k: int, *, session) -> np.ndarray:
    """A level's k-coherence table, its parts searched in parallel on the session's workers.

    The table is one exact search of the sample's neighbourhoods against themselves (7 s for
    a 256^2 sample's finest level on one core), which the client did alone while every
    worker waited. The same parts as :func:`tasks.texture_optimization.coherence`: the same
    bits.
    """
    import dask

    from tasks.texture_optimization import coherence, coherence_parts, coherence_rows

    parts = coherence_parts(len(projected))
    if len(parts) < 2:
        return coherence(projected, k)
    shared = session.share(projected)
    rows = session.compute(*(dask.delayed(coherence_rows, pure=True)(shared, k, a, b)
                             for a, b in parts))
    return np.concatenate(rows)


def _no_table(projected: np.ndarray, k: int) -> None:
    """No k-coherence table: for a level none of whose tiles is computed."""
    return None


def _tile_names(level: int, regions: list) -> list[str]:
    """The units of a level's tiles (:func:`_level_tasks`)."""
    return [f"level{level}-tile{k}" for k in range(len(regions))]


def _level_regions(shape: tuple[int, int], tile: int
                   ) -> tuple[bool, list[tuple[int, int, int, int]]]:
    """Whether a level fits in one tile (then it is one task), and its tasks' regions."""
    whole = max(shape) <= tile
    return whole, [(0, shape[0], 0, shape[1])] if whole else tiles(shape, tile)


def _tile_statistics(sample: np.ndarray, shape: tuple[int, int], tile: int, halo: int,
                     params):
    """The sample's statistics for tiles of ``tile`` texels plus halo, or None without them."""
    from tasks.enlargement import statistics_channels
    from tasks.statistical_synthesis import sample_statistics

    big_h, big_w = shape
    side = (min(big_h, tile + 2 * halo), min(big_w, tile + 2 * halo))
    return None if params.statistics is None else sample_statistics(
        sample, side, params=params.statistics, channels=statistics_channels(sample, params))


def _level_tasks(here: str, name: str, regions, *, level: int, blend: bool, shape, factor: int,
                 coarse: str | None, coarse_shape, source, guide: Guide, params, halo: int,
                 finish) -> list:
    """One named :func:`level_task` per tile of a level, for :class:`pipeline.resume.Progress`.

    With ``blend`` the tiles write their grown results to ``_grown``, one slot each.
    """
    import dask

    return [(unit, dask.delayed(level_task)(
                here, "_grown" if blend else name, region, shape=shape, factor=factor,
                coarse=coarse, coarse_shape=coarse_shape, source=source, guide=guide,
                params=params, halo=halo, finish=finish, slot=k if blend else None))
            for k, (unit, region) in enumerate(zip(_tile_names(level, regions), regions,
                                                   strict=True))]


def _run_level(tasks: list, progress, session, *, factor: int, shape) -> list:
    """Log a level and compute its tasks not finished yet; returns every task's report."""
    done = len(progress.finished(name for name, _ in tasks))  # one look at the markers
    session.log(f"enlarge: level 1/{factor} ({shape[0]} x {shape[1]}) in {len(tasks)} "
                f"task(s)" + (f", {done} finished by the interrupted run" if done else ""))
    return progress.run(session.compute, tasks)


def _blend_level(out, here: str, name: str, regions, progress, session, *, shape,
                 halo: int) -> None:
    """Blend the grown tiles of ``_grown`` into ``name`` (:func:`blend_task`), then drop them."""
    import dask

    boxes = grown_boxes(regions, halo, shape)
    progress.run(session.compute, [
        (f"blend{k}", dask.delayed(blend_task)(here, "_grown", name, region, boxes,
                                               shape=shape, halo=halo))
        for k, region in enumerate(regions)])
    del out["_grown"]


def _level_arrays(out, name: str, shape: tuple[int, int], rank: int, tile: int, grown: int,
                  halo: int) -> None:
    """A level's scratch array, and with ``grown`` tiles to blend, their halo-grown copies.

    Both are kept when a killed run made them: their finished tiles are not redone.
    """
    from pipeline.stores.base import add_array

    if name not in out:
        add_array(out, name, shape=(*shape, rank), dims=("y", "x", "component"),
                  chunks=(tile, tile, rank))
    if grown and "_grown" not in out:
        side = tile + 2 * halo
        add_array(out, "_grown", shape=(grown, side, side, rank),
                  dims=("tile", "gy", "gx", "component"), chunks=(1, side, side, rank))


def _finest_report(reports: list[dict]) -> dict:
    """What the finest level's tasks report, summed over them: rounds, changes, residual."""
    residual2 = sum(r["residual2"] for r in reports)
    values = sum(r["values"] for r in reports)
    return {"rounds": max(len(r["changes"]) for r in reports),
            "changes": [r["changes"] for r in reports],
            "damping": [r["damping"] for r in reports],
            "constraint_residual_rms": float(np.sqrt(residual2 / values))}


def write_factors(out, path, u: np.ndarray, *, tile: int, session
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Re-factorise ``_coefficients`` in ``u``'s basis: write ``V``, return ``U`` and ``S``.

    The Gram matrix is summed over tiles, ``V`` written tile by tile; the scratch array goes.
    """
    import dask

    from pipeline.resume import Progress
    from pipeline.stores.base import location
    from tasks.svd import refactor_gram

    progress = Progress(path)
    regions = tiles(out["V"].shape[:2], tile)
    here = location(path)
    grams = progress.run(session.compute, [
        (f"gram{k}", dask.delayed(gram_task)(here, "_coefficients", r))
        for k, r in enumerate(regions)])
    new_u, new_s, basis = refactor_gram(u, sum(grams))
    progress.run(session.compute, [
        (f"factor{k}", dask.delayed(factor_task)(here, "_coefficients", r, basis, new_s))
        for k, r in enumerate(regions)])
    if "_coefficients" in out:
        del out["_coefficients"]
    return new_u, new_s
