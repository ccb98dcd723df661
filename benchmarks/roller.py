"""The roller: analysis time, synthesis throughput, and its seams against quilting's.

All in one run, on generated ``tiles`` ABTFs (a periodic material) with 24 lights
(``abtf:6,4``, one view):

- **analysis**: lattice detection (:func:`tasks.periodicity.detect_lattice`) and the double
  toroidal tile (:func:`tasks.roller.plan_roller`, default periods and band) on the
  perpendicularly lit layer of a 256^2 and a 512^2 sample, as ``btf roller`` does; next to
  quilting's plan (:func:`tasks.quilting.plan_tiles`, block 32, overlap 8, K = 5) of a
  periodic tile on the same image, for scale;
- **synthesis**: one layer of a large region rendered lazily from the roller tile set of the
  last sample (:func:`pipeline.graphs.surface.lazy_layer`: hash of the lattice cell, slice copies),
  against ``numpy.tile`` of one tile into blocks of the same size and threads
  (:func:`benchmarks.quilt.render_throughput`), and ``btf roller`` end to end;
- **seams**: on that sample, the mean absolute difference between neighbouring texels that lie
  in different tiles (different lattice cells for the roller, different tile positions for
  quilting), over a 1024^2 region of several layers, divided by the sample's own mean
  neighbour difference in that layer (1 = no rougher than the sample); and the same ratio
  over all neighbour pairs of the region, which also counts quilting's seams inside a tile.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.harness import (
    best_of,
    btf_executable,
    fastest,
    generate_store,
    git_revision,
    machine,
    parse_sizes,
)
from benchmarks.lattices import detection_rates
from benchmarks.quilt import render_throughput

SUITE = "roller"
SAMPLING = "abtf:6,4"
SEAM_REGION = 1024
SEAM_LIGHTS = (0, 11, 23)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the suite."""
    parser.add_argument("--material", default="tiles",
                        help="a periodic generated material (default tiles)")
    parser.add_argument("--sizes", default="256,512",
                        help="sample sizes to analyse (comma-separated; the last one is also "
                             "tiled, rendered and compared with quilting)")
    parser.add_argument("--render", type=int, default=16384,
                        help="side of the rendered region in texels (default 16384)")
    parser.add_argument("--lattices", type=int, default=400, metavar="N",
                        help="random lattices to detect (benchmarks.lattices; 0 skips; default "
                             "400)")
    parser.add_argument("--seam-seeds", type=int, default=20, metavar="N",
                        help="random lattices rolled into 3 tiles and laid with their seed, "
                             "each measured on its own (benchmarks/seams.py; 0: none)")
    parser.add_argument("--seams-only", action="store_true",
                        help="measure the per-seed tile borders only")
    parser.add_argument("--repeat", type=int, default=3,
                        help="runs of each timing; the fastest is kept (default 3)")


