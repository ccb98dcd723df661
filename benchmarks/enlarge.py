"""Enlargement against ground truth: eq. (11) error per phase, baselines and Eref (paper 000).

The experiment of the paper's section 4 (Fig. 3), on generated materials whose ground truth
``M`` is known: the sample ``S`` is the central half of ``M`` (compressed at ``--rank``), the
constraint photos ``C`` are layers of ``M`` at full size, in the paper's three sets:

- **top**: the light closest to the normal (one photo);
- **random**: that and 9 more lights drawn at random (seeded): ten photos;
- **mean**: the mean colour image (the mean over all lights, eq. 10).

For every material and set, the average ABRDF RMSE of eq. (11), in linear radiance, over the
texels outside the sample, of (1) Texture Optimization alone, (2) after the first statistical
synthesis, (3) the result after the QP rounds (``btf enlarge --keep-phases``); next to ``Eref``
(``M`` itself compressed at the same rank) and baselines measured in the same run:

- **tiling**: ``S`` repeated periodically, aligned with its place in ``M``;
- **quilt**: ``btf quilt`` of ``S`` (one periodic texture of the target's size, unconstrained);
- **roller**: ``btf roller`` of ``S`` laid over the target (only where ``S`` is periodic);
- **lookup**: every target texel takes the ABRDF of the sample texel whose constraint values
  are nearest (a k-d tree on the log constraint values; no neighbourhoods).

"C residual" is the RMS of the reconstructed constraint layers against the photos C over the
target (log domain, the QP's ``A x - b``); "S residual" is the same for the sample against its
own constraint layers, i.e. the sample's compression error on them: the issue's target is C
residual within S residual. Times per phase come from the enlarged store's attrs. ``--sheet
FILE`` draws ground truth, result and baselines side by side for a few lights of the first
material.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import btf_executable, git_revision, machine, measure
from tasks.constrained_blend import sample_covariance
from tasks.evaluation import abrdf_error, gap_share, lookup_baseline, oracle, tiling_baseline
from tasks.realism import log_luminance, realism
from tasks.transform import Transform

SUITE = "enlarge"
SAMPLING = "abtf:12,4"
SETS = ("top", "random", "mean")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the suite."""
    parser.add_argument("--materials", default="wood,leather,fabric,brick",
                        help="generated materials; 'brick' is a photo (skimage's brick) used "
                             "with --albedo")
    parser.add_argument("--size", type=int, default=256, help="target side (the sample is half)")
    parser.add_argument("--rank", type=int, default=32)
    parser.add_argument("--sets", default=",".join(SETS), help="constraint sets: top, random, "
                                                               "mean")
    parser.add_argument("--baselines", default="tiling,quilt,roller,lookup")
    parser.add_argument("--enlarge-options", default="",
                        help="extra btf enlarge options, given with '=' since they start with "
                             "'-': --enlarge-options='--patch 8 --beta 1'")
    parser.add_argument("--sheet", metavar="PNG", help="contact sheet of the first material")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--scaling", metavar="N,..", default="",
                        help="also time btf enlarge --tile 512 of a 128^2 sample (rank 32, 12 "
                             "lights) to targets of these sides, in fresh processes (wall time "
                             "and peak memory), e.g. 256,1024,4096")
    parser.add_argument("--scaling-options", default="",
                        help="btf enlarge options of the scaling runs (with '=', as above)")
    parser.add_argument("--tile-seams", type=int, default=0, metavar="N",
                        help="also measure the tile borders of btf enlarge --tile 128 "
                             "(wood 256^2, rank 16) for N seeds, each on its own "
                             "(benchmarks/seams.py; 0: not)")
    parser.add_argument("--tile-seams-only", action="store_true",
                        help="measure the tile borders only (with --tile-seams, default 20)")
    parser.add_argument("--timing-rank", type=int, default=64,
                        help="rank of the timing run (wood 128^2 -> 256^2, one photo; 0: none)")


def _btf(*args) -> None:
    from pipeline.cli import main

    code = main([str(a) for a in args] + ["--quiet"])
    if code != 0:
        raise RuntimeError(f"btf {' '.join(map(str, args))} failed with status {code}")


def _factors(path: Path):
    import zarr

    g = zarr.open_group(path, mode="r")
    return (np.asarray(g["U"][...], np.float64), np.asarray(g["S"][...], np.float64),
            np.asarray(g["V"][...], np.float32), Transform.from_attrs(g.attrs["transform"]), g)


