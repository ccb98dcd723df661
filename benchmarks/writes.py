"""Writes: the stages that write radiance against zarr writing the same array from memory.

One run, each command in a fresh process:

- a Bonn-style DFMF file (colour model 11, float16 factors, 16 components per channel) with
  the 151 x 151 dome of UBO2014 at ``--texels`` (:func:`benchmarks.formats.write_file`),
  ingested as factors (``btf ingest``), then rebuilt whole by ``btf reconstruct`` into
  radiance stores of 786 KB chunks (``--dir-chunk 16``, the default) and of 3 MB chunks
  (``--dir-chunk 64``); ``btf crop`` of the 786 KB store (every layer, a copy); ``btf
  generate`` of a store of the same shape (``--sampling dome151``; shading is most of its
  time, shown for completeness); ``btf ingest`` of a folder of EXR layers, ``btf quilt``
  (the planning and the application to every layer), quilting's and the roller's application
  alone (their stored plans applied in a new process, :func:`apply_stored_plan`) and ``btf
  render`` of a large layer (:func:`_more_stages`);
- **the floor**: zarr writing an array of the same shape, chunks and codecs (bytes, blosc
  lz4, btf's checksum) from memory, a block of the stage's own output in every place, on as
  many threads as the machine has cores;
- ``btf ingest --radiance`` of the file: its layers decoded straight into a radiance store of
  786 KB chunks, the same radiance in one command;
- with ``.venv-btfx`` (see ``.ci/run``), btf-extractor decoding every image of the file into
  memory, the figure issue 56 sets ingest plus reconstruct against.

Each stage's rate is reported beside its floor's, as a ratio (goal: 0.5x or more).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.harness import btf_executable, git_revision, machine, measure, store_bytes

SUITE = "writes"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the suite."""
    parser.add_argument("--texels", type=int, default=64, help="texels per side (default 64)")
    parser.add_argument("--components", type=int, default=16,
                        help="components per channel of the DFMF file (default 16)")
    parser.add_argument("--dir-chunks", default="16,64",
                        help="lights per chunk of the rebuilt stores (default 16,64: 786 KB "
                             "and 3 MB chunks at 64^2)")
    parser.add_argument("--stages",
                        default="reconstruct,crop,generate,ingest,quilt,roller,render",
                        help="stages to measure (default: every one)")
    parser.add_argument("--repeat", type=int, default=2, help="runs of each; the fastest counts")
    parser.add_argument("--s3", action="store_true",
                        help="also reconstruct and crop into a local S3 server (SeaweedFS on "
                             "loopback, benchmarks.s3server), beside zarr writing the same "
                             "array there; at the first of --dir-chunks")
    parser.add_argument("--image-size", type=int, default=512,
                        help="texels per side of the EXR layers ingested; quilt's output is "
                             "15/8 of it, render's layer 16x (default 512)")


def zarr_floor(store: str, out: str, threads: int) -> None:
    """Write an array like ``store``'s radiance (shape, chunks, codecs) from memory; print s.

    Chunk by chunk through zarr (``array[...] = block``), the stage's first chunk in every
    place, on ``threads`` threads.
    """
    import itertools
    import time
    from concurrent.futures import ThreadPoolExecutor

    import numpy as np
    import zarr

    from pipeline import storage

    src = zarr.open_group(storage.store(store), mode="r")["radiance"]
    block = np.asarray(src[tuple(slice(0, c) for c in src.chunks)])
    z = zarr.create_array(storage.store(out) if storage.is_url(out) else out, shape=src.shape,
                          chunks=src.chunks, dtype=src.dtype, serializer=src.serializer,
                          compressors=src.compressors, filters=src.filters, overwrite=True)
    grid = itertools.product(*(range(-(-n // c)) for n, c in zip(src.shape, src.chunks,
                                                                 strict=True)))

    def put(index: tuple[int, ...]) -> None:
        region = tuple(slice(i * c, min((i + 1) * c, n))
                       for i, c, n in zip(index, src.chunks, src.shape, strict=True))
        z[region] = block[tuple(slice(0, r.stop - r.start) for r in region)]

    start = time.perf_counter()
    with ThreadPoolExecutor(threads) as pool:
        list(pool.map(put, grid))
    print(json.dumps({"seconds": time.perf_counter() - start}))


def _floor(store: Path | str, tmp: Path | str) -> tuple[float, float]:
    """One run of :func:`zarr_floor` in a new process, beside ``store``.

    ``(writes, process)`` seconds: the writes alone, as the floor times them, and the whole
    process (the interpreter started, numpy and zarr imported, the first chunk read, the array
    created and written), which pays the fixed costs any program writing it with zarr pays.
    """
    from pipeline import storage

    out = storage.join(str(tmp), "floor.zarr")
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", "from benchmarks.writes import zarr_floor; "
                           f"zarr_floor({str(store)!r}, {out!r}, {os.cpu_count() or 1})"],
                          stdout=subprocess.PIPE, text=True, check=True)
    process = time.perf_counter() - start
    storage.remove(out)
    return json.loads(done.stdout.strip().splitlines()[-1])["seconds"], process


