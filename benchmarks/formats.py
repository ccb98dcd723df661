"""Measured BTF formats: decoding Bonn DFMF files against btf-extractor, and archive ingest.

A DFMF file (colour model 11, float16, as Bonn's UBO2014 files) is written with a real
geometry (``--sampling``: ubo2003's 81 x 81 or ubo2014's 151 x 151 directions) at two texel
sizes, and decoded to radiance images by

- btf (:func:`pipeline.dfmf_io.decode_pairs`: the file's ``U`` rows and ``S V`` a band of
  texels at a time, BLAS products, the colour model in numpy);
- btf-extractor 1.7.0's C++ decoder (``btf.hh`` with F16C and OpenMP; the decoder the Mitsuba
  BTF plugin uses), from its own venv ``.venv-btfx`` (see ``.ci/run``),

each in a fresh process: the time to open the file, to decode every image of the file (per
image: btf-extractor one at a time, btf in batches of ``--batch``), to decode one (view, light)
pair (best of a few, after the whole-file pass), and the peak resident memory. btf's first
calls compile its kernels (numba, about a second): they run before the timed passes and are
reported apart. ``btf ingest
FILE.btf`` (file to compressed store, no expansion) is timed with its peak memory too. With
``--archive`` the suite also measures ingest of a UBO2003-style zip of JPEGs against the JPEG
decoder's own rate (:mod:`benchmarks.archives`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import btf_executable, git_revision, machine, measure

SUITE = "formats"
ROOT = Path(__file__).resolve().parents[1]
BTFX = ROOT / ".venv-btfx" / "bin" / "python"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the suite."""
    parser.add_argument("--sampling", default="ubo2003", choices=("ubo2003", "ubo2014"),
                        help="direction sampling of the DFMF file (btf-extractor needs as "
                             "many views as lights)")
    parser.add_argument("--texels", default="128,256",
                        help="texels per side of the files (comma-separated: memory against "
                             "file size)")
    parser.add_argument("--components", type=int, default=16, help="components per channel")
    parser.add_argument("--batch", type=int, default=64, help="images btf decodes at once")
    parser.add_argument("--views", type=int, default=0,
                        help="decode the images of only the first N views in the whole-file "
                             "pass (0: all)")
    parser.add_argument("--archive", action="store_true",
                        help="also measure ingest of a UBO2003-style zip of 256^2 JPEGs")
    parser.add_argument("--archive-views", type=int, default=81,
                        help="views of that zip (81 lights each)")


def write_file(path: Path, sampling: str, texels: int, k: int, seed: int = 0,
               decay: float = 0.7) -> None:
    """A DFMF file, colour model 11 in float16, with a plausible spectrum of components.

    Component ``j`` has the scale ``decay^j``: 0.7 is steep (most components carry little and
    compress well), about 0.97 is as flat as measured materials' spectra over 150 components.
    """
    from pipeline.dfmf_io import COLOUR_MODEL
    from tasks.dfmf import DfmfHeader, channel_head, header_bytes, layout, radians
    from tasks.sampling import parse_sampling

    s = parse_sampling(sampling)
    tv, pv = radians(s.theta_view, s.phi_view)
    tl, pl = radians(s.theta_light, s.phi_light)
    rows = len(tv) * len(tl)
    header = DfmfHeader(
        version=4, rotations=0, measurement_setup="btf bench formats", image_sensor="",
        light_source="", ppmm=0.0, rgb_scale=(1.0, 1.0, 1.0), cosine=False, xml="",
        channel_names=("R", "G", "B"), theta_view=tv, phi_view=pv, theta_light=tl,
        phi_light=pl, width=texels, height=texels, components=k,
        colour_model=COLOUR_MODEL["ylog-uv-over-y"], colour_mean=(0.0, 0.0, 0.0),
        colour_matrix=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), channels=())
    start = len(header_bytes(header))
    header = dataclasses.replace(header, channels=layout(start, 2, [k] * 3, rows,
                                                         texels * texels))
    rng = np.random.default_rng(seed)
    decay = decay ** np.arange(k)
    with open(path, "wb") as f:
        f.write(header_bytes(header))
        for c, block in enumerate(header.channels):
            u = rng.normal(size=(rows, k)) * 0.05 * (0.2 if c else 1.0)
            u[:, 0] = (-1.5 if c == 0 else 0.02) + rng.normal(size=rows) * 0.05
            f.write(channel_head(block) + decay.astype("<f2").tobytes())
            f.write(u.astype("<f2").tobytes())
            for y0 in range(0, texels, 64):  # S x V a band at a time
                n = min(64, texels - y0) * texels
                v = rng.normal(size=(n, k)) * decay
                v[:, 0] = 1.0
                f.write(v.astype("<f2").tobytes())


_OURS = r"""
import json, resource, sys, time
from pipeline.dfmf_io import decode_pairs, read_header

path, batch, views, repeat = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), 15
t = time.perf_counter()
h = read_header(path)
opened = time.perf_counter() - t
nl = len(h.theta_light)
pair = (len(h.theta_view) // 2, nl // 3)
pairs = [(v, li) for v in range(views or len(h.theta_view)) for li in range(nl)]
t = time.perf_counter()  # the first calls compile the kernels (numba): timed apart
decode_pairs(path, h, [pair])
decode_pairs(path, h, pairs[:batch])
compile_s = time.perf_counter() - t
t = time.perf_counter()
for i in range(0, len(pairs), batch):
    decode_pairs(path, h, pairs[i : i + batch])
whole = time.perf_counter() - t
one = float("inf")
for _ in range(repeat):
    s = time.perf_counter()
    decode_pairs(path, h, [pair])
    one = min(one, time.perf_counter() - s)
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
print(json.dumps({"open": opened, "one": one, "images": len(pairs), "whole": whole,
                  "peak_rss": rss, "first_calls": compile_s}))
"""