def _analysis(store: Path, args, session) -> tuple[dict, np.ndarray]:
    from pipeline.stages.roller import analysis_image
    from tasks.corner_tiles import plan_tiles
    from tasks.periodicity import detect_lattice
    from tasks.quilting import QuiltParams
    from tasks.reference import luminance
    from tasks.roller import RollerParams, plan_roller

    image, _ = analysis_image(str(store), "layer", session)
    if detect_lattice(luminance(image)).confidence < 0.5:
        raise SystemExit(f"btf bench roller: {store.name} shows no clear periodicity (a larger "
                         "--sizes, or a periodic --material)")

    def analyse():
        lattice = detect_lattice(luminance(image))
        return lattice, plan_roller(image, lattice.u, lattice.v, RollerParams())

    seconds, (lattice, plan) = fastest(args.repeat, analyse)
    detect, _ = fastest(args.repeat, lambda: detect_lattice(luminance(image)))
    step = 32 - 8
    tile = tuple(max(2 * step, (n // step) * step) for n in image.shape[:2])
    # one plan and its border check, no planning again: the cost of a plan that passes
    quilt, _ = fastest(args.repeat, lambda: plan_tiles(
        image, QuiltParams(32, 8, 5, 1, tile, max_seam=1e9), seed=0))
    return {"size": image.shape[0], "seconds": seconds, "detect_seconds": detect,
            "quilt_plan_seconds": quilt, "lengths_px": list(lattice.lengths_px),
            "angles_deg": list(lattice.angles_deg), "confidence": lattice.confidence,
            "tile_texels": plan.area, "periods": list(plan.periods)}, image


def _roughness(img: np.ndarray) -> float:
    return float(np.mean([np.abs(np.diff(img, axis=a)).mean() for a in (0, 1)]))


def _across(img: np.ndarray, cells: np.ndarray) -> float:
    """Mean absolute difference of neighbouring texels in different cells."""
    dx = np.abs(np.diff(img, axis=1)).mean(axis=-1)[np.any(cells[:, 1:] != cells[:, :-1], -1)]
    dy = np.abs(np.diff(img, axis=0)).mean(axis=-1)[np.any(cells[1:] != cells[:-1], -1)]
    return float(np.concatenate([dx, dy]).mean())


def _seams(store: Path, roller: Path, quilt: Path) -> dict:
    import zarr

    from pipeline.graphs.surface import lazy_layer
    from pipeline.stores.base import RADIANCE
    from pipeline.stores.radiance import open_radiance
    from tasks.placement import lattice_cells

    n = SEAM_REGION
    sample = open_radiance(store)[RADIANCE]
    lat = zarr.open_group(roller, mode="r").attrs["lattice"]
    cells = {"roller": lattice_cells(0, 0, n, n, hnf=tuple(lat["hnf"]),
                                     basis=(tuple(lat["U"]), tuple(lat["V"])),
                                     representative=zarr.open_group(roller, mode="r")[
                                         "representative"][...])}
    ty, tx = zarr.open_group(quilt, mode="r").attrs["tile_shape"]
    yy, xx = np.mgrid[0:n, 0:n]
    cells["quilt"] = np.stack([yy // ty, xx // tx], axis=-1)
    rows = {}
    for name, path in (("roller", roller), ("quilt", quilt)):
        border, overall = [], []
        for light in SEAM_LIGHTS:
            own = _roughness(sample[0, light].values)
            img = lazy_layer(path, view=0, light=light, size=(n, n)).compute()
            border.append(_across(img, cells[name]) / own)
            overall.append(_roughness(img) / own)
        rows[name] = {"tile_border": float(np.mean(border)), "all_pairs": float(np.mean(overall))}
    return rows


def run(args: argparse.Namespace) -> dict:
    """Analyse, tile, render and compare, with their references, in this run."""
    from benchmarks.seams import roller_seams
    from pipeline.session import RuntimeOptions, Session

    per_seed = roller_seams(range(args.seam_seeds),
                            log=lambda m: print(m, file=sys.stderr)) if args.seam_seeds else None
    if args.seams_only:
        return {"suite": SUITE, "per_seed": per_seed, "machine": machine(),
                "git": git_revision()}
    btf = btf_executable()
    detection = detection_rates(args.lattices, seed=1, threshold=0.5) if args.lattices else None
    if detection:
        found = sum(r["found"] for r in detection["rows"])
        print(f"detection: {found} of {args.lattices} random lattices", file=sys.stderr)
    tmp = Path(tempfile.mkdtemp(prefix="btf-bench-roller-"))
    sizes = parse_sizes(args.sizes, SUITE)
    analysis = []
    try:
        with Session(RuntimeOptions(quiet=True)) as session:
            for size in sizes:
                store = tmp / f"{args.material}-{size}.zarr"
                generate_store(store, args.material, size, SAMPLING)
                row, _ = _analysis(store, args, session)
                analysis.append(row)
                print(f"analysed {size}^2: {row['seconds']:.2f} s (detection "
                      f"{row['detect_seconds']:.3f} s); quilting plan "
                      f"{row['quilt_plan_seconds']:.2f} s", file=sys.stderr)
        tiles = tmp / "roller.zarr"
        cli = best_of(args.repeat, [btf, "roller", str(store), str(tiles), "--quiet",
                                    "--overwrite"])
        rendering = render_throughput(tiles, args)
        quilt = tmp / "quilt.zarr"
        subprocess.run([btf, "quilt", str(store), str(quilt), "--quiet"], check=True)
        seams = _seams(store, tiles, quilt)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return {"suite": SUITE, "material": args.material, "sampling": SAMPLING,
            "repeat": args.repeat, "analysis": analysis,
            "roller_cli": {"size": sizes[-1], "seconds": cli.seconds, "peak_rss": cli.peak_rss},
            "rendering": rendering, "seams": seams, "per_seed": per_seed,
            "detection": detection, "machine": machine(),
            "git": git_revision()}


def per_seed_report(p: dict | None) -> list[str]:
    """The per-seed tile-border table of :func:`benchmarks.seams.roller_seams`."""
    if not p:
        return []

    def cell(key):
        s = p[key]
        return (f"{s['worst']:.2f} (seed {s['worst_seed']}: {s['worst_case']}) | "
                f"{s['median']:.2f}")

    failed = "; ".join(f"seed {s}: {why}" for s, why in p["failed"]) or "none"
    return ["", f"Tile borders of the roller, seed by seed: {len(p['seeds'])} random lattices "
                f"(`benchmarks/lattices.py`, drawn from the seed), {p['tiles']} tiles each, a "
                f"{384}^2 surface laid with the seed; borders of the lattice cells against "
                "their insides (`benchmarks/seams.py`; 1.00 = as good as the inside, which "
                "copies the sample: there the sample's own period-to-period distance is the "
                f"reference). Not rolled: {failed}.", "",
            "| measure | worst (seed: texture) | median |", "|---|---|---|",
            f"| seam across cell borders | {cell('seam')} |",
            f"| structure along them | {cell('structure')} |",
            f"| sharpness vs the sample (lowest) | {cell('sharpness')} |"]


def report(result: dict) -> str:
    """Markdown tables of a result."""
    if "analysis" not in result:
        return "\n".join(per_seed_report(result["per_seed"])).strip()
    mib = 1 << 20
    lines = [f"`btf bench roller`: {result['material']} samples, {result['sampling']} "
             f"(24 lights, one view); best of {result['repeat']} runs.", "",
             "| sample | lattice (px, deg) | confidence | tile texels | detection (s) | "
             "detection + tile (s) | quilting plan, same image (s) |",
             "|---|---|---|---|---|---|---|"]
    for r in result["analysis"]:
        lattice = ", ".join(f"{n:.1f} at {a:.0f}" for n, a in zip(r["lengths_px"],
                                                                  r["angles_deg"], strict=True))
        lines.append(f"| {r['size']}^2 | {lattice} | {r['confidence']:.2f} | "
                     f"{r['tile_texels']} | {r['detect_seconds']:.3f} | {r['seconds']:.2f} | "
                     f"{r['quilt_plan_seconds']:.2f} |")
    c, r, s = result["roller_cli"], result["rendering"], result["seams"]
    lines += ["", f"`btf roller` end to end on the {c['size']}^2 sample (analysis image, "
                  f"detection, tile, applying it to 24 layers, writing): {c['seconds']:.1f} s, "
                  f"peak RSS {c['peak_rss'] / mib:.0f} MiB.", "",
              f"Synthesis of one layer, {r['size']} x {r['size']} texels "
              f"({r['bytes'] / mib:.0f} MiB), blocks of {r['block']}^2, 2 threads:", "",
              "| what | seconds | GB/s |", "|---|---|---|",
              f"| lazy render (lattice cell hash + slice copies), computed and dropped | "
              f"{r['render_seconds']:.2f} | {r['render_gbps']:.2f} |",
              f"| numpy.tile of one tile into the same blocks (reference) | "
              f"{r['tile_seconds']:.2f} | {r['tile_gbps']:.2f} |", "",
              f"Render vs numpy.tile: {r['ratio']:.2f}x its speed.", "",
              f"Seams on the {c['size']}^2 sample, {SEAM_REGION}^2 region, lights "
              f"{', '.join(map(str, SEAM_LIGHTS))}; mean neighbour difference relative to the "
              "sample's own (1.00 = as smooth as the sample):", "",
              "| output | across tile borders | all neighbour pairs |", "|---|---|---|",
              f"| roller (double toroidal tile) | {s['roller']['tile_border']:.2f} | "
              f"{s['roller']['all_pairs']:.2f} |",
              f"| quilting (periodic tile, defaults) | {s['quilt']['tile_border']:.2f} | "
              f"{s['quilt']['all_pairs']:.2f} |"]
    lines += per_seed_report(result.get("per_seed"))
    if result.get("detection"):
        lines += ["", *detection_report(result["detection"])]
    return "\n".join(lines)


def _rate(rows) -> str:
    return f"{sum(r['found'] for r in rows)}/{len(rows)}" if rows else "-"


def detection_report(d: dict) -> list[str]:
    """Detection rates by motif, noise and period; failure modes; stochastic confidences."""
    rows = d["rows"]
    lines = [f"Lattice detection on {d['count']} random lattices (`benchmarks/lattices.py`, seed "
             f"{d['seed']}): found = confidence >= {d['threshold']} and both vectors within 1 px "
             "of the true lattice with the cell area within 5%; "
             f"{d['seconds_per_image'] * 1e3:.0f} ms per image.", "",
             "| motif | all | noise 0 | noise <= 0.1 | noise > 0.1 | shortest period < 12 px | "
             "12-32 px | > 32 px |", "|---|---|---|---|---|---|---|---|"]
    for motif in [*sorted({r["motif"] for r in rows}), "all"]:
        sel = [r for r in rows if motif in ("all", r["motif"])]
        lines.append("| " + " | ".join([motif, _rate(sel)] + [
            _rate([r for r in sel if test(r)]) for test in (
                lambda r: r["noise"] == 0, lambda r: 0 < r["noise"] <= 0.1,
                lambda r: r["noise"] > 0.1, lambda r: r["shortest"] < 12,
                lambda r: 12 <= r["shortest"] <= 32, lambda r: r["shortest"] > 32)]) + " |")
    misses = [r for r in rows if not r["found"]]
    lines += ["", "Misses:" if misses else "No misses."]
    lines += [f"- {r['case']}: {r['mode']} (confidence {r['confidence']:.2f})" for r in misses]
    neg = d["negatives"]
    lines += ["", f"Stochastic textures ({', '.join(sorted({k.rsplit('-', 1)[0] for k in neg}))};"
                  f" {len(neg)} images): highest confidence {max(neg.values()):.2f}, false "
                  f"positives {sum(c >= d['threshold'] for c in neg.values())}."]
    return lines
