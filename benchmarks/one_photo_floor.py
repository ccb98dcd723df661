"""How low can one photo take the gap share? Regressors trained on many truths (issue 57, a study).

``python -m benchmarks.one_photo_floor bumps:1,bumps:2,stone:5 [OPTIONS]``: the cases
(``material:seed``), each the enlargement bench's one-photo case
(:func:`benchmarks.enlarge._material`: a 128^2 truth under btf's shading, ``abtf:12,4``, its
central 64^2 at rank 16, the top light's layer as the photo), whose oracle, lookup and
``btf enlarge`` error it measures; ``OPTIONS``, more ``btf generate`` options for every truth
(e.g. ``"--renderer mitsuba --spp 64 --bsdf conductor"``). For each material, 24 more truths
of other seeds (for the bumps also other crops of the grass photo, none overlapping the
bench's) train regressors from what a photo shows at a texel to its whole ABRDF (linear
radiance, every layer): 96x the texels a 64^2 sample holds, of the very process the case was
drawn from.

Regressors: ridge regression on 1,000 random Fourier features (a smooth nonlinear fit) at
three length scales, and the mean of the 64 training texels nearest in photo colour (the
posterior mean given the colour). Features:

- ``colour``: the photo's log colour at the texel;
- ``multiscale``: that, and the photo's log luminance blurred at 1, 2, 4 and 8 texels with
  its gradients there (the shading's slope and the neighbours' heights, if the photo shows
  them);
- ``patch``: the log colour and the 5 x 5 neighbourhood of log luminance around it;
- controls, information one photo does not give: ``ten`` (the log colours under the
  bench's ten lights of the case's seed) and ``slope`` (the colour and the truth's height
  gradient).

Each regressor's gap share is against the case's own oracle and lookup; the best length
scale is taken on the case itself, which favours the regressors. If no regressor given one
photo comes near 0.5 while the controls do, what is missing is information, not fitting.
One JSON line per case. Not a ``btf bench`` suite: a study whose figures are in BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.ndimage as ndi
from numpy.lib.stride_tricks import sliding_window_view

from benchmarks.enlarge import (
    SAMPLING,
    _btf,
    _material,
    generate_args,
    material_seeds,
    truth_rows,
)
from tasks.evaluation import gap_share

SIZE, TRAIN, FEATURES, NEIGHBOURS = 128, 24, 1000, 64
SCALES = (2.0, 4.0, 8.0)  # length scales of the random features, in standard deviations
EPS = 1e-3  # the log's offset, as in btf's own log transform
GRASS_CROPS = [(y, x) for y in (0, 64, 192, 320, 384) for x in (0, 64, 192, 320, 384)
               if (y, x) != (192, 192)]  # 128^2 crops of the 512^2 photo off its centre's


def _truth(name: str, seed: int, folder: Path, crop: tuple[int, int] | None,
           renderer: tuple) -> Path:
    """A 128^2 truth store; ``crop``: the bumps' albedo from the grass photo at this offset;
    ``renderer``: more ``btf generate`` options."""
    store = folder / f"{name}_{seed}.zarr"
    if not store.exists():
        if crop is None:
            source = generate_args(name, SIZE, seed, folder)
        else:
            from skimage import data

            from pipeline.images import write_png

            photo = folder / f"grass_{crop[0]}_{crop[1]}.png"
            write_png(photo, data.grass()[crop[0] : crop[0] + SIZE, crop[1] : crop[1] + SIZE])
            source = ["--albedo", photo, "--height", "bumps", "--seed", seed]
        _btf("generate", store, *source, "--sampling", SAMPLING, *renderer)
    return store


def _features(store: Path, kind: str, top: int, ten: np.ndarray) -> np.ndarray:
    """``(H * W, F)`` features of a truth store's photo (its ``top`` light) of one kind."""
    import zarr

    rows = truth_rows(store)
    colour = np.log(rows[..., 3 * top : 3 * top + 3] + EPS)
    lum = colour @ np.array([0.2126, 0.7152, 0.0722])
    if kind == "colour":
        parts = [colour]
    elif kind == "multiscale":
        parts = [colour]
        for sigma in (1, 2, 4, 8):
            blurred = ndi.gaussian_filter(lum, sigma, mode="reflect")
            gy, gx = np.gradient(blurred)
            parts += [blurred[..., None], sigma * gy[..., None], sigma * gx[..., None]]
    elif kind == "patch":
        window = sliding_window_view(np.pad(lum, 2, mode="reflect"), (5, 5))
        parts = [colour, window.reshape(*lum.shape, 25) - lum[..., None]]
    elif kind == "ten":
        parts = [np.log(rows[..., ten] + EPS)]
    else:  # slope
        gy, gx = np.gradient(zarr.open_array(store, path="height", mode="r")[...].astype(float))
        parts = [colour, gy[..., None], gx[..., None]]
    return np.concatenate(parts, axis=-1).reshape(SIZE * SIZE, -1)