def truth_rows(path: Path) -> np.ndarray:
    """``(H, W, rows)`` radiance of a store, rows in BTF-matrix order (view, light, channel)."""
    import zarr

    rad = zarr.open_array(path, path="radiance", mode="r")[...]
    nv, nl, h, w, nc = rad.shape
    return np.moveaxis(rad, (0, 1), (2, 3)).reshape(h, w, nv * nl * nc)


PHOTO_MATERIALS = {  # a bench material from a photo that ships with scikit-image
    "brick": ("brick", ()),  # the photo's lightness as its relief
    "bumps": ("grass", ("--height", "bumps")),  # smooth bumps of two scales, its albedo grass
}


def _photo(tmp: Path, name: str = "brick") -> Path:
    from skimage import data

    from pipeline.images import write_png

    path = tmp / f"{name}.png"
    write_png(path, getattr(data, name)())
    return path


def material_seeds(text: str) -> list[tuple[str, int]]:
    """``material:seed,...`` (the studies' cases) as pairs, or ValueError naming the bad one."""
    pairs = []
    for item in text.split(","):
        name, _, seed = item.partition(":")
        if not seed.lstrip("-").isdigit():
            raise ValueError(f"{item!r}: expected material:seed, e.g. stone:5")
        pairs.append((name, int(seed)))
    return pairs


def generate_args(name: str, size: int, seed: int, tmp: Path) -> list:
    """``btf generate``'s source options for a bench material (procedural or photo)."""
    if name in PHOTO_MATERIALS:
        photo, extra = PHOTO_MATERIALS[name]
        seeded = ("--seed", seed) if "bumps" in extra else ()  # a photo's own relief has none
        return ["--albedo", _photo(tmp, photo), "--size", size, *extra, *seeded]
    return ["--material", name, "--size", size, "--seed", seed]


def _mean_colour_store(source: Path, out: Path) -> Path:
    """A one-layer store holding the mean over the lights of view 0 (eq. 10)."""
    import zarr

    from pipeline.stores.base import Directions
    from pipeline.stores.radiance import Layout, create_radiance_store

    rad = zarr.open_array(source, path="radiance", mode="r")
    mean = rad[0].mean(axis=0, dtype=np.float64).astype(np.float32)
    d = Directions(np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1))
    group = create_radiance_store(out, directions=d, ny=mean.shape[0], nx=mean.shape[1],
                                  channels=("R", "G", "B"), layout=Layout(),
                                  attrs={"source": "mean colour of view 0"})
    group["radiance"][0, 0] = mean
    return out


def _log_layers(path: Path, transform: Transform) -> np.ndarray:
    """All layers of a store in the log domain, ``(H, W, layers * channels)``."""
    return transform.encode(truth_rows(path))  # generated stores: the log transform, per value


REALISM_LIGHTS = 8  # lights (evenly spaced) whose layers the realism figure averages


