"""Precision: float16 radiance stores against float32 ones, side by side in one run.

Three parts (``--parts``), each measuring both precisions in the same run:

- **ingest**: a synthetic UBO2003 zip of JPEGs (:func:`benchmarks.archives.write_archive`), the
  JPEG decoder's own rate on one thread (members' bytes in memory), and ``btf ingest`` of the
  zip in this process after a one-image warm-up, by default (8-bit sources: float16) and with
  ``--dtype float32``, alternately twice (float16, float32, float16, float32): images per
  second, the ratio to the decoder, the stores' bytes on disk, and whether the float16 store is
  the float32 one rounded to float16 (a few layers compared exactly).
- **compress**: a generated float32 store larger than the memory its ``btf compress`` is given
  (a cgroup v1 memory limit, which charges the page cache the process reads too, so the store
  cannot be served from it), and its float16 crop. Each of four runs (float32/float16, default
  and ``--passes 1``, interleaved) starts with the page cache dropped and the libraries read
  again by a compress of a tiny store outside the cgroup; the run itself is a child process in
  the cgroup that reports the bytes it read from storage (``read_bytes`` of /proc/self/io
  around ``pipeline.cli.main``): wall time, bytes read and the read passes they make of the
  store's bytes on disk (with one pass's scratch sketch where read back from storage), peak
  RSS, the relative error the compressed store records, and the largest relative difference
  of ``S`` between the two precisions.
- **view**: a small float32 store and its float16 crop: ``btf view --rank 16`` of each (best of
  two, the page compressed on the way) and ``btf scene`` of each with one spec (barycentric
  directions, a region, zarr output): times, the pages' sizes, and the float16 scene's
  relative RMS and largest absolute difference from the float32 one.

``--quick`` is a smoke test (a 9 x 9 zip, a 128^2 store under a 1 GiB limit, a 128^2 view
store). The compress part needs root (the cgroup and dropping the page cache); without the
cgroup it runs unlimited and the report says whether the store still exceeds the machine's
memory.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np

from benchmarks.harness import (
    btf_executable,
    chosen_stages,
    drop_page_cache,
    git_revision,
    machine,
    measure,
    store_bytes,
)

SUITE = "precision"
PARTS = ("ingest", "compress", "view")
GiB = 1 << 30
CGROUP_ROOT = Path("/sys/fs/cgroup/memory")

# option: (default, --quick default); None in the parser means "not given"
DEFAULTS = {
    "views": (81, 9), "lights": (81, 9), "size": (256, 128),
    "memory_limit": ("4GiB", "1GiB"), "compress_size": (512, 128),
    "view_size": (256, 128), "view_sampling": ("abtf:24,8", "abtf:12,4"),
}

# Runs pipeline.cli.main(argv) in the cgroup named by argv[1] (joined first, before any
# import), then prints its figures as JSON on the last line of stdout.
WRAPPER = """\
import os, sys
if sys.argv[1]:
    with open(os.path.join(sys.argv[1], "cgroup.procs"), "w") as f:
        f.write(str(os.getpid()))
import json, resource, time
def io():
    with open("/proc/self/io") as f:
        return {k: int(v) for k, v in (line.split(":") for line in f)}
