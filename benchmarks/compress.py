"""Compression: ``btf compress`` against dask's and scikit-learn's randomized SVDs.

One run, one stored matrix, the same rank K, oversampling P and power iterations Q, dask's
threaded scheduler everywhere:

- wall time and peak RSS of ``btf compress``, of ``dask.array.linalg.svd_compressed`` (its default
  ``power`` iterator and ``iterator="QR"``) on the same range-reduced matrix read from the same
  store, and of ``sklearn.utils.extmath.randomized_svd`` on the matrix in memory (if sklearn is
  installed and the matrix fits);
- the machine bound of ``btf compress``: for every pass, one plain dask read pass of the store
  plus the same pass's matrix products on in-memory blocks, both measured in this run;
- error relative to the optimal rank-K error, on a smaller store where numpy's exact SVD is
  feasible (every method run again there);
- a scaling table: time and peak memory of ``btf compress`` for growing stores, in the default
  mode and in one pass (``--passes 1``);
- a texel scaling table: the same at equal rows for growing textures, with the sketches on the
  row side (the default for such stores), in one pass, and, where it fits, on the texel side;
- a sketch-size table of the one pass: error relative to the optimal rank-K error on the small
  store, the error it reports, time and scratch, for range sketches of k = c K + 1 columns.

Stores are generated once into ``--data-dir`` and reused by later runs.
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import (
    best_of,
    btf_executable,
    drop_page_cache,
    generate_store,
    machine,
    measure,
    store_bytes,
)

SUITE = "compress"
EPS = 1e-3


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the suite."""
    parser.add_argument("--material", default="leather")
    parser.add_argument("--size", type=int, default=256, help="texels per side (default 256)")
    parser.add_argument("--sampling", default="hemi:82",
                        help="sampling of the timed store (default hemi:82: 20172 x 65536, "
                             "5.3 GB of float32)")
    parser.add_argument("--small", default="64,hemi:24",
                        help="SIZE,SAMPLING of the store for errors against an exact SVD")
    parser.add_argument("--rank", type=int, default=64)
    parser.add_argument("--oversample", type=int, default=10)
    parser.add_argument("--power-iters", type=int, default=2)
    parser.add_argument("--scaling", default="1,2,4,8",
                        help="approximate input sizes in GB for the scaling table ('' to skip)")
    parser.add_argument("--texel-scaling", default="512,1024,2048,4096",
                        help="texels per side for the texel scaling table ('' to skip)")
    parser.add_argument("--texel-sampling", default="abtf:12,4",
                        help="sampling (hence rows) of the texel scaling stores")
    parser.add_argument("--texel-side-up-to", type=int, default=1024,
                        help="largest size also run with --sketch texels (its client memory "
                             "grows with the texels)")
    parser.add_argument("--sketch-multiples", default="2,3,4,6,8",
                        help="range sketch sizes k = c K + 1 of the sketch-size table")
    parser.add_argument("--parts", default="timed,errors,sketch,scaling,texels",
                        help="which tables to measure (comma-separated; also 'disk', not run "
                             "by default: a store larger than memory, see --disk-gigabytes)")
    parser.add_argument("--disk-gigabytes", type=float, default=0.0,
                        help="disk part: the store's float32 size in GB (default 0: 1.5x this "
                             "machine's memory, e.g. 36 GB on 24 GiB: minutes to generate and "
                             "about 1.2x that on disk)")
    parser.add_argument("--disk-size", type=int, default=512,
                        help="disk part: texels per side of the large store (its sampling is "
                             "the hemi:N that reaches --disk-gigabytes)")
    parser.add_argument("--disk-small-size", type=int, default=128,
                        help="disk part: texels per side of the same material and sampling "
                             "compressed for comparison (it fits memory)")
    parser.add_argument("--repeat", type=int, default=3,
                        help="runs of btf compress and of the bound's parts, interleaved so "
                             "that both see the same machine (best kept; default 3); other "
                             "methods run once")
    parser.add_argument("--methods", default="btf,dask-power,dask-qr,sklearn",
                        help="methods to time and compare (comma-separated)")
    parser.add_argument("--data-dir", default=str(Path(tempfile.gettempdir()) / "btf-bench"),
                        help="where generated stores are kept between runs")