_BTFX = r"""
import json, resource, sys, time
from btf_extractor import Ubo2014

path, views, repeat = sys.argv[1], int(sys.argv[2]), 15
t = time.perf_counter()
b = Ubo2014(path)
opened = time.perf_counter() - t
keys = sorted(b.angles_vs_index_dict, key=lambda a: b.angles_vs_index_dict[a])
nl = int(round(len(keys) ** 0.5))
key = keys[(nl // 2) * nl + nl // 3]
chosen = keys[: (views or nl) * nl]
t = time.perf_counter()
for a in chosen:
    b.angles_to_image(*a)
whole = time.perf_counter() - t
one = float("inf")
for _ in range(repeat):
    s = time.perf_counter()
    b.angles_to_image(*key)
    one = min(one, time.perf_counter() - s)
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
print(json.dumps({"open": opened, "one": one, "images": len(chosen), "whole": whole,
                  "peak_rss": rss}))
"""


def _decode(python: str, script: str, *args) -> dict:
    done = subprocess.run([python, "-c", script, *map(str, args)], capture_output=True,
                          text=True)
    if done.returncode != 0:
        raise RuntimeError(f"decoding failed ({python}):\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def run(args: argparse.Namespace) -> dict:
    """All measurements of the suite, in one run."""
    result = {"suite": SUITE, "machine": machine(), "git": git_revision(),
              "sampling": args.sampling, "components": args.components, "files": [],
              "btfx": BTFX.exists()}
    with tempfile.TemporaryDirectory(prefix="btf-bench-formats-") as tmp:
        tmp = Path(tmp)
        for texels in (int(t) for t in args.texels.split(",") if t):
            path = tmp / f"f{texels}.btf"
            write_file(path, args.sampling, texels, args.components)
            row = {"texels": texels, "bytes": path.stat().st_size,
                   "btf": _decode(sys.executable, _OURS, path, args.batch, args.views)}
            if BTFX.exists():
                row["btfx"] = _decode(str(BTFX), _BTFX, path, args.views)
            start = time.perf_counter()
            ingest = measure([btf_executable(), "ingest", str(path), str(tmp / "s.zarr"),
                              "--quiet", "--overwrite"])
            row["ingest"] = {"seconds": ingest.seconds, "peak_rss": ingest.peak_rss,
                             "wall": time.perf_counter() - start}
            result["files"].append(row)
            path.unlink()
        if args.archive:
            from benchmarks.archives import archive_rates

            result["archive"] = archive_rates(tmp / "archive", views=args.archive_views)
    return result


def _mb(n: float) -> str:
    return f"{n / 2**20:.0f}"


def report(result: dict) -> str:
    """Markdown tables of a result."""
    lines = [f"DFMF decode, {result['sampling']} directions, {result['components']} "
             "components per channel, colour model 11, float16; per image = whole-file pass "
             "/ images decoded.", "",
             "| texels | file MB | decoder | open s | one pair ms | per image ms (images) | "
             "peak RSS MB | btf-extractor / btf, per image |",
             "|---|---|---|---|---|---|---|---|"]
    for row in result["files"]:
        ours = row["btf"]
        mine = ours["whole"] / ours["images"]
        for name in ("btf", "btfx"):
            if name not in row:
                continue
            d = row[name]
            per = d["whole"] / d["images"]
            ratio = f"{per / mine:.2f}x" if name == "btfx" else ""
            lines.append(f"| {row['texels']}^2 | {_mb(row['bytes'])} | "
                         f"{'btf' if name == 'btf' else 'btf-extractor 1.7.0'} | "
                         f"{d['open']:.3f} | {d['one'] * 1e3:.2f} | {per * 1e3:.3f} "
                         f"({d['images']}) | {_mb(d['peak_rss'])} | {ratio} |")
        lines.append(f"| {row['texels']}^2 | {_mb(row['bytes'])} | btf, first calls "
                     f"(compiling) | | | {ours['first_calls']:.2f} s | | |")
        lines.append(f"| {row['texels']}^2 | {_mb(row['bytes'])} | btf ingest (to a "
                     f"compressed store) | | | {row['ingest']['seconds']:.2f} s in all | "
                     f"{_mb(row['ingest']['peak_rss'])} | |")
    if not result["btfx"]:
        lines += ["", "btf-extractor is not installed (.venv-btfx, see .ci/run): no "
                      "side-by-side figures."]
    if "archive" in result:
        a = result["archive"]
        lines += ["", f"UBO2003-style zip, {a['images']} JPEGs of {a['size']}^2 "
                      f"({a['archive_mb']} MB), images per second:", "",
                  "| JPEG decoder, 1 thread | JPEG decoder, 2 threads | btf ingest "
                  f"({a['scheduler']}) | ingest / decoder (1 thread) | ingest peak RSS MB |",
                  "|---|---|---|---|---|",
                  f"| {a['decode_1_per_s']} | {a['decode_2_per_s']} | {a['ingest_per_s']} "
                  f"({a['ingest_s']} s) | {a['ingest_per_s'] / a['decode_1_per_s']:.2f} | "
                  f"{a.get('peak_rss_mb', '')} |"]
    return "\n".join(lines)