def _picks(truth: np.ndarray, channels: int = 3) -> np.ndarray:
    return np.linspace(0, truth.shape[-1] // channels - 1, REALISM_LIGHTS).astype(int)


def _light_rows(picks) -> np.ndarray:
    """BTF-matrix rows (view 0) of the picked lights' three channels."""
    return np.concatenate([np.arange(3 * li, 3 * li + 3) for li in picks])


def _layers(u: np.ndarray, coef: np.ndarray, transform: Transform, picks) -> np.ndarray:
    """Linear radiance ``(H, W, len(picks) * 3)`` of the picked lights (view 0)."""
    from tasks.svd import reconstruct

    flat = coef.reshape(-1, coef.shape[-1])
    return reconstruct(u[_light_rows(picks)], np.ones(u.shape[1]), flat,
                       transform=transform).T.reshape(*coef.shape[:2], -1)


def _realism(approx: np.ndarray, truth: np.ndarray, picks) -> float:
    """Mean over the picked lights of :func:`tasks.realism.realism` of the log luminance.

    ``approx``: ``(H, W, len(picks) * 3)``; ``truth``: every light's rows.
    """
    h, w = approx.shape[:2]
    ours = log_luminance(approx.reshape(h, w, -1, 3))
    real = log_luminance(truth[..., _light_rows(picks)].reshape(h, w, -1, 3))
    return float(np.mean([realism(ours[..., k], real[..., k]) for k in range(len(picks))]))


def _scored(u, coef, transform, truth, mask) -> dict:
    """Eq. (11) error outside the sample and realism of one result."""
    picks = _picks(truth)
    return {"error": abrdf_error(u, coef, transform, truth, mask),
            "realism": _realism(_layers(u, coef, transform, picks), truth, picks)}


def _baselines(names, tmp, sample_svd, size, origin, truth, mask, u, coef_s, transform) -> dict:
    out = {}
    if "tiling" in names:
        out["tiling"] = _scored(u, tiling_baseline(coef_s, (size, size), origin), transform, truth,
                                mask)
    if "quilt" in names:
        from pipeline.cli import main

        step = 32 - 8
        tile = -(-size // step) * step
        out["quilt"] = None  # every seed refused by the border check (issue 23): n/a
        for seed in (1, 2, 3):
            if main(["quilt", str(sample_svd), str(tmp / "q.zarr"), "--size", f"{tile},{tile}",
                     "--seed", str(seed), "--quiet", "--overwrite"]) == 0:
                uq, sq, _, _, g = _factors(tmp / "q.zarr")
                coef = np.asarray(g["V"][0], np.float32)[:size, :size] * sq.astype(np.float32)
                out["quilt"] = _scored(uq.reshape(-1, len(sq)), coef, transform, truth, mask)
                break
    if "roller" in names:
        from pipeline.cli import main

        if main(["roller", str(sample_svd), str(tmp / "r.zarr"), "--quiet"]) != 0:
            out["roller"] = None  # not periodic: the roller refuses
        else:
            out["roller"] = _roller_scored(tmp / "r.zarr", size, truth, mask)
    return out


def _roller_scored(path: Path, size: int, truth, mask) -> dict:
    import zarr

    from pipeline.graphs.surface import lazy_layer

    g = zarr.open_group(path, mode="r")
    nv, nl = g["theta_view"].shape[0], g["theta_light"].shape[0]
    layers = np.stack([lazy_layer(path, view=v, light=li, size=(size, size)).compute(
        scheduler="synchronous") for v in range(nv) for li in range(nl)], axis=2)
    approx = layers.reshape(size, size, -1)
    err = np.sqrt(np.mean((approx - truth) ** 2, axis=-1))
    picks = _picks(truth)
    return {"error": float(np.mean(err[mask])),
            "realism": _realism(approx[..., _light_rows(picks)], truth, picks)}


def _constraint_rows(info: dict, us: np.ndarray, coef_s: np.ndarray) -> tuple[np.ndarray,
                                                                              np.ndarray]:
    """The QP's rows ``(G, K)`` and offsets ``(G,)`` of an enlargement, from its attrs."""
    from tasks.enlargement import mean_colour_rows

    rows, offsets = [], []
    for layer in info["constraint_layers"]:
        if layer["kind"] == "mean colour":
            r, offset, _ = mean_colour_rows(us[layer["sample_view"]], coef_s)
            rows.append(r)
            offsets.append(offset)
        else:
            r = us[layer["sample_view"], layer["sample_light"]]
            rows.append(r)
            offsets.append(np.zeros(len(r)))
    return np.concatenate(rows).astype(np.float64), np.concatenate(offsets)


def _material(name: str, args, tmp: Path, generate: tuple | None = ()) -> dict:
    """One material's row; ``generate``: more ``btf generate`` options (a renderer), or None
    to use the ``M.zarr`` already in ``tmp``."""
    size, half = args.size, args.size // 2
    origin = ((size - half) // 2, (size - half) // 2)
    m = tmp / "M.zarr"
    if generate is not None:  # None: M.zarr is there already (the same truth, another run)
        _btf("generate", m, *generate_args(name, size, args.seed, tmp), "--sampling", SAMPLING,
             *generate)
    _btf("crop", m, tmp / "S.zarr", "--region",
         f"{origin[0]}:{origin[0] + half},{origin[1]}:{origin[1] + half}")
    _btf("compress", tmp / "S.zarr", tmp / "S_svd.zarr", "--rank", args.rank)
    _btf("compress", m, tmp / "M_svd.zarr", "--rank", args.rank)
    truth = truth_rows(m)
    mask = np.ones((size, size), bool)
    mask[origin[0] : origin[0] + half, origin[1] : origin[1] + half] = False
    us, ss, vs, transform, sample_group = _factors(tmp / "S_svd.zarr")
    um, sm, vm, _, _ = _factors(tmp / "M_svd.zarr")
    rows, rank = us.shape[0] * us.shape[1] * us.shape[2], len(ss)
    u = us.reshape(rows, rank)
    coef_s = vs * ss.astype(np.float32)
    result = {"material": name, "eref": abrdf_error(um.reshape(rows, rank),
                                                    vm * sm.astype(np.float32), transform, truth,
                                                    mask)}
    copy, _ = oracle(u, coef_s, transform, truth)
    result["oracle_copy"] = _scored(u, copy, transform, truth, mask)
    baselines = [b for b in args.baselines.split(",") if b]
    result["baselines"] = _baselines(baselines, tmp, tmp / "S_svd.zarr", size, origin, truth,
                                     mask, u, coef_s, transform)
    import zarr

    theta = zarr.open_group(m, mode="r")["theta_light"][...]
    top = int(np.argmin(theta))
    rng = np.random.default_rng(args.seed)
    others = rng.choice([i for i in range(len(theta)) if i != top], 9, replace=False)
    result["sets"] = {}
    for which in args.sets.split(","):
        c = tmp / f"C_{which}.zarr"
        if which == "mean":
            _mean_colour_store(m, c)
            extra = ["--mean-colour", "0"]
        else:
            lights = [top] if which == "top" else [top, *sorted(int(i) for i in others)]
            _btf("crop", m, c, "--light", ",".join(map(str, lights)))
            extra = []
        out = tmp / f"E_{which}.zarr"
        start = time.perf_counter()
        _btf("enlarge", tmp / "S_svd.zarr", c, out, "--keep-phases", *extra,
             *args.enlarge_options.split())
        wall = time.perf_counter() - start
        ue, se, ve, _, g = _factors(out)
        ue = ue.reshape(rows, rank)
        info = dict(g.attrs["enlargement"])
        row = {"to": _scored(ue, np.asarray(g["phase_texture_optimization"][...]), transform, truth,
                             mask),
               "stats": _scored(ue, np.asarray(g["phase_statistics"][...]), transform, truth, mask)
               if "phase_statistics" in g.array_keys() else None,
               "final": _scored(ue, ve * se.astype(np.float32), transform, truth, mask),
               "seconds": info["seconds"], "wall": wall, "rounds": info["rounds"],
               "residual": info["constraint_residual_rms"],
               "sample_residual": info["sample_constraint_residual_rms"],
               "lambda": info["lambda"],
               "placement": info["placement"]}
        keys = _log_layers(c, transform)
        sample_keys = keys[origin[0] : origin[0] + half, origin[1] : origin[1] + half]
        if "lookup" in baselines:
            row["lookup"] = _scored(u, lookup_baseline(coef_s, sample_keys, keys), transform, truth,
                                    mask)
        qp_rows, offsets = _constraint_rows(info, us, coef_s)
        # the copy through the paper's QP and through the sample-metric one: the lower is
        # the best achievable (the same oracle for results of either QP)
        best = None
        for metric in ("plain", "sample"):  # either way, whichever QP the result used
            _, constrained = oracle(
                u, coef_s, transform, truth, rows=qp_rows, values=keys - offsets,
                noise=info["sample_constraint_residual_rms"],
                metric=sample_covariance(coef_s) if metric == "sample" else None)
            scored = {**_scored(u, constrained, transform, truth, mask), "qp": metric}
            if best is None or (scored["error"], metric) < (best["error"], best["qp"]):
                best = scored
        row["oracle"] = best
        result["sets"][which] = row
        if args.sheet and not getattr(args, "_sheet_done", False) and which == "top":
            _sheet(args.sheet, name, truth, u, ue, ve * se.astype(np.float32), coef_s, origin,
                   size, transform, (sample_keys, keys) if "lookup" in baselines else None)
            args._sheet_done = True
    del sample_group
    return result


def _sheet(path, name, truth, u, ue, coef, coef_s, origin, size, transform, lookup) -> None:
    """Ground truth, result, lookup and tiling, for three lights, side by side."""
    from matplotlib.figure import Figure

    from tasks.svd import reconstruct
    from tasks.tonemap import exposure, tonemap

    channels = 3
    lights = truth.shape[-1] // channels
    picks = [0, lights // 3, 2 * lights // 3]
    h = coef_s.shape[0]
    reps = -(-size // h) + 1
    shift = (h - origin[0] % h) % h, (h - origin[1] % h) % h
    tiled = np.tile(coef_s, (reps, reps, 1))[shift[0] : shift[0] + size, shift[1] : shift[1] + size]
    columns = [("ground truth", None, None), ("enlarged", ue, coef), ("tiling", u, tiled)]
    if lookup is not None:
        columns.insert(2, ("lookup", u, lookup_baseline(coef_s, *lookup)))
    fig = Figure(figsize=(2.4 * len(columns), 2.5 * len(picks)), layout="constrained")
    scale = exposure(truth[::4, ::4])
    for r, light in enumerate(picks):
        rows = slice(light * channels, (light + 1) * channels)
        for c, (title, basis, coefficients) in enumerate(columns):
            if basis is None:
                image = truth[..., rows]
            else:
                image = reconstruct(basis[rows], np.ones(basis.shape[1]),
                                    coefficients.reshape(-1, coefficients.shape[-1]),
                                    transform=transform).T.reshape(size, size, channels)
            ax = fig.add_subplot(len(picks), len(columns), r * len(columns) + c + 1)
            ax.imshow(tonemap(image, scale=scale), interpolation="nearest")
            ax.set_axis_off()
            if r == 0:
                ax.set_title(title, fontsize=9)
    fig.suptitle(f"{name}: sample = central half; one constraint photo (top light)",
                 fontsize=10)
    fig.savefig(path, format="png", dpi=80)


def _timing(args, tmp: Path) -> dict:
    """Wood 128^2 -> 256^2 at ``--timing-rank`` with one photo: time per phase, wall time."""
    m = tmp / "M.zarr"
    _btf("generate", m, "--material", "wood", "--size", 256, "--sampling", SAMPLING, "--seed",
         args.seed)
    _btf("crop", m, tmp / "S.zarr", "--region", "64:192,64:192")
    _btf("compress", tmp / "S.zarr", tmp / "S_svd.zarr", "--rank", args.timing_rank)
    _btf("crop", m, tmp / "C.zarr", "--light", 3)
    took = measure([btf_executable(), "enlarge", str(tmp / "S_svd.zarr"), str(tmp / "C.zarr"),
                    str(tmp / "E.zarr"), "--quiet", *args.enlarge_options.split()])
    import zarr

    info = zarr.open_group(tmp / "E.zarr", mode="r").attrs["enlargement"]
    return {"rank": args.timing_rank, "wall": took.seconds, "peak_rss": took.peak_rss,
            "seconds": info["seconds"]}


def _scaling(args, tmp: Path) -> list[dict]:
    """``btf enlarge --tile 512`` of one 128^2 sample to targets of growing sides.

    Each result is also scored against its ground truth: eq. (11) error and realism on the
    four corner windows of 256^2 (:func:`_corner_scores`).
    """
    rows = []
    for side in [int(n) for n in args.scaling.split(",") if n]:
        m = tmp / f"M{side}.zarr"
        _btf("generate", m, "--material", "wood", "--size", side, "--sampling", "abtf:12,1",
             "--seed", args.seed, "--chunk", 256)
        if not (tmp / "S_svd.zarr").exists():  # one sample for all: the centre of the first
            o = (side - 128) // 2
            _btf("crop", m, tmp / "S.zarr", "--region", f"{o}:{o + 128},{o}:{o + 128}")
            _btf("compress", tmp / "S.zarr", tmp / "S_svd.zarr", "--rank", 32)
        _btf("crop", m, tmp / f"C{side}.zarr", "--light", 0)
        took = measure([btf_executable(), "enlarge", str(tmp / "S_svd.zarr"),
                        str(tmp / f"C{side}.zarr"), str(tmp / f"E{side}.zarr"), "--tile", "512",
                        "--quiet", *args.scaling_options.split()])
        rows.append({"side": side, "texels": side * side, "seconds": took.seconds,
                     "peak_rss": took.peak_rss, **_corner_scores(m, tmp / f"E{side}.zarr")})
        for name in (f"E{side}.zarr", f"C{side}.zarr", f"M{side}.zarr"):
            shutil.rmtree(tmp / name)
    return rows


def _corner_scores(truth_store: Path, result: Path, window: int = 256) -> dict:
    """Eq. (11) error and realism of ``result`` on the four corner windows of its truth.

    For targets up to twice the window the windows overlap the sample (at 256^2 each is the
    whole target).
    """
    import zarr

    radiance = zarr.open_array(truth_store, path="radiance", mode="r")
    g = zarr.open_group(result, mode="r")
    s = np.asarray(g["S"][...], np.float64)
    u = np.asarray(g["U"][...], np.float64).reshape(-1, len(s))
    v, transform = g["V"], Transform.from_attrs(g.attrs["transform"])  # windows read one at a time
    side = radiance.shape[2]
    window = min(window, side)
    errors, real = [], []
    for y in (0, side - window):
        for x in (0, side - window):
            t = np.moveaxis(radiance[:, :, y : y + window, x : x + window], (0, 1), (2, 3))
            t = t.reshape(window, window, -1)
            c = np.asarray(v[y : y + window, x : x + window]) * s.astype(np.float32)
            scored = _scored(u, c, transform, t, np.ones((window, window), bool))
            errors.append(scored["error"])
            real.append(scored["realism"])
    return {"error": float(np.mean(errors)), "realism": float(np.mean(real))}


def run(args: argparse.Namespace) -> dict:
    """Every material and constraint set (see the module), the timing and scaling runs."""
    tmp = Path(tempfile.mkdtemp(prefix="btf-bench-enlarge-"))
    try:
        tile_seams = _tile_seams(args, tmp)
        if args.tile_seams_only:
            return {"suite": SUITE, "tile_seams": tile_seams, "machine": machine(),
                    "revision": git_revision()}
        materials = []
        for name in [m for m in args.materials.split(",") if m]:
            folder = tmp / name
            folder.mkdir()
            materials.append(_material(name, args, folder))
        timing = None
        if args.timing_rank:
            (tmp / "timing").mkdir()
            timing = _timing(args, tmp / "timing")
        (tmp / "scaling").mkdir()
        scaling = _scaling(args, tmp / "scaling")
        return {"suite": SUITE, "size": args.size, "sample": args.size // 2, "rank": args.rank,
                "sampling": SAMPLING, "enlarge_options": args.enlarge_options,
                "materials": materials, "timing": timing, "scaling": scaling,
                "scaling_options": args.scaling_options, "tile_seams": tile_seams,
                "machine": machine(), "revision": git_revision()}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


TILE_SEAMS_SAMPLING = "abtf:6,4"


def enlarge_tile_seams(seeds, *, tmp, material: str = "wood", size: int = 256,
                       tile: int = 128, rank: int = 16, log=None) -> dict:
    """Tile borders of a tiled enlargement (``btf enlarge --tile``), seed by seed.

    A generated ``material`` of ``size^2`` texels (24 lights) stands for the truth; its central
    half, compressed at ``rank``, is the sample, and its light closest to the normal the photo.
    Each seed enlarges with ``--tile tile --seed S``; three lights of the result (log
    luminance, one channel each) are measured along the tile grid's inner lines against the
    tiles' insides, with the reach of the tiles' blend (their halo) and the sample's same
    three layers as exemplar (:func:`tasks.seams.border_figures`).
    """
    import zarr

    from benchmarks.seams import summary
    from pipeline.graphs.enlarge import HALO
    from tasks.seams import Borders, PatchExemplar, border_figures
    from tasks.svd import reconstruct_layers

    m, sample, svd, photo = (tmp / n for n in ("M.zarr", "S.zarr", "S_svd.zarr", "C.zarr"))
    half, origin = size // 2, size // 4
    _btf("generate", m, "--material", material, "--size", size, "--sampling", TILE_SEAMS_SAMPLING,
         "--seed", 1)
    _btf("crop", m, sample, "--region", f"{origin}:{origin + half},{origin}:{origin + half}")
    _btf("compress", sample, svd, "--rank", rank)
    theta = zarr.open_group(m, mode="r")["theta_light"][...]
    _btf("crop", m, photo, "--light", int(np.argmin(theta)))
    lights = np.linspace(0, len(theta) - 1, 3).astype(int)

    def lights_last(radiance: np.ndarray) -> np.ndarray:  # (lights, h, w, 3) -> (h, w, 3)
        return np.moveaxis(log_luminance(radiance), 0, -1)

    exemplar = PatchExemplar(lights_last(zarr.open_array(sample, path="radiance",
                                                           mode="r")[0, lights]))
    borders = Borders(tuple(range(tile, size, tile)), tuple(range(tile, size, tile)))
    rows = []
    for seed in seeds:
        out = tmp / f"E{seed}.zarr"
        start = time.perf_counter()
        _btf("enlarge", svd, photo, out, "--tile", tile, "--seed", seed, "--overwrite")
        seconds = time.perf_counter() - start
        u, s, v, transform, _ = _factors(out)
        image = lights_last(np.stack([reconstruct_layers(u[0, li], s, v, transform=transform)
                                      for li in lights]))
        f = border_figures(exemplar, image, borders, reach=HALO * 4)
        rows.append({"seed": seed, "failed": None, "seam": f.worst_seam,
                     "structure": f.worst_structure, "worst": f.worst_line(),
                     "seconds": seconds})
        shutil.rmtree(out)
        if log is not None:
            log(f"enlarge --tile {tile} seed {seed}: seam {f.worst_seam:.2f} structure "
                f"{f.worst_structure:.2f} ({f.worst_line()}), {seconds:.1f} s")
    return {"material": material, "size": size, "tile": tile, "rank": rank, "seeds": rows,
            **summary(rows, keys=("seam", "structure", "seconds"))}


def _tile_seams(args, tmp: Path) -> dict | None:
    import sys

    seeds = args.tile_seams or (20 if args.tile_seams_only else 0)
    if not seeds:
        return None
    (tmp / "tile_seams").mkdir()
    return enlarge_tile_seams(range(seeds), tmp=tmp / "tile_seams",
                              log=lambda m: print(m, file=sys.stderr))


def tile_seams_report(t: dict | None) -> list[str]:
    """The per-seed tile-border table."""
    if not t:
        return []

    def cell(key):
        s = t[key]
        return f"{s['worst']:.2f} (seed {s['worst_seed']}) | {s['median']:.2f}"

    return ["", f"Tile borders of `btf enlarge --tile {t['tile']}` ({t['material']} "
                f"{t['size']}^2 from its central half at rank {t['rank']}, one photo), "
                f"{len(t['seeds'])} seeds each measured on its own (`benchmarks/seams.py`: "
                "three lights' log luminance; 1.00 = as good as the tiles' insides):", "",
            "| measure | worst | median |", "|---|---|---|",
            f"| seam across the tile grid | {cell('seam')} |",
            f"| structure along it | {cell('structure')} |",
            f"| enlarge seconds | {cell('seconds')} |"]


def _num(x, key: str = "error") -> str:
    if isinstance(x, dict):
        x = x[key]
    return "n/a" if x is None else f"{x:.4f}" if key == "error" else f"{x:.2f}"


COLUMNS = ("to", "stats", "final")
BASELINES = ("lookup", "tiling", "quilt", "roller")


def _cells(m: dict, row: dict) -> dict:
    """Every column and baseline of one row, by name (None where not run)."""
    return {**{k: row.get(k) for k in (*COLUMNS, "lookup", "oracle")},
            **{k: m["baselines"].get(k) for k in BASELINES if k != "lookup"},
            "copy": m.get("oracle_copy")}


def _gap(cell, row) -> str:
    if cell is None or row.get("lookup") is None:
        return "n/a"
    return f"{gap_share(cell['error'], row['lookup']['error'], row['oracle']['error']):.2f}"


def summary(result: dict) -> dict:
    """Rows where column (3) is below every baseline, and the worst gap share left."""
    below, gaps, total = 0, [], 0
    for m in result["materials"]:
        for row in m["sets"].values():
            cells = _cells(m, row)
            others = [cells[k]["error"] for k in BASELINES if cells.get(k)]
            total += 1
            below += all(row["final"]["error"] < e for e in others)
            if row.get("lookup"):
                gaps.append(gap_share(row["final"]["error"], row["lookup"]["error"],
                                      row["oracle"]["error"]))
    return {"rows": total, "below_every_baseline": below,
            "worst_gap": max(gaps) if gaps else None,
            "median_gap": float(np.median(gaps)) if gaps else None}


def report(result: dict) -> str:
    """Markdown tables for BENCHMARKS.md."""
    if "materials" not in result:
        return "\n".join(tile_seams_report(result["tile_seams"])).strip()
    options = f", {result['enlarge_options']}" if result["enlarge_options"] else ""
    lines = [f"Enlargement of the central {result['sample']}^2 of a {result['size']}^2 "
             f"ground truth ({result['sampling']}, rank {result['rank']}{options}).", "",
             "Error: eq. (11) ABRDF RMSE outside the sample (linear radiance; lower is better). "
             "Oracle: each texel copies the sample ABRDF nearest to the truth's (copy), then "
             "the same QP as (3). Gap: (E - oracle) / (lookup - oracle), the share of the gap "
             "to the best achievable that is left (0 = oracle, 1 = lookup).", "",
             "| material | set | Eref | copy | oracle | (1) TO | (2) + stats | (3) final | "
             "lookup | tiling | quilt | roller | gap (1) | gap (3) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for m in result["materials"]:
        for which, row in m["sets"].items():
            c = _cells(m, row)
            lines.append(
                f"| {m['material']} | {which} | {_num(m['eref'])} | {_num(c['copy'])} | "
                f"{_num(c['oracle'])} | {_num(c['to'])} | {_num(c['stats'])} | "
                f"{_num(c['final'])} | {_num(c['lookup'])} | {_num(c['tiling'])} | "
                f"{_num(c['quilt'])} | {_num(c['roller'])} | {_gap(c['to'], row)} | "
                f"{_gap(c['final'], row)} |")
    lines += ["", "Realism: statistics distance from the truth over the truth's own "
                  "(`tasks/realism.py`, log luminance of 8 lights; 1 = as alike as two halves "
                  "of the truth; lower is better).", "",
              "| material | set | copy | oracle | (1) TO | (2) + stats | (3) final | lookup | "
              "tiling | quilt | roller |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for m in result["materials"]:
        for which, row in m["sets"].items():
            c = _cells(m, row)
            lines.append(f"| {m['material']} | {which} | " + " | ".join(
                _num(c[k], "realism") for k in ("copy", "oracle", "to", "stats", "final",
                                                "lookup", "tiling", "quilt", "roller")) + " |")
    lines += ["", "| material | set | TO s | stats s | QP s | rounds | C residual | "
                  "S residual |", "|---|---|---|---|---|---|---|---|"]
    for m in result["materials"]:
        for which, row in m["sets"].items():
            s = row["seconds"]
            lines.append(f"| {m['material']} | {which} | {s['texture_optimization']:.1f} | "
                         f"{s['statistics']:.1f} | {s['qp']:.2f} | {row['rounds']} | "
                         f"{_num(row.get('residual'))} | {_num(row.get('sample_residual'))} |")
    sm = summary(result)
    if sm["worst_gap"] is not None:
        lines += ["", f"(3) is below every baseline in {sm['below_every_baseline']} of "
                      f"{sm['rows']} rows; gap left: median {sm['median_gap']:.2f}, worst "
                      f"{sm['worst_gap']:.2f}."]
    t = result.get("timing")
    if t:
        lines += ["", f"Wood 128^2 -> 256^2 at rank {t['rank']}, one photo: {t['wall']:.1f} s "
                      f"wall in a fresh process (peak {t['peak_rss'] / 2**20:.0f} MiB); "
                      + ", ".join(f"{k.replace('_', ' ')} {v:.1f} s"
                                  for k, v in t["seconds"].items())]
    if result.get("scaling"):
        base = result["scaling"][0]
        lines += ["", f"Scaling: a 128^2 sample (rank 32, 12 lights) to larger targets, "
                      f"btf enlarge --tile 512 {result['scaling_options']} in a fresh process.",
                  "", "| target | texels | wall s | s per Mtexel | vs first | peak RSS MiB | "
                      "error | realism |", "|---|---|---|---|---|---|---|---|"]
        for row in result["scaling"]:
            per = row["seconds"] / row["texels"] * 2**20
            first = base["seconds"] / base["texels"] * 2**20
            lines.append(f"| {row['side']}^2 | {row['texels']} | {row['seconds']:.1f} | "
                         f"{per:.1f} | {per / first:.2f} | {row['peak_rss'] / 2**20:.0f} | "
                         f"{_num(row.get('error'))} | {_num(row.get('realism'), 'realism')} |")
    return "\n".join(lines + tile_seams_report(result.get("tile_seams")))