def ensure_store(data: Path, material: str, size: int, sampling: str) -> Path:
    """A generated store, made once and reused."""
    path = data / f"{material}-{size}-{sampling.replace(':', '').replace(',', 'x')}.zarr"
    if not (path / "zarr.json").is_file():
        generate_store(path, material, size, sampling)
    return path


def matrix_shape(store: Path) -> tuple[int, int]:
    """Rows and columns of a store's BTF matrix."""
    import zarr

    nv, nl, ny, nx, nc = zarr.open_array(store, path="radiance", mode="r").shape
    return nv * nl * nc, ny * nx


def dask_matrix(store: str):
    """The range-reduced BTF matrix as a dask array read from the store (task blocks)."""
    import dask.array as da
    import zarr

    from pipeline.graphs.blocks import aligned_chunks

    z = zarr.open_array(store, path="radiance", mode="r")
    a = da.log(da.from_zarr(z, chunks=aligned_chunks(z)) + np.float32(EPS))
    nv, nl, ny, nx, nc = a.shape
    return a.transpose(0, 1, 4, 2, 3).reshape(nv * nl * nc, ny * nx)


def run_dask(store: str, rank: int, oversample: int, power_iters: int, iterator: str,
             recompute: bool = False):
    """Factors from ``dask.array.linalg.svd_compressed`` on the threaded scheduler.

    ``recompute`` is its ``compute=True``: re-read the input at each use instead of keeping it.
    """
    import dask
    import dask.array as da

    u, s, vt = da.linalg.svd_compressed(dask_matrix(store), k=rank, n_power_iter=power_iters,
                                        n_oversamples=oversample, iterator=iterator, seed=0,
                                        compute=recompute)
    with dask.config.set(scheduler="threads"):
        u, s, vt = dask.compute(u, s, vt)
    return u, s, vt.T


def run_sklearn(store: str, rank: int, oversample: int, power_iters: int):
    """Factors from ``sklearn.utils.extmath.randomized_svd`` (the matrix in memory)."""
    from sklearn.utils.extmath import randomized_svd

    a = dask_matrix(store).compute(scheduler="threads")
    u, s, vt = randomized_svd(a, n_components=rank, n_oversamples=oversample,
                              n_iter=power_iters, random_state=0)
    return u, s, vt.T


def read_pass(store: str) -> None:
    """One plain dask read pass over the store (every block decoded, then dropped)."""
    import dask.array as da
    import zarr

    from pipeline.graphs.blocks import aligned_chunks

    z = zarr.open_array(store, path="radiance", mode="r")
    blocks = da.from_zarr(z, chunks=aligned_chunks(z))
    blocks.map_blocks(lambda b: np.zeros((1,) * b.ndim, b.dtype),
                      chunks=tuple((1,) * len(c) for c in blocks.chunks)).compute(
        scheduler="threads")


def one_read(store: Path) -> float:
    """Seconds of :func:`read_pass` over ``store`` in a fresh process, as ``btf compress`` runs
    (imports included): the floor of a mode that reads the store once from the page cache.
    From a disk, zarr's chunk-by-chunk read may be slower than the disk (BENCHMARKS.md, "A
    store larger than memory")."""
    return measure(_py(f"from benchmarks.compress import read_pass; read_pass({str(store)!r})")
                   ).seconds


def memory_bytes() -> int:
    """This machine's physical memory."""
    import os

    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def _modes(args) -> list[tuple[str, list[str]]]:
    """The default mode (the suite's P and Q) and the one pass (its default sketch)."""
    return [("default", ["--oversample", str(args.oversample), "--power-iters",
                         str(args.power_iters)]),
            ("one pass", ["--passes", "1"])]