start = time.perf_counter()
from pipeline.cli import main
before = io()
begun = time.perf_counter()
code = main(sys.argv[2:])
after = io()
end = time.perf_counter()
print(json.dumps({"code": code, "main_s": end - begun, "process_s": end - start,
                  "read_bytes": after["read_bytes"] - before["read_bytes"],
                  "rchar": after["rchar"] - before["rchar"],
                  "process_read_bytes": after["read_bytes"], "process_rchar": after["rchar"],
                  "peak_rss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}))
sys.exit(code)
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the suite."""
    parser.add_argument("--parts", default=",".join(PARTS),
                        help="parts to run, comma-separated (default: ingest,compress,view)")
    parser.add_argument("--quick", action="store_true",
                        help="a smoke test: 9 x 9 zip of 128^2, a 128^2 compress store under "
                             "a 1 GiB limit, a 128^2 abtf:12,4 view store (options given "
                             "explicitly still win)")
    ingest = parser.add_argument_group("ingest part")
    ingest.add_argument("--views", type=int, help="views of the zip (default 81; quick 9)")
    ingest.add_argument("--lights", type=int, help="lights of the zip (default 81; quick 9)")
    ingest.add_argument("--size", type=int,
                        help="JPEGs' pixels per side (default 256; quick 128)")
    compress = parser.add_argument_group("compress part")
    compress.add_argument("--memory-limit", help="the compress process's cgroup memory limit, "
                                                 "page cache included (default 4GiB; quick 1GiB)")
    compress.add_argument("--compress-size", type=int,
                          help="texels per side of the store (default 512; quick 128)")
    compress.add_argument("--gigabytes", type=float,
                          help="the store's float32 size in GB, reached by the smallest hemi:N "
                               "(default 2.5x the memory limit)")
    compress.add_argument("--sampling", help="the store's sampling (default: the hemi:N that "
                                             "reaches --gigabytes)")
    compress.add_argument("--rank", type=int, default=32, help="components (default 32)")
    compress.add_argument("--material", default="leather", help="material (default leather)")
    view = parser.add_argument_group("view part")
    view.add_argument("--view-size", type=int,
                      help="texels per side of the view store (default 256; quick 128)")
    view.add_argument("--view-sampling",
                      help="sampling of the view store (default abtf:24,8; quick abtf:12,4)")
    view.add_argument("--view-rank", type=int, default=16,
                      help="btf view --rank (default 16)")
    parser.add_argument("--workdir", default=tempfile.gettempdir(),
                        help="where the temporary stores go (a folder made and removed there; "
                             "the compress part needs 1.7x --gigabytes free)")


def _settings(args) -> dict:
    """The options with the full or quick defaults filled in."""
    out = {}
    for name, (full, quick) in DEFAULTS.items():
        given = getattr(args, name, None)
        out[name] = given if given is not None else (quick if args.quick else full)
    return out


def _btf(*args) -> None:
    subprocess.run([btf_executable(), *map(str, args), "--quiet"], check=True)


def _radiance(path: Path):
    import zarr

    return zarr.open_array(str(path), path="radiance", mode="r")


def rounded_equal(f32: Path, f16: Path, layers: int = 4) -> dict:
    """Whether a few layers of the float16 store equal the float32 store's rounded to float16:
    the first ``layers`` lights of the first, middle and last views."""
    a, b = _radiance(f32), _radiance(f16)
    if a.shape != b.shape:
        return {"equal": False, "values": 0, "dtypes": [str(a.dtype), str(b.dtype)]}
    views = sorted({0, a.shape[0] // 2, a.shape[0] - 1})
    equal, values = True, 0
    for v in views:
        x, y = a[v, :layers], b[v, :layers]
        equal &= y.dtype == np.float16 and np.array_equal(x.astype(np.float16), y)
        values += x.size
    return {"equal": bool(equal), "values": int(values), "dtypes": [str(a.dtype), str(b.dtype)],
            "views": views, "lights": min(layers, a.shape[1])}


# ---------------------------------------------------------------------------------- ingest


def ingest(tmp: Path, s: dict) -> dict:
    """The zip, the decoder's rate, and btf ingest in float16 and float32, twice each."""
    from benchmarks.archives import decode_rate, write_archive
    from pipeline.cli import main

    views, lights, size = s["views"], s["lights"], s["size"]
    archive = write_archive(tmp / f"ubo_{views}x{lights}_{size}.zip", size=size, views=views,
                            lights=lights)
    with zipfile.ZipFile(archive) as z:
        members = [z.read(i.filename) for i in z.infolist()[:2000]]
    decoder = decode_rate(members, 1)
    del members
    images = views * lights
    warm = write_archive(tmp / "warm.zip", size=size, views=1, lights=1)
    if main(["ingest", str(warm), str(tmp / "warm.zarr"), "--quiet"]) != 0:  # imports
        raise RuntimeError("btf ingest failed on a one-image archive")
    shutil.rmtree(tmp / "warm.zarr")
    stores = {"float16": tmp / "ingest_f16.zarr", "float32": tmp / "ingest_f32.zarr"}
    options = {"float16": [], "float32": ["--dtype", "float32"]}
    runs = []
    for dtype in ("float16", "float32", "float16", "float32"):
        out = stores[dtype]
        shutil.rmtree(out, ignore_errors=True)
        start = time.perf_counter()
        code = main(["ingest", str(archive), str(out), "--quiet", *options[dtype]])
        seconds = time.perf_counter() - start
        if code != 0:
            raise RuntimeError(f"btf ingest ({dtype}) failed with status {code}")
        runs.append({"dtype": dtype, "seconds": seconds, "per_s": images / seconds,
                     "vs_decoder": images / seconds / decoder})
    result = {"images": images, "views": views, "lights": lights, "size": size,
              "archive_bytes": archive.stat().st_size, "decode_1_per_s": decoder,
              "decoded_members": min(2000, images), "runs": runs,
              "stored_dtype": {d: str(_radiance(p).dtype) for d, p in stores.items()},
              "store_bytes": {d: store_bytes(p) for d, p in stores.items()},
              "rounded": rounded_equal(stores["float32"], stores["float16"])}
    for path in stores.values():
        shutil.rmtree(path, ignore_errors=True)
    return result


# ---------------------------------------------------------------------------------- compress


class MemoryCgroup:
    """A cgroup v1 memory cgroup with a limit, made on entry and removed on exit."""

    def __init__(self, limit: int):
        self.limit = limit
        self.path = CGROUP_ROOT / f"btfbench_{os.getpid()}"
        self.error = None

    def __enter__(self):
        try:
            self.path.mkdir()
        except OSError as exc:
            self.error = f"{self.path} could not be made ({exc.strerror or exc})"
            self.path = None
            return self
        try:
            (self.path / "memory.limit_in_bytes").write_text(str(self.limit))
            self.limit = int((self.path / "memory.limit_in_bytes").read_text())
        except OSError as exc:
            self.error = f"the limit could not be set ({exc.strerror or exc})"
            self.close()
        return self

    def reset_peak(self) -> None:
        for name in ("memory.max_usage_in_bytes", "memory.failcnt"):
            try:
                (self.path / name).write_text("0")
            except OSError:
                pass

    def read(self, name: str) -> int | None:
        try:
            return int((self.path / name).read_text())
        except (OSError, ValueError):
            return None

    def close(self) -> None:
        """Remove the cgroup (its processes have ended: the runs are waited for)."""
        if self.path is None:
            return
        for _ in range(50):
            try:
                self.path.rmdir()
                break
            except FileNotFoundError:
                break
            except OSError:  # a process still leaving
                time.sleep(0.1)
        self.path = None

    def __exit__(self, *exc):
        self.close()


def run_in_cgroup(cgroup: MemoryCgroup, argv: list[str]) -> dict:
    """``btf ARGV`` in a child process in ``cgroup`` (none: unlimited): its figures."""
    if cgroup.path is not None:
        cgroup.reset_peak()
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", WRAPPER, str(cgroup.path or ""),
                           *map(str, argv)], capture_output=True, text=True)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        killed = " (killed: over the memory limit?)" if done.returncode < 0 else ""
        raise RuntimeError(f"btf {' '.join(map(str, argv))} failed with status "
                           f"{done.returncode}{killed}\n{done.stderr[-4000:]}")
    figures = json.loads(done.stdout.strip().splitlines()[-1])
    figures["wall_s"] = wall
    if cgroup.path is not None:
        figures["cgroup_peak"] = cgroup.read("memory.max_usage_in_bytes")
        figures["cgroup_failcnt"] = cgroup.read("memory.failcnt")
    return figures


def _memory_bytes() -> int:
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def compress(tmp: Path, s: dict, args) -> dict:
    """Four compress runs (float32/float16 x default/one pass) of a store larger than the
    memory they are given, each from a dropped page cache."""
    import zarr
    from dask.utils import parse_bytes

    limit = parse_bytes(s["memory_limit"])
    size = s["compress_size"]
    gigabytes = args.gigabytes or 2.5 * limit / 1e9
    n = max(2, math.ceil(math.sqrt(gigabytes * 1e9 / (4 * 3 * size**2))))
    sampling = args.sampling or f"hemi:{n}"
    f32, f16 = tmp / "compress_f32.zarr", tmp / "compress_f16.zarr"
    started = time.perf_counter()
    _btf("generate", f32, "--material", args.material, "--size", size, "--sampling", sampling,
         "--seed", 0)
    generated = time.perf_counter() - started
    started = time.perf_counter()
    _btf("crop", f32, f16, "--dtype", "float16")
    cropped = time.perf_counter() - started
    # a tiny store of each precision: compressed outside the cgroup after each drop of the
    # page cache, so that the libraries come from memory and the run reads only its store
    tiny = {"float32": tmp / "tiny_f32.zarr", "float16": tmp / "tiny_f16.zarr"}
    _btf("generate", tiny["float32"], "--material", args.material, "--size", 16, "--sampling",
         "abtf:4,2", "--seed", 0)
    _btf("crop", tiny["float32"], tiny["float16"], "--dtype", "float16")
    stores = {"float32": f32, "float16": f16}
    shape = _radiance(f32).shape
    values = int(np.prod(shape))
    result = {"material": args.material, "size": size, "sampling": sampling, "shape": shape,
              "rows": shape[0] * shape[1] * shape[4], "cols": shape[2] * shape[3],
              "rank": args.rank, "requested_limit": limit, "machine_memory": _memory_bytes(),
              "values_bytes": {"float32": values * 4, "float16": values * 2},
              "on_disk": {d: store_bytes(p) for d, p in stores.items()},
              "generate_s": generated, "crop_s": cropped,
              "rounded": rounded_equal(f32, f16), "runs": []}
    modes = [("default", []), ("one pass", ["--passes", "1"])]
    dropped = []
    with MemoryCgroup(limit) as cgroup:
        result["cgroup"] = str(cgroup.path) if cgroup.path else None
        result["cgroup_error"] = cgroup.error
        result["limit"] = cgroup.limit if cgroup.path else None
        for mode, options in modes:
            for dtype in ("float32", "float16"):
                out, warm = tmp / "compressed.zarr", tmp / "tiny_compressed.zarr"
                dropped.append(drop_page_cache())
                _btf("compress", tiny[dtype], warm, "--rank", 2, *options, "--overwrite")
                figures = run_in_cgroup(cgroup, ["compress", stores[dtype], out, "--rank",
                                                 args.rank, *options, "-q", "--overwrite"])
                g = zarr.open_group(str(out), mode="r")
                figures.update(mode=mode, dtype=dtype, passes=g.attrs["svd"]["passes"],
                               error=g.attrs["error"]["log_relative_frobenius"],
                               S=[float(x) for x in g["S"][...]],
                               read_passes=figures["read_bytes"] / result["on_disk"][dtype])
                result["runs"].append(figures)
                shutil.rmtree(out, ignore_errors=True)
                shutil.rmtree(warm, ignore_errors=True)
    for mode, _ in modes:
        a, b = (np.array(next(r["S"] for r in result["runs"]
                              if r["mode"] == mode and r["dtype"] == d), np.float64)
                for d in ("float32", "float16"))
        result.setdefault("s_difference", {})[mode] = float(np.max(np.abs(b - a) / np.abs(a)))
    result["page_cache"] = "dropped before each run" if all(dropped) else \
        "not dropped (not root?)"
    return result


# ---------------------------------------------------------------------------------- view


def _scene_spec(path: Path, source: Path, size: int) -> Path:
    q = size // 8
    path.write_text(
        f"source: {source}\n"
        "directions:\n"
        "  - [0, 0, 0, 0]\n"
        "  - [45, 30, 20, 210]\n"
        "  - [70, 120, 35, 300]\n"
        "  - [30, 250, 50, 60]\n"
        "interpolation: barycentric\n"
        f"region: [{2 * q}, {6 * q}, {q}, {7 * q}]\n"
        "format: zarr\n")
    return path


def view(tmp: Path, s: dict, args) -> dict:
    """btf view and btf scene of a small float32 store and of its float16 crop."""
    size, sampling, rank = s["view_size"], s["view_sampling"], args.view_rank
    stores = {"float32": tmp / "view_f32.zarr", "float16": tmp / "view_f16.zarr"}
    _btf("generate", stores["float32"], "--material", "leather", "--size", size, "--sampling",
         sampling, "--seed", 1)
    _btf("crop", stores["float32"], stores["float16"], "--dtype", "float16")
    specs = {d: _scene_spec(tmp / f"scene_{d}.yaml", store, size) for d, store in stores.items()}
    runs = {("view", d): [] for d in stores} | {("scene", d): [] for d in stores}
    for _ in range(2):  # alternately, best of 2
        for dtype, store in stores.items():
            runs["view", dtype].append(measure([
                btf_executable(), "view", str(store), str(tmp / f"view_{dtype}.html"),
                "--rank", str(rank), "--quiet", "--overwrite"]))
            runs["scene", dtype].append(measure([
                btf_executable(), "scene", str(specs[dtype]), str(tmp / f"scene_{dtype}.zarr"),
                "--quiet", "--overwrite"]))
    pages, scenes = {}, {}
    for (kind, dtype), measured in runs.items():
        best = min(measured, key=lambda m: m.seconds)
        row = {"seconds": best.seconds, "all_s": [m.seconds for m in measured],
               "peak_rss": best.peak_rss}
        if kind == "view":
            pages[dtype] = {**row, "page_bytes": (tmp / f"view_{dtype}.html").stat().st_size}
        else:
            scenes[dtype] = row
    a = _radiance(tmp / "scene_float32.zarr")[...].astype(np.float64)
    out16 = _radiance(tmp / "scene_float16.zarr")
    b = out16[...].astype(np.float64)
    diff = b - a
    return {"size": size, "sampling": sampling, "rank": rank, "pages": pages,
            "scenes": scenes, "scene_shape": list(a.shape),
            "scene_dtypes": [str(_radiance(tmp / "scene_float32.zarr").dtype), str(out16.dtype)],
            "scene_rel_rms": float(np.sqrt(np.mean(diff**2)) / np.sqrt(np.mean(a**2))),
            "scene_max_abs": float(np.max(np.abs(diff))),
            "scene_max_value": float(np.max(np.abs(a))),
            "rounded": rounded_equal(stores["float32"], stores["float16"])}


# ---------------------------------------------------------------------------------- suite


def run(args: argparse.Namespace) -> dict:
    """All measurements of the suite, in one run."""
    parts = chosen_stages(args.parts, PARTS, "precision")
    s = _settings(args)
    result = {"suite": SUITE, "quick": bool(args.quick), "settings": s, "parts": parts,
              "machine": machine(), "revision": git_revision()}
    Path(args.workdir).mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="btf-bench-precision-", dir=args.workdir))
    started = time.perf_counter()
    try:
        if "ingest" in parts:
            (tmp / "ingest").mkdir()
            result["ingest"] = ingest(tmp / "ingest", s)
        if "compress" in parts:
            (tmp / "compress").mkdir()
            result["compress"] = compress(tmp / "compress", s, args)
        if "view" in parts:
            (tmp / "view").mkdir()
            result["view"] = view(tmp / "view", s, args)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    result["bench_seconds"] = time.perf_counter() - started
    return result


