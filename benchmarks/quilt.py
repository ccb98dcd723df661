"""Quilting: one plan for all layers against quilting each layer, application, rendering.

All in one run, on generated ABTFs with 24 lights (``abtf:6,4``, one view):

- **planning**: :func:`tasks.quilting.plan_tiles` on the reference image of a 256^2 and a 512^2
  sample (block 32, overlap 8, K = 5, one corner type: a periodic texture), against the same
  code run on each of the 24 layers independently, which is what a user without prescriptions
  would do; how much those independent plans disagree (share of output texels whose main source
  texel differs from layer 0's plan) shows why that gives inconsistent layers;
- **application**: the 512^2 plan's prescription applied to the 24 layers in memory
  (:func:`tasks.prescription.apply`), with one thread and with two threads each taking half of
  the layers (the pipeline's tasks each take a block of lights), in GB/s of output, next to
  ``numpy.copyto`` of the same bytes with the same threads (and scipy's CSR product per layer,
  the previous implementation); and
  ``btf quilt`` end to end (fresh process: wall time and peak RSS);
- **rendering**: one layer of a large surface from the tile set, computed block by block with
  dask's threads and dropped (:func:`pipeline.graphs.surface.lazy_layer`), against ``numpy.tile`` of
  one tile into blocks of the same size and threads; and ``btf render`` of that region into a
  zarr array end to end (wall time and peak RSS: bounded by the block size).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

import numpy as np

from benchmarks.harness import (
    best_of,
    btf_executable,
    fastest,
    generate_store,
    git_revision,
    in_threads,
    machine,
    measure,
    parse_sizes,
)

SUITE = "quilt"
SAMPLING = "abtf:6,4"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the suite."""
    parser.add_argument("--material", default="fabric")
    parser.add_argument("--sizes", default="256,512",
                        help="sample sizes to plan on (comma-separated; the last one is also "
                             "applied and rendered)")
    parser.add_argument("--block", type=int, default=32)
    parser.add_argument("--overlap", type=int, default=8)
    parser.add_argument("--candidates", type=int, default=5)
    parser.add_argument("--render", type=int, default=16384,
                        help="side of the rendered region in texels (default 16384)")
    parser.add_argument("--repeat", type=int, default=3,
                        help="runs of the planning, application and copy timings; the fastest "
                             "is kept (default 3); independent per-layer plans run once")
    parser.add_argument("--seams", default="brick,gravel,grass,moon,lattice,tiles,fabric",
                        metavar="T,..",
                        help="textures whose wrap and tile-border seams to measure "
                             "(benchmarks/seams.py: scikit-image photos, a random lattice or "
                             "generated materials; empty: none)")
    parser.add_argument("--seam-seeds", type=int, default=20, metavar="N",
                        help="seeds per texture and setting, each measured on its own "
                             "(default 20)")
    parser.add_argument("--seam-corners", default="1,2", metavar="V,..",
                        help="corner types of the tile sets measured (default 1,2)")
    parser.add_argument("--seam-blocks", default="auto,48", metavar="B,..",
                        help="blocks of the seams' plans: auto (as btf quilt chooses) and given "
                             "sizes, overlap a quarter (default auto,48)")
    parser.add_argument("--search-checks", type=int, default=0, metavar="N",
                        help="also time the border check's nearest-patch search against an "
                             "exact brute-force one on N checks recorded per texture "
                             "(benchmarks/seams.py, search_accuracy; default 0: not run)")
    parser.add_argument("--seam-threads", type=int, default=os.cpu_count() or 1, metavar="N",
                        help="tiles planned at once, as btf quilt plans them (default: one per "
                             "core; the plans are the same for any number)")
    parser.add_argument("--seams-only", action="store_true",
                        help="measure the seams (and the photo plans) only (no planning, "
                             "application or rendering)")
    parser.add_argument("--photo-plans", default="brick,gravel,grass", metavar="P,..",
                        help="scikit-image photos to plan tile sets on as btf quilt "
                             "--corners 2 does, 256^2 crops and seeds drawn at random "
                             "(benchmarks/photoplans.py; empty: none)")
    parser.add_argument("--photo-seeds", type=int, default=20, metavar="N",
                        help="draws (crop and seed) per photo (default 20; 0: none)")
    parser.add_argument("--photo-draw", type=int, default=None, metavar="N",
                        help="repeat the draw a run printed (default: a new one)")
    parser.add_argument("--photos-only", action="store_true",
                        help="the photo plans only")


def _main_source(tile) -> np.ndarray:
    """Per output texel, the sample texel with the largest weight."""
    from tasks.canvas import TERMS

    index = tile.index.reshape(-1, TERMS)
    weight = tile.weight.reshape(-1, TERMS)
    return index[np.arange(index.shape[0]), np.argmax(weight, axis=1)]