def disk(args, data: Path, tmp: Path) -> dict:
    """``btf compress`` of a store larger than memory, read from the disk: the default and the
    one pass against one read of the store, and their errors against the same material and
    sampling at ``--disk-small-size`` (which fits memory).

    Before each timed run the page cache is dropped where this process may (Linux, root); a
    store larger than memory cannot stay in it anyway, being read in order.
    """
    import zarr

    memory = memory_bytes()
    gigabytes = args.disk_gigabytes or 1.5 * memory / 1e9
    n = max(2, math.ceil(math.sqrt(gigabytes * 1e9 / (4 * 3 * args.disk_size**2))))
    sampling = f"hemi:{n}"
    started = time.perf_counter()
    store = ensure_store(data, args.material, args.disk_size, sampling)
    generated = time.perf_counter() - started
    m_rows, n_cols = matrix_shape(store)
    out = {"memory": memory, "store": str(store), "rows": m_rows, "cols": n_cols,
           "gigabytes": m_rows * n_cols * 4 / 1e9, "on_disk": store_bytes(store),
           "sampling": sampling, "prepared_seconds": generated, "runs": []}
    larger = out["on_disk"] > memory
    dropped = [larger and drop_page_cache()]
    out["one_read"] = one_read(store)
    small = ensure_store(data, args.material, args.disk_small_size, sampling)

    def compress(source: Path, options: list[str]):
        path = tmp / "disk.zarr"
        m = measure([btf_executable(), "compress", str(source), str(path), "--rank",
                     str(args.rank), *options, "--quiet", "--overwrite"])
        return m, zarr.open_group(path, mode="r").attrs

    for mode, options in _modes(args):
        dropped.append(larger and drop_page_cache())
        m, attrs = compress(store, options)
        _, small_attrs = compress(small, options)
        out["runs"].append({"mode": mode, "seconds": m.seconds, "peak_rss": m.peak_rss,
                            "passes": attrs["svd"]["passes"], "one_read": out["one_read"],
                            "error": attrs["error"]["log_relative_frobenius"],
                            "small_error": small_attrs["error"]["log_relative_frobenius"]})
    out["page_cache"] = ("dropped before each run" if all(dropped) else
                         "not dropped (not root?); the store is larger than memory" if larger
                         else "not dropped: the store fits memory (a small form)")
    out["small_shape"] = matrix_shape(small)
    return out


def products_pass(store: str, rank: int, oversample: int, kind: str) -> None:
    """One pass's matrix products of ``btf compress`` on in-memory blocks, on 2 threads."""
    from concurrent.futures import ThreadPoolExecutor

    import zarr
    from threadpoolctl import threadpool_limits

    from pipeline.graphs.row_passes import plan_row_blocks
    from tasks.svd import frobenius2, power_step, project

    z = zarr.open_array(store, path="radiance", mode="r")
    blocks = plan_row_blocks(z.shape, z.chunks[1])
    n = z.shape[2] * z.shape[3]
    width = rank + oversample if kind == "power" else 2 * (rank + oversample)  # Krylov basis
    x = np.random.default_rng(0).standard_normal((n, width)).astype(np.float32)
    biggest = max(b.rows for b in blocks)
    data = np.random.default_rng(1).standard_normal((biggest, n)).astype(np.float32)

    def one(rows):
        a = data[:rows]
        if kind == "power":
            power_step(a, x)
        else:
            project(a, x)
            frobenius2(a)

    with threadpool_limits(limits=1, user_api="blas"), ThreadPoolExecutor(2) as pool:
        list(pool.map(one, [b.rows for b in blocks]))


def _py(code: str) -> list[str]:
    return [sys.executable, "-c", code]


