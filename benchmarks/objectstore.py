"""Object storage against local disk: generate and compress on S3 next to the same runs locally.

A SeaweedFS server on loopback (:mod:`benchmarks.s3server`) stands for the object store. For
each chunk layout, ``btf generate`` then ``btf compress`` run in fresh processes, once with
their stores on the local disk and once at ``s3://`` URLs; the table gives wall times, their
ratio (S3 over local, measured in the same run: the machine's noise cancels), the bytes
stored (what generate uploads and every compress pass downloads), the objects (S3 requests
scale with them, not only with bytes) and the peak RSS. Layouts: the default chunks
(``128^2 x 16`` lights, about 3 MiB), chunks of 256^2 texels, and the default chunks in shards
of 2 x 2 (one object per shard).

A second table compares the two zarr store classes on the same server and chunks, in this
process (``zarr.storage.ObjectStore`` on obstore, which btf uses, and ``FsspecStore`` on
s3fs): writing an array, reading it whole, and reading it chunk block by chunk block as
tasks do.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.harness import btf_executable, git_revision, machine, measure

SUITE = "objectstore"
LAYOUTS = {"chunks 128, 16 lights": [],
           "chunks 256, 16 lights": ["--chunk", "256"],
           "chunks 128 in 2x2 shards": ["--shard", "256"]}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the suite."""
    parser.add_argument("--size", type=int, default=512, help="texels per side (default 512)")
    parser.add_argument("--sampling", default="abtf:24,4",
                        help="light sampling (default abtf:24,4: 96 lights)")
    parser.add_argument("--rank", type=int, default=32)
    parser.add_argument("--repeat", type=int, default=2,
                        help="runs of each command; the fastest is kept (default 2)")


def _sizes(location: str) -> tuple[int, int]:
    """Bytes and objects (files) of a store."""
    from pipeline import storage

    if storage.is_url(location):
        import obstore

        bucket, key = storage._bucket(location)
        metas = [m for batch in obstore.list(bucket, prefix=key + "/") for m in batch]
        return sum(m["size"] for m in metas), len(metas)
    files = [p for p in Path(location).rglob("*") if p.is_file()]
    return sum(p.stat().st_size for p in files), len(files)


def _best(repeat: int, argv: list[str]) -> object:
    best = None
    for _ in range(max(1, repeat)):
        m = measure(argv)
        best = m if best is None or m.seconds < best.seconds else best
    return best


def run(args: argparse.Namespace) -> dict:
    """Every layout on both kinds of location; then the two store classes."""
    from benchmarks.s3server import serving
    from pipeline import storage

    btf = btf_executable()
    tmp = Path(tempfile.mkdtemp(prefix="btf-bench-objectstore-"))
    rows = []
    try:
        with serving(tmp / "s3"):
            for label, layout in LAYOUTS.items():
                row = {"layout": label}
                for where, root in (("local", str(tmp / "local")), ("s3", "s3://btf/bench")):
                    store, svd = storage.join(root, "wood.zarr"), storage.join(root, "svd.zarr")
                    gen = [btf, "generate", store, "--material", "wood", "--size", str(args.size),
                           "--sampling", args.sampling, "--quiet", "--overwrite", *layout]
                    row[f"{where}_generate"] = _best(args.repeat, gen)
                    row[f"{where}_bytes"], row[f"{where}_objects"] = _sizes(store)
                    comp = [btf, "compress", store, svd, "--rank", str(args.rank), "--quiet",
                            "--overwrite"]
                    row[f"{where}_compress"] = _best(args.repeat, comp)
                    print(f"{label} {where}: generate {row[f'{where}_generate'].seconds:.1f} s, "
                          f"compress {row[f'{where}_compress'].seconds:.1f} s", file=sys.stderr)
                    storage.remove(store)
                    storage.remove(svd)
                rows.append(row)
            classes = _store_classes(args)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return {"suite": SUITE, "size": args.size, "sampling": args.sampling, "rank": args.rank,
            "repeat": args.repeat, "rows": [_plain(r) for r in rows], "classes": classes,
            "machine": machine(), "git": git_revision()}


def _plain(row: dict) -> dict:
    return {k: (vars(v) if hasattr(v, "seconds") else v) for k, v in row.items()}


def _store_classes(args) -> list[dict]:
    """Write, read whole and read block by block with obstore and fsspec (see the module)."""
    import numpy as np
    import zarr
    from obstore.store import from_url
    from zarr.storage import FsspecStore, ObjectStore

    data = np.random.default_rng(0).random((1, 48, args.size, args.size, 3), dtype=np.float32)
    out = []
    for kind in ("obstore", "fsspec", "obstore", "fsspec"):
        name = f"s3://btf/classes/{kind}-{time.time_ns()}.zarr"

        def make(name=name, kind=kind):
            return (ObjectStore(from_url(name)) if kind == "obstore"
                    else FsspecStore.from_url(name))
        chunks = (1, 16, 128, 128, 3)
        start = time.perf_counter()
        array = zarr.create_array(make(), shape=data.shape, chunks=chunks, dtype="f4")
        array[:] = data
        write = time.perf_counter() - start
        start = time.perf_counter()
        zarr.open_array(make(), mode="r")[:]
        whole = time.perf_counter() - start
        start = time.perf_counter()
        array = zarr.open_array(make(), mode="r")
        for lo in range(0, 48, 16):
            for y in range(0, args.size, 256):
                for x in range(0, args.size, 256):
                    array[:, lo : lo + 16, y : y + 256, x : x + 256]
        blocks = time.perf_counter() - start
        mib = data.nbytes / 2**20
        out.append({"class": kind, "write_mib_s": mib / write, "read_mib_s": mib / whole,
                    "blocks_mib_s": mib / blocks})
    merged = {}
    for row in out:  # the better of the two runs of each class
        best = merged.setdefault(row["class"], dict(row))
        for key in ("write_mib_s", "read_mib_s", "blocks_mib_s"):
            best[key] = max(best[key], row[key])
    return list(merged.values())


def report(result: dict) -> str:
    """Markdown tables of a result."""
    mib = 2**20
    lines = [f"`btf bench objectstore`: wood {result['size']}^2, {result['sampling']}, compress "
             f"at rank {result['rank']}; SeaweedFS on loopback; fresh processes, best of "
             f"{result['repeat']}.", "",
             "| layout | step | local s | S3 s | S3 / local | stored MiB | objects | peak RSS "
             "local / S3 MiB |", "|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        for step in ("generate", "compress"):
            lo, s3 = r[f"local_{step}"], r[f"s3_{step}"]
            lines.append(f"| {r['layout']} | {step} | {lo['seconds']:.1f} | {s3['seconds']:.1f} "
                         f"| {s3['seconds'] / lo['seconds']:.2f} | "
                         f"{r['s3_bytes'] / mib:.0f} | {r['s3_objects']} | "
                         f"{lo['peak_rss'] / mib:.0f} / {s3['peak_rss'] / mib:.0f} |")
    lines += ["", "zarr store classes on the same server, 128^2 x 16-light chunks (MiB/s, the "
                  "better of two runs):", "",
              "| class | write | read whole | read by task blocks |", "|---|---|---|---|"]
    for c in result["classes"]:
        lines.append(f"| {c['class']} | {c['write_mib_s']:.0f} | {c['read_mib_s']:.0f} | "
                     f"{c['blocks_mib_s']:.0f} |")
    return "\n".join(lines)