def _error(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Eq. (11): the mean over texels of each texel's RMS radiance error."""
    return float(np.mean(np.sqrt(np.mean((estimate - truth) ** 2, axis=1))))


def _random_features(x: np.ndarray, w: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.c_[np.cos(x @ w + b), np.ones(len(x), np.float32)].astype(np.float64)


def _ridge(x: np.ndarray, y: np.ndarray, queries: list[np.ndarray], scale: float,
           rng: np.random.Generator) -> list[np.ndarray]:
    """Ridge regression on random Fourier features of ``x``; predictions at each query set."""
    w = (rng.standard_normal((x.shape[1], FEATURES)) / scale).astype(np.float32)
    b = rng.uniform(0, 2 * np.pi, FEATURES).astype(np.float32)
    gram = np.zeros((FEATURES + 1, FEATURES + 1))
    cross = np.zeros((FEATURES + 1, y.shape[1]))
    for k in range(0, len(x), 32768):
        z = _random_features(x[k : k + 32768], w, b)
        gram += z.T @ z
        cross += z.T @ y[k : k + 32768]
    coef = np.linalg.solve(gram + 1e-2 * np.eye(FEATURES + 1), cross)
    return [_random_features(q, w, b) @ coef for q in queries]


def material(name: str, seeds: list[int], folder: Path, renderer: tuple = (),
             train: int = TRAIN) -> list[dict]:
    """Every case of one material: the bench's figures and each regressor's gap share."""
    import zarr
    from scipy.spatial import cKDTree

    crops = [GRASS_CROPS[i % len(GRASS_CROPS)] if name == "bumps" else None for i in range(train)]
    stores = [_truth(name, 100 + i, folder, crop, renderer) for i, crop in enumerate(crops)]

    theta = zarr.open_array(stores[0], path="theta_light", mode="r")[...]
    top = int(np.argmin(theta))
    mask = np.ones((SIZE, SIZE), bool)
    mask[SIZE // 4 : 3 * SIZE // 4, SIZE // 4 : 3 * SIZE // 4] = False
    rows = []
    for seed in seeds:
        case = Path(tempfile.mkdtemp(prefix="case-", dir=folder))
        start = time.perf_counter()
        args = argparse.Namespace(size=SIZE, rank=16, sets="top", baselines="lookup",
                                  seed=seed, enlarge_options="", sheet=None)
        top_set = _material(name, args, case, renderer)["sets"]["top"]
        rows.append({"case": f"{name}:{seed}", "store": case / "M.zarr",
                     "oracle": top_set["oracle"]["error"],
                     "lookup": top_set["lookup"]["error"],
                     "enlarge": top_set["final"]["error"],
                     "bench_s": round(time.perf_counter() - start, 1)})
    y = np.concatenate([truth_rows(t).reshape(SIZE * SIZE, -1) for t in stores]).astype(float)
    truths = [truth_rows(r["store"])[mask] for r in rows]
    for kind in ("colour", "multiscale", "patch", "ten", "slope"):
        start = time.perf_counter()
        # the ten lights of the first case's seed, as the bench draws them
        others = np.random.default_rng(seeds[0]).choice(
            [i for i in range(len(theta)) if i != top], 9, replace=False)
        ten = np.array([3 * i + c for i in (top, *sorted(others)) for c in range(3)])
        x = np.concatenate([_features(t, kind, top, ten) for t in stores])
        mean, spread = x.mean(0), x.std(0) + 1e-9
        x = ((x - mean) / spread).astype(np.float32)
        queries = [((_features(r["store"], kind, top, ten).reshape(SIZE, SIZE, -1)[mask]
                     - mean) / spread).astype(np.float32) for r in rows]
        best = [np.inf] * len(rows)
        rng = np.random.default_rng(0)
        for scale in SCALES:
            for i, estimate in enumerate(_ridge(x, y, queries, scale, rng)):
                best[i] = min(best[i], _error(estimate, truths[i]))
        if kind == "colour":  # the posterior mean given the colour
            tree = cKDTree(x)
            for i, q in enumerate(queries):
                _, near = tree.query(q, k=NEIGHBOURS)
                rows[i]["colour_mean"] = _error(y[near].mean(axis=1), truths[i])
        for i, r in enumerate(rows):
            r[kind] = best[i]
        print(f"{name} {kind}: {time.perf_counter() - start:.0f} s", file=sys.stderr,
              flush=True)
    out = []
    for r in rows:
        gap = {k: round(gap_share(r[k], r["lookup"], r["oracle"]), 3)
               for k in ("enlarge", "colour_mean", "colour", "multiscale", "patch", "ten",
                         "slope")}
        out.append({"case": r["case"], "oracle": round(r["oracle"], 5),
                    "lookup": round(r["lookup"], 5), "gap": gap, "bench_s": r["bench_s"]})
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.one_photo_floor",
                                     description=__doc__.split("\n\n")[1])
    parser.add_argument("cases", help="material:seed,... (e.g. bumps:1,bumps:2,stone:5)")
    parser.add_argument("options", nargs="?", default="",
                        help="more btf generate options for every truth")
    parser.add_argument("--train", type=int, default=TRAIN, metavar="N",
                        help=f"truths of other seeds to train on (default {TRAIN})")
    args = parser.parse_args(argv)
    cases: dict[str, list[int]] = {}
    for name, seed in material_seeds(args.cases):
        cases.setdefault(name, []).append(seed)
    folder = Path(tempfile.mkdtemp(prefix="btf-one-photo-floor-"))
    try:
        for name, seeds in cases.items():
            for row in material(name, seeds, folder, tuple(args.options.split()), args.train):
                print(json.dumps(row), flush=True)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