def timed_methods(store: Path, args, tmp: Path) -> list[dict]:
    """Wall time and peak RSS of every method on ``store``."""
    k, p, q = args.rank, args.oversample, args.power_iters
    methods = set(args.methods.split(","))
    rows = []
    if "btf" in methods:
        m = measure([btf_executable(), "compress", str(store), str(tmp / "two.zarr"), "--rank",
                     str(k), "--oversample", str(p), "--power-iters", str(q), "--quiet",
                     "--overwrite", "--workers", "2"])
        rows.append({"method": "btf compress --workers 2 (dask's thread count)",
                     "reads": q + 1, "passes": q + 1, **m.__dict__})
    for iterator, recompute in [("power", False), ("QR", False), ("QR", True)]:
        if f"dask-{iterator.lower()}" not in methods:
            continue
        m = best_of(1, _py(f"from benchmarks.compress import run_dask; run_dask("
                           f"{str(store)!r}, {k}, {p}, {q}, {iterator!r}, {recompute})"))
        rows.append({"method": f"dask svd_compressed, iterator={iterator}"
                               + (", compute=True" if recompute else ""),
                     "reads": 2 * q + 2 if recompute else 1, "passes": 2 * q + 2,
                     **m.__dict__})
    m_rows, n_cols = matrix_shape(store)
    # sklearn needs the matrix in memory; computing it from the store briefly needs two copies
    if ("sklearn" in methods and _have_sklearn()
            and m_rows * n_cols * 4 * 2.2 < _available_memory() * 0.8):
        m = best_of(1, _py(f"from benchmarks.compress import run_sklearn; "
                                     f"run_sklearn({str(store)!r}, {k}, {p}, {q})"))
        rows.append({"method": "sklearn randomized_svd (in memory)", "reads": 1,
                     "passes": 2 * q + 2, **m.__dict__})
    return rows


def bound_parts(store: str, rank: int, oversample: int, repeat: int) -> None:
    """Print (JSON) the best in-process times of a read pass and of one pass's products."""
    import json

    import dask.array  # noqa: F401  (imports are start-up, not part of a pass)
    import threadpoolctl  # noqa: F401
    import zarr  # noqa: F401

    import pipeline.stages.compress  # noqa: F401

    def best(fn, *a):
        times = []
        for _ in range(max(1, repeat)):
            t = time.perf_counter()
            fn(*a)
            times.append(time.perf_counter() - t)
        return min(times)

    print(json.dumps({"read_pass": best(read_pass, store),
                      "power_products": best(products_pass, store, rank, oversample, "power"),
                      "projection_products": best(products_pass, store, rank, oversample,
                                                  "project")}))


def ours_and_bound(store: Path, args, tmp: Path) -> tuple[dict, dict]:
    """``btf compress`` and its machine bound, measured in alternation (best of each).

    Bound: ``Q * (read + power products) + (read + projection products)``.
    """
    import json

    k, p, q = args.rank, args.oversample, args.power_iters
    ours, parts = [], []
    for _ in range(max(1, args.repeat)):
        ours.append(measure([btf_executable(), "compress", str(store), str(tmp / "ours.zarr"),
                             "--rank", str(k), "--oversample", str(p), "--power-iters", str(q),
                             "--quiet", "--overwrite"]))
        done = subprocess.run(_py(f"from benchmarks.compress import bound_parts; bound_parts("
                                  f"{str(store)!r}, {k}, {p}, 1)"),
                              stdout=subprocess.PIPE, text=True, check=True)
        parts.append(json.loads(done.stdout.strip().splitlines()[-1]))
    best = {key: min(part[key] for part in parts) for key in parts[0]}
    start = best_of(args.repeat, _py("import pipeline.cli, dask.array, zarr"))
    bound = (q * (best["read_pass"] + best["power_products"]) + best["read_pass"]
             + best["projection_products"])
    fastest = min(ours, key=lambda m: m.seconds)
    row = {"method": "btf compress (default: cores + 1 workers)", "reads": q + 1,
           "passes": q + 1, **fastest.__dict__,
           "all_seconds": [m.seconds for m in ours]}
    return row, {**best, "python_start": start.seconds, "bound": bound,
                 "bound_with_start": bound + start.seconds}


