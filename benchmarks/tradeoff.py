"""Run time against error for every stage that trades one for the other.

All configurations run once, in this process, one after the other (wall time of the stage's
own command, inputs prepared beforehand, after one untimed warm-up run of the stage):

- **compress**: rank, power iterations, and one pass against several, on a generated wood ABTF
  (256^2, ``abtf:12,4`` = 48 lights); error: the average ABRDF RMSE of paper 000, eq. (11),
  in linear radiance against the store itself;
- **quilt**: block size (overlap a quarter of it) and candidates K, on scikit-image's brick
  photo (three tone curves as layers, :mod:`benchmarks.seams`); error: the worst tile border
  of a V = 2 tile set over 2 seeds, seam or structure against the tile's inside (1 = as good
  as the inside; the planner keeps it under 1.3), with the lowest sharpness against the photo
  alongside; time: the slower seed's planning (border checks included), in-process;
- **roller**: tiles per set on a generated ``tiles`` ABTF (384^2, period 32); error: mean
  neighbour difference across tile borders of a rendered 1024^2 layer over the sample's own;
- **enlarge**: levels, EM iterations and rounds, wood 128^2 -> 256^2 with one photo at rank
  32 (as ``btf bench enlarge``); error: eq. (11) outside the sample.

A PNG per stage (``--plots DIR``): time on x, error on y, the default marked.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.enlarge import _btf, _factors, abrdf_error, truth_rows
from benchmarks.harness import chosen_stages, git_revision, machine

SUITE = "tradeoff"
STAGES = ("compress", "quilt", "roller", "enlarge")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the suite."""
    parser.add_argument("--stages", default=",".join(STAGES),
                        help="stages to sweep (default: all four)")
    parser.add_argument("--plots", metavar="DIR", default=None,
                        help="write tradeoff_STAGE.png files there")


def _timed(*args) -> float:
    start = time.perf_counter()
    _btf(*args)
    return time.perf_counter() - start


def _error(store: Path, truth: np.ndarray, mask: np.ndarray) -> float:
    """Eq. (11) of a compressed store against the truth over the masked texels."""
    u, s, v, transform, _ = _factors(store)
    return abrdf_error(u.reshape(-1, len(s)), v * s.astype(np.float32), transform, truth, mask)


def _compress(tmp: Path) -> list[dict]:
    store = tmp / "wood.zarr"
    _btf("generate", store, "--material", "wood", "--size", 256, "--sampling", "abtf:12,4",
         "--seed", 1)
    _btf("compress", store, tmp / "warm-up.zarr", "--rank", 8)  # imports, not timed
    truth = truth_rows(store)
    mask = np.ones(truth.shape[:2], bool)
    configs = [("rank 8", ["--rank", 8]), ("rank 16", ["--rank", 16]),
               ("rank 32", ["--rank", 32]), ("rank 64", ["--rank", 64]),
               ("rank 32, q = 0", ["--rank", 32, "--power-iters", 0]),
               ("rank 32, q = 1", ["--rank", 32, "--power-iters", 1]),
               ("rank 32, q = 4", ["--rank", 32, "--power-iters", 4]),
               ("rank 32, one pass", ["--rank", 32, "--passes", 1])]
    rows = []
    for label, options in configs:
        out = tmp / "svd.zarr"
        seconds = _timed("compress", store, out, *options, "--overwrite")
        error = _error(out, truth, mask)
        # --rank has no default: rank 32 with the default power iterations is the reference
        rows.append({"label": label, "seconds": seconds, "error": error,
                     "default": label == "rank 32"})
        print(f"compress {label}: {seconds:.1f} s, E {error:.4g}", file=sys.stderr)
    return rows


def _quilt() -> list[dict]:
    from benchmarks.seams import texture_seams

    rows = []
    configs = [(16, 5), (32, 5), (48, 5), (64, 5), (32, 1), (32, 20)]
    for block, k in configs:
        r = texture_seams("brick", block=block, seeds=range(2), corners=2, candidates=k)
        worst = max(r["seam"]["worst"], r["structure"]["worst"]) if r["seam"] else float("nan")
        rows.append({"label": f"B = {block}, K = {k}", "seconds": r["seconds"]["median"],
                     "error": worst, "sharpness": r["sharpness"]["worst"],
                     "default": (block, k) == (32, 5)})
        print(f"quilt B {block} K {k}: {rows[-1]['seconds']:.1f} s, worst border "
              f"{worst:.2f}", file=sys.stderr)
    return rows