def _rss(n: int | None) -> str:
    return "-" if n is None else f"{n / GiB:.2f} GiB" if n >= GiB else f"{n / 2**20:.0f} MiB"


def _ingest_report(r: dict) -> list[str]:
    lines = [f"Ingest: a UBO2003-style zip of {r['images']} JPEGs ({r['views']} x "
             f"{r['lights']}, {r['size']}^2, {r['archive_bytes'] / 1e6:.0f} MB); the JPEG "
             f"decoder alone, 1 thread, on {r['decoded_members']} members in memory: "
             f"{r['decode_1_per_s']:.0f} images/s. btf ingest in this process (threads), "
             "after a one-image warm-up:", "",
             "| stored as | images/s | s | ingest / decoder | store on disk |",
             "|---|---|---|---|---|"]
    for run in r["runs"]:
        lines.append(f"| {run['dtype']} ({r['stored_dtype'][run['dtype']]}) | "
                     f"{run['per_s']:.0f} | {run['seconds']:.2f} | {run['vs_decoder']:.3f} | "
                     f"{r['store_bytes'][run['dtype']] / 1e6:.1f} MB |")
    b = r["store_bytes"]
    lines += ["", f"float16 store / float32 store on disk: {b['float16'] / b['float32']:.3f}. "
              + _rounded_line(r["rounded"])]
    return lines