def _side_by_side(repeat: int, argv: list[str], out: Path | str, tmp: Path | str,
                  floors: int = 1):
    """The stage's fastest run and zarr's fastest floor, taken in turns; ``(run, floor)``.

    ``floor`` is the fastest ``(writes, process)`` seconds of :func:`_floor`, each taken
    alone. Each of ``repeat`` runs of ``argv`` (writing ``out``) is followed by ``floors``
    runs of the floor, and every run starts after ``sync``, so that none pays for writing
    back the dirty pages of the one before (up to a gigabyte here), and the stage and its
    floor meet the machine's slow and fast stretches alike.
    """
    from pipeline import storage

    best = floor = None
    for _ in range(repeat):
        storage.remove(str(out))
        os.sync()
        m = measure(argv)
        best = m if best is None or m.seconds < best.seconds else best
        for _ in range(floors):
            os.sync()
            seconds = _floor(out, tmp)
            floor = seconds if floor is None else tuple(map(min, floor, seconds))
    return best, floor


def _s3_rows(btf: str, tmp: Path, factors: Path, local: Path | None, repeat: int,
             dir_chunk: int) -> list[dict]:
    """Reconstruct (``dir_chunk`` lights a chunk: 786 KB chunks at 64^2 and 16) and crop (of the
    local store of those chunks) into a SeaweedFS server on loopback, each beside zarr writing
    the same array into the same server from memory."""
    from benchmarks.s3server import serving
    from pipeline import storage

    rows = []
    with serving(tmp / "s3") as server:
        root = server.url("bench")
        out = storage.join(root, f"r{dir_chunk}.zarr")
        m, floor = _side_by_side(repeat, [btf, "reconstruct", str(factors), out, "--dir-chunk",
                                          str(dir_chunk), "-q"], out, root)
        rows.append(_row("reconstruct (S3)", out, m, floor))
        if local is not None:
            out = storage.join(root, "crop.zarr")
            m, floor = _side_by_side(repeat, [btf, "crop", str(local), out, "-q"], out, root)
            rows.append(_row("crop (S3)", out, m, floor))
    return rows


def _btfx_decode(path: Path) -> float | None:
    """btf-extractor's time to decode every image of ``path`` (None without .venv-btfx)."""
    from benchmarks.formats import BTFX

    if not BTFX.exists():
        return None
    code = ("import time, btf_extractor\nt = time.perf_counter()\n"
            f"b = btf_extractor.Ubo2014({str(path)!r})\n"
            "for a in list(b.angles_vs_index_dict):\n    b.angles_to_image(*a)\n"
            "print(time.perf_counter() - t)\n")
    done = subprocess.run([str(BTFX), "-c", code], capture_output=True, text=True)
    return float(done.stdout.strip().splitlines()[-1]) if done.returncode == 0 else None