def errors(small: Path, args, tmp: Path) -> list[dict]:
    """Error of each method relative to the optimal rank-K error (exact SVD), on ``small``."""
    import zarr

    from pipeline.cli import main

    k, p, q = args.rank, args.oversample, args.power_iters
    a = dask_matrix(str(small)).compute(scheduler="threads").astype(np.float64)
    exact = np.linalg.svd(a, compute_uv=False)
    optimal = math.sqrt(float(np.sum(exact[k:] ** 2)))

    def ratio(u, s, v):
        return float(np.linalg.norm(a - (np.asarray(u, np.float64) * s) @ np.asarray(
            v, np.float64).T) / optimal)

    out = []
    for passes in ("auto", "1"):
        path = tmp / f"small-{passes}.zarr"
        # the one-pass row uses the CLI's own sketch size (k = 6K + 1, s = 2k + 1)
        extra = ["--power-iters", str(q), "--oversample", str(p)] if passes == "auto" else []
        main(["compress", str(small), str(path), "--rank", str(k), "--passes", passes,
              "--quiet", "--overwrite", *extra])
        g = zarr.open_group(path, mode="r")
        u, s, v = g["U"][:].reshape(-1, k), g["S"][:], g["V"][:].reshape(-1, k)
        out.append({"method": "btf compress" + (", one pass (default sketch, k = 6K + 1)"
                                                if passes == "1" else ""),
                    "error_vs_optimal": ratio(u, s, v),
                    "reported_error_vs_optimal": g.attrs["error"]["log_relative_frobenius"]
                    * np.linalg.norm(a) / optimal})
    for iterator in ("power", "QR"):
        out.append({"method": f"dask svd_compressed, iterator={iterator}",
                    "error_vs_optimal": ratio(*run_dask(str(small), k, p, q, iterator))})
    if _have_sklearn():
        out.append({"method": "sklearn randomized_svd",
                    "error_vs_optimal": ratio(*run_sklearn(str(small), k, p, q))})
    return out


def scaling(args, data: Path, tmp: Path) -> list[dict]:
    """``btf compress`` on stores of growing size: time and peak memory."""
    rows = []
    for gb in (float(g) for g in args.scaling.split(",") if g):
        # hemi:N at size^2 holds 3 N^2 size^2 float32 values
        n = max(2, round(math.sqrt(gb * 1e9 / (4 * 3 * args.size**2))))
        store = ensure_store(data, args.material, args.size, f"hemi:{n}")
        m_rows, n_cols = matrix_shape(store)
        floor = one_read(store)
        for mode, options in _modes(args):
            m = measure([btf_executable(), "compress", str(store), str(tmp / "scale.zarr"),
                         "--rank", str(args.rank), *options, "--quiet", "--overwrite"])
            rows.append({"gigabytes": m_rows * n_cols * 4 / 1e9, "rows": m_rows,
                         "cols": n_cols, "mode": mode, "seconds": m.seconds,
                         "peak_rss": m.peak_rss, "one_read": floor})
    return rows


def sketch_sizes(small: Path, args, tmp: Path) -> list[dict]:
    """The one pass on ``small`` for range sketches of ``c K + 1`` columns: error and time."""
    import zarr

    k = args.rank
    a = dask_matrix(str(small)).compute(scheduler="threads").astype(np.float64)
    optimal = math.sqrt(float(np.sum(np.linalg.svd(a, compute_uv=False)[k:] ** 2)))
    out = []
    for c in (int(v) for v in args.sketch_multiples.split(",") if v):
        path = tmp / "sketch.zarr"
        m = measure([btf_executable(), "compress", str(small), str(path), "--rank", str(k),
                     "--passes", "1", "--oversample", str((c - 1) * k + 1), "--quiet",
                     "--overwrite"])
        g = zarr.open_group(path, mode="r")
        u, s, v = (g["U"][:].reshape(-1, k).astype(np.float64), g["S"][:].astype(np.float64),
                   g["V"][:].reshape(-1, k).astype(np.float64))
        svd = g.attrs["svd"]
        out.append({"multiple": c, "k": svd["sketch_k"], "s": svd["sketch_s"],
                    "error_vs_optimal": float(np.linalg.norm(a - (u * s) @ v.T) / optimal),
                    "reported_vs_optimal": g.attrs["error"]["log_relative_frobenius"]
                    * np.linalg.norm(a) / optimal,
                    "seconds": m.seconds, "peak_rss": m.peak_rss,
                    "scratch_bytes": svd["scratch_bytes"]})
    return out