def _rounded_line(rounded: dict) -> str:
    verdict = "equals" if rounded["equal"] else "does NOT equal"
    return (f"The float16 store {verdict} the float32 store rounded to float16 "
            f"({rounded['values']} values compared exactly: views {rounded.get('views')}, "
            f"first {rounded.get('lights')} lights; stored {' / '.join(rounded['dtypes'])}).")


def _compress_report(c: dict) -> list[str]:
    od, vb = c["on_disk"], c["values_bytes"]
    if c["cgroup"]:
        limit = c["limit"]
        room = limit - max(r["peak_rss"] for r in c["runs"])
        where = (f"compress runs in a cgroup v1 memory cgroup limited to {_rss(limit)}, page "
                 f"cache included; beside the process (its peak RSS) that leaves "
                 f"{_rss(max(room, 0))} for the page cache")
        fits = "; ".join(
            f"the {d} store on disk is {od[d] / limit:.2f}x the limit, "
            + ("more than that room" if od[d] > room else "NOT more than that room: it may "
               "be served from the page cache (a small form)") for d in ("float32", "float16"))
    else:
        limit = c["machine_memory"]
        where = (f"NO memory limit: {c['cgroup_error']}; compress runs unlimited on a machine "
                 f"of {_rss(limit)}")
        fits = ("both stores exceed the machine's memory on disk"
                if min(od.values()) > limit else
                "the stores do NOT both exceed the machine's memory: reads may come from the "
                "page cache, so these are not figures of a store larger than memory")
    lines = [f"Compress: {c['material']} {c['size']}^2, {c['sampling']}, a {c['rows']} x "
             f"{c['cols']} matrix at rank {c['rank']}; float32 store {vb['float32'] / 1e9:.2f} "
             f"GB of values, {od['float32'] / 1e9:.2f} GB on disk; float16 store "
             f"{vb['float16'] / 1e9:.2f} GB of values, {od['float16'] / 1e9:.2f} GB on disk "
             f"(generated in {c['generate_s']:.0f} s, cropped to float16 in "
             f"{c['crop_s']:.0f} s). {where}; {fits}. Page cache {c['page_cache']}, then the "
             "libraries read back by a tiny compress outside the cgroup. Bytes read: "
             "/proc/self/io read_bytes of the compress process around btf's main (storage, "
             "not page cache); read passes: bytes read / the store's bytes on disk (one pass's "
             "scratch sketch counts too where it is read back from storage).", "",
             "| store | mode | passes | wall s | read from storage | read passes | peak RSS | "
             "cgroup peak | log rel. error | S vs float32 (max rel.) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in c["runs"]:
        diff = (f"{c['s_difference'][r['mode']]:.2e}" if r["dtype"] == "float16" else "-")
        lines.append(f"| {r['dtype']} | {r['mode']} | {r['passes']} | {r['wall_s']:.1f} | "
                     f"{r['read_bytes'] / 1e9:.2f} GB | {r['read_passes']:.2f} | "
                     f"{_rss(r['peak_rss'])} | {_rss(r.get('cgroup_peak'))} | "
                     f"{r['error']:.6g} | {diff} |")
    lines += ["", _rounded_line(c["rounded"])]
    return lines


def _view_report(v: dict) -> list[str]:
    lines = [f"View: leather {v['size']}^2, {v['sampling']}, and its float16 crop; btf view "
             f"--rank {v['rank']} (compressing on the way) and btf scene (4 directions, "
             "barycentric, a region, zarr), each best of 2 alternating (fresh processes):", "",
             "| store | btf view s | page MB | view peak RSS | btf scene s | scene peak RSS |",
             "|---|---|---|---|---|---|"]
    for d in ("float32", "float16"):
        p, s = v["pages"][d], v["scenes"][d]
        lines.append(f"| {d} | {p['seconds']:.2f} | {p['page_bytes'] / 1e6:.2f} | "
                     f"{_rss(p['peak_rss'])} | {s['seconds']:.2f} | {_rss(s['peak_rss'])} |")
    lines += ["", f"Scene {tuple(v['scene_shape'])} ({' / '.join(v['scene_dtypes'])}): float16 "
              f"against float32, relative RMS {v['scene_rel_rms']:.2e}, largest absolute "
              f"difference {v['scene_max_abs']:.2e} (largest value {v['scene_max_value']:.3g}). "
              + _rounded_line(v["rounded"])]
    return lines


def report(result: dict) -> str:
    """Markdown tables of a result."""
    m = result["machine"]
    lines = [f"Precision, float16 against float32 (at {result['revision']}, {m['cpus']} cores, "
             f"{m['when']}{', --quick' if result['quick'] else ''}; "
             f"{result.get('bench_seconds', 0):.0f} s in all):", ""]
    if result.get("ingest"):
        lines += [*_ingest_report(result["ingest"]), ""]
    if result.get("compress"):
        lines += [*_compress_report(result["compress"]), ""]
    if result.get("view"):
        lines += [*_view_report(result["view"]), ""]
    return "\n".join(lines).rstrip()
