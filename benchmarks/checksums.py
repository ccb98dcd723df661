"""Chunk checksums: writing and reading a store with and without its crc32c codec.

A generated radiance store's values (wood, ``abtf:12,4``, chunks of 128^2 texels and 12
lights) are written to a new array on the local disk with the project's codecs, Blosc lz4 then
crc32c (:mod:`pipeline.checksums`), and with Blosc alone, as stores were before; then each is
read back whole. Writes and reads alternate between the two, and the fastest of ``--repeat`` is
kept for each. Reads come from the page cache (the files were just written), so the figures
are the CPU cost, the worst case for the checksum's share: from a disk or object storage the
same work hides behind the transfer.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

from benchmarks.harness import generate_store, git_revision, machine

SUITE = "checksums"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the suite."""
    parser.add_argument("--size", type=int, default=512,
                        help="texels per side of the generated store (default 512)")
    parser.add_argument("--repeat", type=int, default=5,
                        help="writes and reads of each; the fastest is kept (default 5)")


def run(args: argparse.Namespace) -> dict:
    """All measurements of the suite, in one run."""
    import zarr
    from zarr.codecs import BloscCodec

    from pipeline import checksums
    from pipeline.stores.base import compressors

    checksums.install()
    rows = {"blosc": [], "blosc + crc32c": []}
    with tempfile.TemporaryDirectory(prefix="btf-bench-checksums-") as tmp:
        tmp = Path(tmp)
        source = zarr.open_group(generate_store(tmp / "src.zarr", "wood", args.size,
                                                "abtf:12,4"), mode="r")["radiance"]
        values, chunks = source[...], source.chunks
        codecs = {"blosc": (BloscCodec(cname="lz4", clevel=5, shuffle="shuffle"),),
                  "blosc + crc32c": compressors()}
        for _ in range(max(1, args.repeat)):
            for name, chosen in codecs.items():
                path = tmp / "out.zarr"
                shutil.rmtree(path, ignore_errors=True)
                start = time.perf_counter()
                array = zarr.create_array(str(path), shape=values.shape, chunks=chunks,
                                          dtype=values.dtype, compressors=chosen)
                array[...] = values
                written = time.perf_counter() - start
                start = time.perf_counter()
                back = zarr.open_array(str(path), mode="r")[...]
                read = time.perf_counter() - start
                assert (back == values).all()
                rows[name].append((written, read))
        stored = sum(p.stat().st_size for p in (tmp / "out.zarr").rglob("*") if p.is_file())
    return {"suite": SUITE, "size": args.size, "bytes": int(values.nbytes),
            "stored_bytes": stored, "chunks": list(chunks),
            "write_seconds": {k: min(w for w, _ in v) for k, v in rows.items()},
            "read_seconds": {k: min(r for _, r in v) for k, v in rows.items()},
            "machine": machine(), "git": git_revision()}


def report(result: dict) -> str:
    """Markdown table of a result."""
    mb = result["bytes"] / 1e6
    lines = [f"{result['size']}^2 texels, {mb:.0f} MB of float32 in chunks of "
             f"{tuple(result['chunks'])}, local disk (page cache)", "",
             "| codecs | write MB/s | read MB/s | write time / without | read time / without |",
             "|---|---|---|---|---|"]
    base_w, base_r = (result[k]["blosc"] for k in ("write_seconds", "read_seconds"))
    for name in ("blosc", "blosc + crc32c"):
        w, r = result["write_seconds"][name], result["read_seconds"][name]
        lines.append(f"| {name} | {mb / w:.0f} | {mb / r:.0f} | {w / base_w:.3f} | "
                     f"{r / base_r:.3f} |")
    return "\n".join(lines)