def texel_scaling(args, data: Path, tmp: Path) -> list[dict]:
    """``btf compress`` at equal rows on growing textures: time, peak memory, passes."""
    import zarr

    rows = []
    for size in (int(v) for v in args.texel_scaling.split(",") if v):
        store = ensure_store(data, args.material, size, args.texel_sampling)
        m_rows, n_cols = matrix_shape(store)
        floor = one_read(store)
        multi = ["--oversample", str(args.oversample), "--power-iters", str(args.power_iters)]
        modes = [("rows", [*multi, "--sketch", "rows"]), ("one pass", ["--passes", "1"])] + (
            [("texels", [*multi, "--sketch", "texels"])] if size <= args.texel_side_up_to
            else [])
        for side, options in modes:
            out = tmp / "texels.zarr"
            m = measure([btf_executable(), "compress", str(store), str(out), "--rank",
                         str(args.rank), *options, "--quiet", "--overwrite"])
            attrs = zarr.open_group(out, mode="r").attrs
            rows.append({"size": size, "rows": m_rows, "cols": n_cols, "sketch": side,
                         "gigabytes": m_rows * n_cols * 4 / 1e9, "seconds": m.seconds,
                         "peak_rss": m.peak_rss, "passes": attrs["svd"]["passes"],
                         "error": attrs["error"]["log_relative_frobenius"], "one_read": floor})
    return rows


def _have_sklearn() -> bool:
    try:
        import sklearn  # noqa: F401
    except ImportError:
        return False
    return True


def _available_memory() -> int:
    with open("/proc/meminfo") as f:
        for line in f:
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    return 8 << 30


def run(args: argparse.Namespace) -> dict:
    """All measurements of the suite, in one run."""
    data = Path(args.data_dir)
    data.mkdir(parents=True, exist_ok=True)
    parts = set(args.parts.split(","))
    with tempfile.TemporaryDirectory(prefix="btf-bench-") as tmp:
        tmp = Path(tmp)
        started = time.perf_counter()
        result = {"suite": SUITE, "rank": args.rank, "oversample": args.oversample,
                  "power_iters": args.power_iters, "timed": [], "errors": [], "scaling": [],
                  "texel_scaling": [], "sketch_sizes": [], "machine": machine()}
        if "timed" in parts:
            store = ensure_store(data, args.material, args.size, args.sampling)
            result.update(store=str(store), shape=matrix_shape(store),
                          timed=timed_methods(store, args, tmp))
            ours, bound = ours_and_bound(store, args, tmp)
            result["timed"].insert(0, ours)
            result["bound"] = bound
        if "errors" in parts:
            small_size, small_sampling = args.small.split(",", 1)
            small = ensure_store(data, args.material, int(small_size), small_sampling)
            result.update(small_shape=matrix_shape(small), errors=errors(small, args, tmp))
        if "sketch" in parts:
            small_size, small_sampling = args.small.split(",", 1)
            small = ensure_store(data, args.material, int(small_size), small_sampling)
            result.update(small_shape=matrix_shape(small),
                          sketch_sizes=sketch_sizes(small, args, tmp))
        if "scaling" in parts and args.scaling:
            result["scaling"] = scaling(args, data, tmp)
        if "texels" in parts and args.texel_scaling:
            result["texel_scaling"] = texel_scaling(args, data, tmp)
        if "disk" in parts:
            result["disk"] = disk(args, data, tmp)
        result["bench_seconds"] = time.perf_counter() - started
    return result