def _planning(store: Path, args, session) -> tuple[dict, object, object]:
    from pipeline.graphs.reference import compute_reference
    from pipeline.stores import open_layers
    from pipeline.stores.base import RADIANCE
    from tasks.corner_tiles import plan_tiles
    from tasks.quilting import QuiltParams

    maps, view = compute_reference(store, weights=(1.0, 0.5, 0.5), view=None, session=session)
    sample = maps.reference.shape[:2]
    step = args.block - args.overlap
    # one plan and its border check, no planning again: the same work on every layer
    params = QuiltParams(args.block, args.overlap, args.candidates, 1,
                         tuple((n // step) * step for n in sample), max_seam=1e9)
    seconds, plan = fastest(args.repeat, lambda: plan_tiles(maps.reference, params, seed=0))
    layers = open_layers(store)[RADIANCE].data[view].compute()
    main = None
    disagree, start = [], time.perf_counter()
    for layer in layers:
        tile = plan_tiles(layer, params, seed=0).tiles[0]
        if main is None:
            main = _main_source(tile)
        else:
            disagree.append(float(np.mean(_main_source(tile) != main)))
    independent = time.perf_counter() - start
    row = {"size": sample[0], "tile": list(params.tile), "placements": len(plan.placements),
           "plan_seconds": seconds, "layers": len(layers), "independent_seconds": independent,
           "independent_disagreement": float(np.mean(disagree)) if disagree else None}
    return row, plan, layers


def _application(plan, layers: np.ndarray, args) -> dict:
    from tasks.canvas import TERMS
    from tasks.prescription import apply, to_csr

    tile = plan.tiles[0]
    ny, nx = layers.shape[1:3]
    matrix = to_csr(tile.index.reshape(-1, TERMS), tile.weight.reshape(-1, TERMS), ny * nx)
    shape = tile.index.shape[:2]
    out = np.empty((layers.shape[0], *shape, layers.shape[-1]), np.float32)
    source = np.ones_like(out)
    nbytes = out.nbytes
    half = layers.shape[0] // 2
    halves = [slice(0, half), slice(half, None)]  # slices: views, not fancy-indexed copies
    def prescribed(ls):  # the compiled loop, whatever the work (not compiled_pays' choice)
        apply(matrix, layers[ls], output=shape, out=out[ls], compiled=True)

    def scipy_product(ls):  # the previous implementation: one scipy CSR product per layer
        for i in range(*ls.indices(layers.shape[0])):
            out[i] = (matrix @ layers[i].reshape(-1, layers.shape[-1])).reshape(out.shape[1:])

    def copied(ls):
        np.copyto(out[ls], source[ls])

    prescribed(slice(0, 1))  # compiles the kernel: not part of the timings
    rows = {}
    for threads in (1, 2):
        parts = halves if threads == 2 else [slice(None)]
        t_apply, _ = fastest(args.repeat, partial(in_threads, threads, prescribed, parts))
        t_copy, _ = fastest(args.repeat, partial(in_threads, threads, copied, parts))
        t_scipy, _ = fastest(args.repeat, partial(in_threads, threads, scipy_product, parts))
        rows[threads] = {"apply_gbps": nbytes / t_apply / 1e9,
                         "copy_gbps": nbytes / t_copy / 1e9, "ratio": t_copy / t_apply,
                         "scipy_gbps": nbytes / t_scipy / 1e9}
    return {"bytes": nbytes, "nnz_per_row": matrix.nnz / matrix.shape[0], "threads": rows}


class _Sink:
    """A write target that drops what it is given (for timing a computation alone)."""

    def __setitem__(self, key, value) -> None:
        pass


def render_throughput(tileset: Path, args) -> dict:
    """One layer of an ``args.render``-square region rendered lazily, against ``numpy.tile``."""
    import dask
    import dask.array as da

    from pipeline.graphs.surface import lazy_layer
    from pipeline.stores import TileSetStore, open_store

    size = args.render
    layer = lazy_layer(tileset, view=0, light=0, size=(size, size), seed=0)
    nbytes = size * size * layer.shape[-1] * 4
    with dask.config.set(scheduler="threads", num_workers=2):
        t_render, _ = fastest(args.repeat, lambda: da.store(layer, _Sink(), lock=False))
    tile = open_store(tileset, TileSetStore)["radiance"][0, 0, 0]
    block = layer.chunksize[0]
    reps = (-(-block // tile.shape[0]), -(-block // tile.shape[1]), 1)
    blocks = range(len(layer.chunks[0]) * len(layer.chunks[1]))

    def tiled(_):
        np.ascontiguousarray(np.tile(tile, reps)[:block, :block])

    t_tile, _ = fastest(args.repeat, lambda: in_threads(2, tiled, blocks))
    return {"size": size, "bytes": nbytes, "block": block, "render_seconds": t_render,
            "render_gbps": nbytes / t_render / 1e9, "tile_seconds": t_tile,
            "tile_gbps": nbytes / t_tile / 1e9, "ratio": t_tile / t_render}


def run(args: argparse.Namespace) -> dict:
    """Plan, apply and render, with their references, in this run."""
    from pipeline.session import RuntimeOptions, Session

    photos = _photos(args)
    if args.photos_only:
        return {"suite": SUITE, "seams": [], "search": [], "photos": photos,
                "machine": machine(), "git": git_revision()}
    seams = _seams(args)
    search = _search(args)
    if args.seams_only:
        return {"suite": SUITE, "seams": seams, "search": search, "photos": photos,
                "machine": machine(), "git": git_revision()}
    btf = btf_executable()
    tmp = Path(tempfile.mkdtemp(prefix="btf-bench-quilt-"))
    sizes = parse_sizes(args.sizes, SUITE)
    planning = []
    try:
        with Session(RuntimeOptions(quiet=True)) as session:
            for size in sizes:
                store = tmp / f"{args.material}-{size}.zarr"
                generate_store(store, args.material, size, SAMPLING)
                row, plan, layers = _planning(store, args, session)
                planning.append(row)
                print(f"planned {size}^2: {row['plan_seconds']:.2f} s; {row['layers']} layers "
                      f"independently {row['independent_seconds']:.1f} s", file=sys.stderr)
        application = _application(plan, layers, args)
        tiles = tmp / "tiles.zarr"
        command = [btf, "quilt", str(store), str(tiles), "--block", str(args.block),
                   "--overlap", str(args.overlap), "--candidates", str(args.candidates),
                   "--quiet", "--overwrite"]
        quilt = best_of(args.repeat, command)
        # one plan, as in the planning rows: the application rate's run (with the border
        # check's bound, the plans it takes again would count as application)
        one_plan = best_of(args.repeat, [*command, "--max-seam", "1e9"])
        rendering = render_throughput(tiles, args)
        region = tmp / "surface.zarr"
        render_cli = measure([btf, "render", str(tiles), str(region), "--light", "0", "--size",
                              f"{args.render},{args.render}", "--quiet"])
        rendering.update({"cli_seconds": render_cli.seconds, "cli_peak_rss": render_cli.peak_rss})
        shutil.rmtree(region)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return {"suite": SUITE, "material": args.material, "sampling": SAMPLING,
            "params": {"block": args.block, "overlap": args.overlap,
                       "candidates": args.candidates}, "repeat": args.repeat,
            "planning": planning, "application": application,
            "quilt_cli": {"size": sizes[-1], "seconds": quilt.seconds,
                          "peak_rss": quilt.peak_rss, "one_plan_seconds": one_plan.seconds},
            "rendering": rendering, "seams": seams, "search": search, "photos": photos,
            "machine": machine(), "git": git_revision()}


def _photos(args) -> dict | None:
    from benchmarks import photoplans

    names = [n for n in args.photo_plans.split(",") if n]
    if not names or args.photo_seeds <= 0:
        return None
    return photoplans.run(names, args.photo_seeds, args.photo_draw, args.seam_threads)


def _seams(args) -> list[dict]:
    from benchmarks.seams import texture_seams

    rows = []
    log = lambda message: print(message, file=sys.stderr)  # noqa: E731
    blocks = [None if b == "auto" else int(b) for b in args.seam_blocks.split(",")]
    if args.seam_seeds <= 0:
        return rows
    for texture in filter(None, args.seams.split(",")):
        for corners in (int(v) for v in args.seam_corners.split(",")):
            for block in blocks:  # e.g. the automatic choice, and the bug report's 48 / 12
                rows.append(texture_seams(texture, block=block, seeds=range(args.seam_seeds),
                                          corners=corners, threads=args.seam_threads, log=log))
    return rows


def _search(args) -> list[dict]:
    from benchmarks.seams import search_accuracy

    if args.search_checks <= 0:
        return []
    return [search_accuracy(texture, checks=args.search_checks)
            for texture in filter(None, args.seams.split(","))]


def _seams_report(result: dict) -> list[str]:
    from benchmarks.photoplans import report as photos_report
    from benchmarks.seams import seams_report, search_report

    lines = ["", *photos_report(result["photos"])] if result.get("photos") else []
    if result.get("search"):
        lines += ["", "The border check's nearest-patch search (`benchmarks/seams.py`, "
                      "search_accuracy): checks recorded while planning V = 2 tile sets, "
                      "measured again with each search and with an exact brute-force one at "
                      "full dimension:", "", *search_report(result["search"])]
    if not result.get("seams"):
        return lines
    return [*lines, "", "Seams of periodic textures (V = 1) and of 4 x 4 mosaics of corner "
            "tile sets (V = 2), seed by seed (`benchmarks/seams.py`): the worst border line of "
            "each texture or tile against its inside (1.00 = as good as the inside; the bound "
            "is 1.3), the worst seed's figure with the seed, and the median; sharpness = the "
            "texture's neighbour differences over the photo's:", "",
            *seams_report(result["seams"])]


def report(result: dict) -> str:
    """Markdown tables of a result."""
    if "planning" not in result:
        return "\n".join(_seams_report(result)).strip()
    mib = 1 << 20
    p = result["params"]
    lines = [f"`btf bench quilt`: {result['material']} samples, {result['sampling']} "
             f"(24 lights, one view); block {p['block']}, overlap {p['overlap']}, "
             f"K = {p['candidates']}, one corner type; best of {result['repeat']} runs.",
             "",
             "| sample | tile | placements | plan once (s) | each layer on its own (s) | ratio | "
             "independent plans disagree |",
             "|---|---|---|---|---|---|---|"]
    for r in result["planning"]:
        lines.append(f"| {r['size']}^2 | {r['tile'][0]}^2 | {r['placements']} | "
                     f"{r['plan_seconds']:.2f} | {r['independent_seconds']:.1f} "
                     f"({r['layers']} layers) | {r['independent_seconds'] / r['plan_seconds']:.1f}x"
                     f" | {100 * r['independent_disagreement']:.0f}% of texels |")
    a = result["application"]
    lines += ["", f"Application of the {result['planning'][-1]['size']}^2 plan's prescription "
                  f"({a['nnz_per_row']:.2f} terms per output texel) to 24 layers, "
                  f"{a['bytes'] / mib:.0f} MiB of output:", "",
              "| threads | prescription GB/s | numpy copy GB/s | ratio (target >= 0.25) | "
              "scipy CSR product GB/s |",
              "|---|---|---|---|---|"]
    for threads, t in a["threads"].items():
        lines.append(f"| {threads} | {t['apply_gbps']:.2f} | {t['copy_gbps']:.2f} | "
                     f"{t['ratio']:.2f} | {t['scipy_gbps']:.2f} |")
    q = result["quilt_cli"]
    r = result["rendering"]
    lines += ["", f"`btf quilt` end to end on the {q['size']}^2 sample (reference, plan, "
                  f"application, writing): {q['seconds']:.1f} s, peak RSS "
                  f"{q['peak_rss'] / mib:.0f} MiB"
                  + (f"; {q['one_plan_seconds']:.1f} s with the border check's bound lifted "
                     "(one plan: the application rate's run)" if "one_plan_seconds" in q
                     else "") + ".", "",
              f"Rendering one layer, {r['size']} x {r['size']} texels "
              f"({r['bytes'] / mib:.0f} MiB), blocks of {r['block']}^2, 2 threads:", "",
              "| what | seconds | GB/s |", "|---|---|---|",
              f"| lazy render (hash placement + gather), computed and dropped | "
              f"{r['render_seconds']:.2f} | {r['render_gbps']:.2f} |",
              f"| numpy.tile of one tile into the same blocks (reference) | "
              f"{r['tile_seconds']:.2f} | {r['tile_gbps']:.2f} |",
              f"| `btf render ... OUT.zarr` end to end (writes lz4 zarr) | "
              f"{r['cli_seconds']:.2f} | {r['bytes'] / r['cli_seconds'] / 1e9:.2f} |",
              "", f"Render vs numpy.tile: {r['ratio']:.2f}x its speed; `btf render` peak RSS "
                  f"{r['cli_peak_rss'] / mib:.0f} MiB for a {r['bytes'] / mib:.0f} MiB region."]
    return "\n".join(lines + _seams_report(result))


def rates(result: dict) -> dict[str, float]:
    """The rates ``btf run --plan`` uses: planning time per tile texel and sample texel (the
    client's, serial) and float32 values written per core-second by ``btf quilt``'s
    application, end to end: the wall time of a run that plans once (the check's bound lifted)
    less that plan and a second of start-up.
    """
    from tasks.sampling import parse_sampling

    if "planning" not in result:
        return {}
    largest = max(result["planning"], key=lambda r: r["size"])
    tile = largest["tile"][0] * largest["tile"][1]
    s = parse_sampling(result["sampling"])
    values = tile * s.theta_view.size * s.theta_light.size * 3
    out = {"quilt_plan_seconds_per_texel_pair":
           largest["plan_seconds"] / (tile * largest["size"] ** 2)}
    # a result of before had no one-plan run: its run planned until the check passed
    applying = result["quilt_cli"].get("one_plan_seconds", 0.0) - largest["plan_seconds"] - 1.0
    if applying > 0:
        out["quilt_values_per_core_second"] = values / applying / result["machine"]["cpus"]
    return out