def _roller(tmp: Path) -> list[dict]:
    import zarr

    from benchmarks.roller import _across, _roughness
    from pipeline.graphs.surface import lazy_layer
    from pipeline.stores.base import RADIANCE
    from pipeline.stores.radiance import open_radiance
    from tasks.placement import lattice_cells

    store = tmp / "tiles.zarr"
    _btf("generate", store, "--material", "tiles", "--size", 384, "--scale", 32, "--sampling",
         "abtf:4,2", "--seed", 1)
    sample = open_radiance(store)[RADIANCE]
    rows = []
    _btf("roller", store, tmp / "warm-up.zarr")  # imports and compilation, not timed
    for tiles in (1, 2, 4, 8):
        out = tmp / "roller.zarr"
        seconds = _timed("roller", store, out, "--tiles", tiles, "--overwrite")
        group = zarr.open_group(out, mode="r")
        lat = group.attrs["lattice"]
        cells = lattice_cells(0, 0, 1024, 1024, hnf=tuple(lat["hnf"]),
                              basis=(tuple(lat["U"]), tuple(lat["V"])),
                              representative=group["representative"][...])
        ratios = []
        for light in (0, 5):
            img = lazy_layer(out, view=0, light=light, size=(1024, 1024)).compute()
            ratios.append(_across(img, cells) / _roughness(sample[0, light].values))
        rows.append({"label": f"{tiles} tile(s)", "seconds": seconds,
                     "error": float(np.mean(ratios)), "default": tiles == 1})
        print(f"roller {tiles} tiles: {seconds:.1f} s, borders {rows[-1]['error']:.2f}",
              file=sys.stderr)
    return rows


def _enlarge(tmp: Path) -> list[dict]:
    m = tmp / "M.zarr"
    _btf("generate", m, "--material", "wood", "--size", 256, "--sampling", "abtf:12,4",
         "--seed", 1)
    _btf("crop", m, tmp / "S.zarr", "--region", "64:192,64:192")
    _btf("compress", tmp / "S.zarr", tmp / "S_svd.zarr", "--rank", 32)
    _btf("crop", m, tmp / "C.zarr", "--light", 0)
    truth = truth_rows(m)
    mask = np.ones((256, 256), bool)
    mask[64:192, 64:192] = False
    _btf("enlarge", tmp / "S_svd.zarr", tmp / "C.zarr", tmp / "warm-up.zarr", "--sample-origin",
         "64,64", "--levels", 1, "--iterations", 1, "--rounds", 1)  # imports, not timed
    configs = [("defaults", []), ("levels 1", ["--levels", 1]), ("levels 2", ["--levels", 2]),
               ("iterations 2", ["--iterations", 2]), ("iterations 5", ["--iterations", 5]),
               ("exact search", ["--search", "exact"]),
               ("statistics", ["--statistics"]),
               ("statistics, rounds 5, tol 0", ["--statistics", "--rounds", 5, "--tol", 0])]
    rows = []
    for label, options in configs:
        out = tmp / "E.zarr"
        seconds = _timed("enlarge", tmp / "S_svd.zarr", tmp / "C.zarr", out,
                         "--sample-origin", "64,64", *options, "--overwrite")
        error = _error(out, truth, mask)
        rows.append({"label": label, "seconds": seconds, "error": error,
                     "default": label == "defaults"})
        print(f"enlarge {label}: {seconds:.1f} s, E {error:.4g}", file=sys.stderr)
    return rows


ERRORS = {"compress": "eq. (11) ABRDF RMSE",
          "quilt": "worst tile border / inside (seam or structure)",
          "roller": "tile-border seam / sample", "enlarge": "eq. (11) ABRDF RMSE outside S"}


def _plot(stage: str, rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4), dpi=100)
    for r in rows:
        ax.scatter(r["seconds"], r["error"], marker="*" if r["default"] else "o",
                   s=160 if r["default"] else 40, color="C3" if r["default"] else "C0")
        ax.annotate(r["label"] + (" (default)" if r["default"] else ""),
                    (r["seconds"], r["error"]), fontsize=7, xytext=(4, 3),
                    textcoords="offset points")
    ax.set_xlabel("time (s)")
    ax.set_ylabel(ERRORS[stage])
    ax.set_title(f"btf {stage}: time against error")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def run(args: argparse.Namespace) -> dict:
    """Sweep every requested stage (see the module)."""
    stages = chosen_stages(args.stages, STAGES, SUITE)
    tmp = Path(tempfile.mkdtemp(prefix="btf-bench-tradeoff-"))
    result = {"suite": SUITE, "stages": {}, "machine": machine(), "git": git_revision()}
    try:
        for stage in stages:
            work = tmp / stage
            work.mkdir()
            rows = _quilt() if stage == "quilt" else {
                "compress": _compress, "roller": _roller, "enlarge": _enlarge}[stage](work)
            result["stages"][stage] = rows
            if args.plots:
                Path(args.plots).mkdir(parents=True, exist_ok=True)
                _plot(stage, rows, Path(args.plots) / f"tradeoff_{stage}.png")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return result


def report(result: dict) -> str:
    """One Markdown table per stage."""
    lines = []
    for stage, rows in result["stages"].items():
        extra = " | sharpness" if stage == "quilt" else ""
        lines += [f"`btf {stage}`: {ERRORS[stage]} against time (* = default).", "",
                  f"| setting | seconds | error{extra} |",
                  "|---|---|---|" + ("---|" if extra else "")]
        for r in rows:
            lines.append(f"| {r['label']}{' *' if r['default'] else ''} | {r['seconds']:.1f} "
                         f"| {r['error']:.4g}"
                         + (f" | {r['sharpness']:.2f}" if stage == "quilt" else "") + " |")
        lines.append("")
    return "\n".join(lines).rstrip()