def report(result: dict) -> str:
    """Markdown tables of a result."""
    gib = 1 << 30
    lines = []
    if result["timed"]:
        lines += [*_timed_report(result), ""]
    if result["errors"]:
        lines += [f"Errors on the {result['small_shape'][0]} x {result['small_shape'][1]} store "
                  "(exact SVD feasible), relative to the optimal rank-K error:", "",
                  "| method | error / optimal |", "|---|---|"]
        for r in result["errors"]:
            extra = (f" (reported: {r['reported_error_vs_optimal']:.3f})"
                     if "reported_error_vs_optimal" in r else "")
            lines.append(f"| {r['method']} | {r['error_vs_optimal']:.3f}{extra} |")
        lines.append("")
    if result.get("sketch_sizes"):
        lines += [f"One pass (`--passes 1`) on the {result['small_shape'][0]} x "
                  f"{result['small_shape'][1]} store at K={result['rank']}: range sketch k = "
                  "c K + 1 columns, co-range sketch s = 2k + 1 rows (at most the rows):", "",
                  "| c | k | s | error / optimal | reported / optimal | wall s | peak RSS | "
                  "scratch |", "|---|---|---|---|---|---|---|---|"]
        for r in result["sketch_sizes"]:
            lines.append(f"| {r['multiple']} | {r['k']} | {r['s']} | "
                         f"{r['error_vs_optimal']:.3f} | {r['reported_vs_optimal']:.3f} | "
                         f"{r['seconds']:.1f} | {r['peak_rss'] / gib:.2f} GiB | "
                         f"{r['scratch_bytes'] / 2**20:.0f} MiB |")
        lines.append("")
    if result["scaling"]:
        base = {mode: next(r for r in result["scaling"] if r.get("mode", "default") == mode)
                for mode in {r.get("mode", "default") for r in result["scaling"]}}
        lines += ["Scaling of btf compress (same K, P, Q; one pass: its default sketch; one "
                  "read: every chunk of the store read and decoded once through zarr, in a "
                  "fresh process as btf compress):", "",
                  "| input | matrix | mode | wall s | vs one read | peak RSS | RSS vs smallest |",
                  "|---|---|---|---|---|---|---|"]
        for r in result["scaling"]:
            mode = r.get("mode", "default")
            lines.append(f"| {r['gigabytes']:.2f} GB | {r['rows']} x {r['cols']} | {mode} | "
                         f"{r['seconds']:.1f} | {_floor(r)} | {r['peak_rss'] / gib:.2f} GiB | "
                         f"{r['peak_rss'] / base[mode]['peak_rss']:.2f}x |")
        lines.append("")
    if result["texel_scaling"]:
        base = {side: next(r for r in result["texel_scaling"] if r["sketch"] == side)
                for side in {r["sketch"] for r in result["texel_scaling"]}}
        lines += [f"Texel scaling of btf compress at equal rows (K={result['rank']}, "
                  f"P={result['oversample']}, Q={result['power_iters']}):", "",
                  "| texels | matrix | input | sketch side | passes | wall s | vs one read | "
                  "peak RSS | RSS vs smallest | log rel. error |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for r in result["texel_scaling"]:
            lines.append(f"| {r['size']}^2 | {r['rows']} x {r['cols']} | {r['gigabytes']:.2f} GB "
                         f"| {r['sketch']} | {r['passes']} | {r['seconds']:.1f} | {_floor(r)} | "
                         f"{r['peak_rss'] / gib:.2f} GiB | "
                         f"{r['peak_rss'] / base[r['sketch']]['peak_rss']:.2f}x | "
                         f"{r['error']:.4g} |")
    if result.get("disk"):
        lines += ["", *_disk_report(result["disk"])]
    return "\n".join(lines).rstrip()


def _disk_report(d: dict) -> list[str]:
    gib = 1 << 30
    larger = "larger than memory" if d["on_disk"] > d["memory"] else "that fits memory"
    lines = [f"A store {larger}: {d['rows']} x {d['cols']} ({d['gigabytes']:.2f} GB of "
             f"float32, {d['on_disk'] / 1e9:.2f} GB on disk, {d['sampling']}) on a machine of "
             f"{d['memory'] / gib:.1f} GiB; page cache {d['page_cache']}. One read of it "
             f"through zarr: {d['one_read']:.1f} s. Errors against the same material and "
             f"sampling on {d['small_shape'][1]} texels ({d['small_shape'][0]} x "
             f"{d['small_shape'][1]}):", "",
             "| mode | passes | wall s | vs one read | peak RSS | log rel. error | the small "
             "store's |", "|---|---|---|---|---|---|---|"]
    for r in d["runs"]:
        lines.append(f"| {r['mode']} | {r['passes']} | {r['seconds']:.1f} | {_floor(r)} | "
                     f"{r['peak_rss'] / gib:.2f} GiB | {r['error']:.4g} | "
                     f"{r['small_error']:.4g} |")
    return lines


def _floor(row: dict) -> str:
    """A run's time over one read of its store (``-`` for results that do not record it)."""
    return (f"{row['seconds'] / row['one_read']:.2f}x ({row['one_read']:.1f} s)"
            if row.get("one_read") else "-")


def _timed_report(result: dict) -> list[str]:
    gib = 1 << 30
    m, n = result["shape"]
    k, p, q = result["rank"], result["oversample"], result["power_iters"]
    timed = result["timed"]
    ours = timed[0]
    qr = next((r for r in timed if r["method"].endswith("iterator=QR")), ours)
    b = result["bound"]
    lines = [f"Timed store: {m} x {n} BTF matrix ({m * n * 4 / 1e9:.2f} GB float32), "
             f"K={k}, P={p}, Q={q}, dask threads on {result['machine']['cpus']} cores.", "",
             "| method | reads of the store | passes over the matrix | wall s | peak RSS | "
             "time vs dask QR | memory vs dask QR |",
             "|---|---|---|---|---|---|---|"]
    for r in timed:
        lines.append(f"| {r['method']} | {r['reads']} | {r['passes']} | {r['seconds']:.1f} | "
                     f"{r['peak_rss'] / gib:.2f} GiB | {r['seconds'] / qr['seconds']:.2f}x | "
                     f"{r['peak_rss'] / qr['peak_rss']:.2f}x |")
    lines += ["", f"Machine bound of btf compress ({q + 1} passes): read pass "
              f"{b['read_pass']:.1f} s, products per power pass {b['power_products']:.1f} s, per "
              f"projection pass {b['projection_products']:.1f} s; bound {b['bound']:.1f} s "
              f"(+ {b['python_start']:.1f} s interpreter and imports). btf compress took "
              f"{ours['seconds'] / b['bound']:.2f}x the bound "
              f"({ours['seconds'] / b['bound_with_start']:.2f}x counting start-up); best of "
              f"{len(ours.get('all_seconds', [0]))} runs alternating with the bound's, all: "
              + ", ".join(f"{t:.1f}" for t in ours.get("all_seconds", [])) + " s."]
    return lines


def rates(result: dict) -> dict[str, float]:
    """The rates ``btf run --plan`` uses: matrix bytes per core-second and pass.

    The default mode's from the timed store; the one pass's from the largest store of the
    scaling table (at this K: its sketch's products, not its read, set its pace).
    """
    out = {}
    cpus = result["machine"]["cpus"]
    if result["timed"]:
        ours, (m, n) = result["timed"][0], result["shape"]
        out["compress_bytes_per_core_second"] = m * n * 4 * ours["passes"] / ours["seconds"] \
            / cpus
    one = [r for r in result["scaling"] if r.get("mode") == "one pass"]
    if one:
        r = max(one, key=lambda r: r["gigabytes"])
        out["compress_one_pass_bytes_per_core_second"] = r["gigabytes"] * 1e9 / r["seconds"] \
            / cpus
    return out