def run(args: argparse.Namespace) -> dict:
    """Every stage and its floor, in this run (see the module)."""
    from benchmarks.formats import write_file

    btf = btf_executable()
    tmp = Path(tempfile.mkdtemp(prefix="btf-bench-writes-"))
    stages = args.stages.split(",")
    rows = []
    try:
        dfmf = tmp / "dome.btf"
        write_file(dfmf, "ubo2014", args.texels, args.components)
        factors = tmp / "f.zarr"
        ingest = measure([btf, "ingest", str(dfmf), str(factors), "-q"])
        btfx = _btfx_decode(dfmf)
        first = None
        for dir_chunk in (int(c) for c in args.dir_chunks.split(",")):
            out = tmp / f"r{dir_chunk}.zarr"
            if "reconstruct" in stages:
                m, floor = _side_by_side(args.repeat, [btf, "reconstruct", str(factors),
                                                       str(out), "--dir-chunk", str(dir_chunk),
                                                       "-q"], out, tmp)
                rows.append(_row("reconstruct", out, m, floor))
            if first is None and out.exists():
                first = out
        if "reconstruct" in stages:  # the same radiance in one command, no factors between
            out = tmp / "decoded.zarr"
            m, floor = _side_by_side(args.repeat, [btf, "ingest", str(dfmf), str(out),
                                                   "--radiance", "-q"], out, tmp)
            rows.append(_row("ingest --radiance", out, m, floor))
            shutil.rmtree(out)
        if "crop" in stages and first is not None:
            out = tmp / "crop.zarr"
            m, floor = _side_by_side(args.repeat, [btf, "crop", str(first), str(out), "-q"],
                                     out, tmp)
            rows.append(_row("crop", out, m, floor))
        if "generate" in stages:
            out = tmp / "g.zarr"
            m, floor = _side_by_side(1, [btf, "generate", str(out), "--material", "leather",
                                         "--size", str(args.texels), "--sampling", "dome151",
                                         "-q"], out, tmp, floors=args.repeat)
            rows.append(_row("generate", out, m, floor))
        if args.s3:
            rows += _s3_rows(btf, tmp, factors, first, args.repeat,
                             int(args.dir_chunks.split(",")[0]))
        rows += _more_stages(btf, tmp, stages, args.repeat, args.image_size)
        recon = next((r for r in rows if r["stage"] == "reconstruct"), None)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return {"suite": SUITE, "texels": args.texels, "components": args.components,
            "ingest_seconds": ingest.seconds, "btfx_decode_seconds": btfx,
            "ingest_and_reconstruct_seconds": (ingest.seconds + recon["seconds"]
                                               if recon else None),
            "rows": rows, "repeat": args.repeat, "machine": machine(), "git": git_revision()}


def _more_stages(btf: str, tmp: Path, stages: list[str], repeat: int, size: int) -> list[dict]:
    """Rows of the stages that write radiance from other inputs than the DFMF file's.

    At the default ``size`` of 512: ``ingest``, a folder of 192 EXR layers of 512^2 (a
    generated wood, exported: 604 MB); ``quilt``, one periodic texture of 960^2 from a 256^2
    sample of 48 layers (530 MB; the planning on the reference image is part of its time),
    and ``quilt apply``, that plan applied alone; ``roller apply``, a roller's 4 tiles of 6 x 6
    periods of a generated ``tiles`` material of ``size``^2 and 48 layers applied (340 MB;
    below a ``size`` of 512, 2 x 2 periods of one of ``max(size, 256)``^2);
    ``render``, one layer of 8192^2 over a tile set of 2 x 2 corner types quilted from that
    sample (805 MB).
    """
    from benchmarks.harness import generate_store
    from pipeline.cli import main

    side = size * 15 // 8
    rows = []
    if "ingest" in stages:
        layers = generate_store(tmp / "layers.zarr", "wood", size, "abtf:24,8")
        assert main([str(v) for v in ["export", layers, tmp / "exr", "--quiet"]]) == 0
        shutil.rmtree(layers)
        out = tmp / "ingest.zarr"
        m, floor = _side_by_side(repeat, [btf, "ingest", str(tmp / "exr"), str(out), "-q"],
                                 out, tmp)
        rows.append(_row("ingest", out, m, floor))
        shutil.rmtree(tmp / "exr")
        shutil.rmtree(out)
    if "quilt" in stages or "render" in stages:
        small = generate_store(tmp / "small.zarr", "wood", size // 2, "abtf:12,4")
    if "quilt" in stages:
        out = tmp / "quilt.zarr"
        block = size // 16  # 32 at the default size
        m, floor = _side_by_side(repeat, [btf, "quilt", str(small), str(out), "--block",
                                          str(block), "--overlap", str(block // 4), "--size",
                                          f"{side},{side}", "-q"], out, tmp)
        rows.append(_row("quilt", out, m, floor))
        rows.append(_apply_row("quilt apply", out, small, tmp, repeat))
        shutil.rmtree(out)
    if "roller" in stages:
        # the material repeats every 64 texels: 256^2 holds the four periods a lattice needs
        # to be found; 6 x 6 of them make a 384^2 tile, 2 x 2 a 128^2 one
        tiles = generate_store(tmp / "lattice.zarr", "tiles", max(size, 256), "abtf:12,4")
        plan = tmp / "roller.zarr"
        periods = 6 if size >= 512 else 2
        assert main([str(v) for v in ["roller", tiles, plan, "--tiles", "4", "--periods",
                                      f"{periods},{periods}", "--quiet"]]) == 0
        rows.append(_apply_row("roller apply", plan, tiles, tmp, repeat))
        shutil.rmtree(plan)
        shutil.rmtree(tiles)
    if "render" in stages:
        tiles = tmp / "tiles.zarr"
        assert main([str(v) for v in ["quilt", small, tiles, "--corners", "2",
                                      "--quiet"]]) == 0
        out = tmp / "render.zarr"
        m, floor = _side_by_side(repeat, [btf, "render", str(tiles), str(out), "--light", "0",
                                          "--size", f"{16 * size},{16 * size}", "-q"], out, tmp)
        rows.append(_row("render", out, m, floor))
    return rows


def apply_stored_plan(tileset: str, sample: str, out: str) -> None:
    """Apply the plan stored in ``tileset`` to ``sample`` into a new tile set ``out``.

    What ``btf quilt`` and ``btf roller`` do once their plan is made (and what a killed run
    resumed after its plan was stored does): the store created, every tile's layers written,
    the output sealed (:func:`pipeline.graphs.prescriptions.write_tileset`), on the threads
    scheduler with a worker per core.
    """
    from pipeline.graphs.prescriptions import write_tileset
    from pipeline.session import RuntimeOptions, Session
    from pipeline.stores.tileset import read_plan

    with Session(RuntimeOptions(quiet=True)) as session:
        write_tileset(read_plan(tileset), out, source=sample, session=session, label="apply",
                      overwrite=False)


def _apply_row(stage: str, plan: Path, sample: Path, tmp: Path, repeat: int) -> dict:
    """The row of a tile set's application alone: its stored plan applied in a new process."""
    out = tmp / "applied.zarr"
    m, floor = _side_by_side(repeat, [sys.executable, "-c", "from benchmarks.writes import "
                                      f"apply_stored_plan; apply_stored_plan({str(plan)!r}, "
                                      f"{str(sample)!r}, {str(out)!r})"], out, tmp)
    row = _row(stage, out, m, floor)
    shutil.rmtree(out)
    return row


def _row(stage: str, out: Path, m, floor: float) -> dict:
    import numpy as np
    import zarr

    from pipeline import storage

    radiance = zarr.open_group(storage.store(str(out)), mode="r")["radiance"]
    nbytes = radiance.nbytes
    return {"stage": stage, "chunk_bytes": radiance.dtype.itemsize * int(np.prod(radiance.chunks)),
            "bytes": int(nbytes),
            "stored": None if storage.is_url(str(out)) else store_bytes(out), "seconds": m.seconds,
            "peak_rss": m.peak_rss, "floor_seconds": floor[0], "floor_process_seconds": floor[1],
            "rate": nbytes / m.seconds, "floor_rate": nbytes / floor[0]}


def report(result: dict) -> str:
    """Markdown table of a result."""
    mib = 1 << 20
    lines = [f"A DFMF file of Bonn's 151 x 151 dome at {result['texels']}^2 "
             f"({result['components']} components per channel); best of {result['repeat']} "
             "runs each. Floor: zarr writing the same array (shape, chunks, codecs) from "
             "memory on every core, in this run, a floor after each run of the stage, every "
             "run after sync. \"vs floor\" times the floor's writes alone; \"vs its process\" "
             "the floor's whole process (Python started, numpy and zarr imported, the array "
             "created), as the stage's own wall time counts its process.", "",
             "| stage | chunk | MiB | wall s | MB/s | floor MB/s | vs floor | floor process s "
             "| vs its process | peak RSS |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        process = r.get("floor_process_seconds")
        lines.append(f"| {r['stage']} | {r['chunk_bytes'] / 1024:.0f} KB | "
                     f"{r['bytes'] / mib:.0f} | {r['seconds']:.2f} | {r['rate'] / 1e6:.0f} | "
                     f"{r['floor_rate'] / 1e6:.0f} | {r['rate'] / r['floor_rate']:.2f}x | "
                     + (f"{process:.2f} | {process / r['seconds']:.2f}x | " if process
                        else "- | - | ")
                     + f"{r['peak_rss'] / mib:.0f} MiB |")
    both = result["ingest_and_reconstruct_seconds"]
    lines += ["", f"`btf ingest` of the file: {result['ingest_seconds']:.2f} s."]
    if result["btfx_decode_seconds"] and both:
        lines.append(f"Ingest and reconstruct: {both:.2f} s; btf-extractor decoding every image "
                     f"into memory: {result['btfx_decode_seconds']:.2f} s "
                     f"({both / result['btfx_decode_seconds']:.1f}x its time; goal 1.5x).")
    decoded = next((r for r in result["rows"] if r["stage"] == "ingest --radiance"), None)
    if result["btfx_decode_seconds"] and decoded:
        lines.append(f"`btf ingest --radiance` (the layers decoded into a radiance store, one "
                     f"command): {decoded['seconds']:.2f} s "
                     f"({decoded['seconds'] / result['btfx_decode_seconds']:.1f}x "
                     "btf-extractor's time).")
    return "\n".join(lines)
