"""Generator throughput: ``btf generate`` against the same kernels run serially in-process.

The reference renders exactly the blocks the pipeline renders (fields with halo once per
spatial task block, then every light block), in one thread, without dask or zarr. The ratio of the
two wall times is the pipeline's parallel speed-up net of its overheads (graph, compression,
writing): on 2 cores the ideal is 2.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.harness import best_of, btf_executable, git_revision, machine, measure

SUITE = "generate"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the suite."""
    parser.add_argument("--material", default="wood")
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--sampling", default="abtf:24,8")
    parser.add_argument("--schedulers", default="threads,processes",
                        help="comma-separated schedulers to time (default: threads,processes)")
    parser.add_argument("--scale-size", type=int, default=1024,
                        help="also generate this size once (threads) to show that peak memory "
                             "does not grow with the store; 0 to skip (default: 1024)")
    parser.add_argument("--repeat", type=int, default=3,
                        help="runs of each measurement; the fastest is reported (default: 3)")


def kernel_reference(material: str, size: int, sampling: str) -> float:
    """Seconds to render the store's blocks serially with the bare kernels (no dask, no zarr)."""
    import numpy as np

    from pipeline.graphs.blocks import task_side
    from pipeline.stores.radiance import Layout
    from tasks.materials import Material
    from tasks.sampling import parse_sampling
    from tasks.shading import ShadingModel, render_block

    s = parse_sampling(sampling)
    m = Material(material)
    model = ShadingModel(relief=m.relief)
    halo = model.halo(float(s.theta_view.max()), float(s.theta_light.max()))
    layout = Layout()
    chunk, shard = layout.spatial(size)
    unit = shard or chunk
    step = task_side(unit)  # the pipeline's task block
    start = time.perf_counter()
    for y0 in range(0, size, step):
        for x0 in range(0, size, step):
            ny, nx = min(step, size - y0), min(step, size - x0)
            fields = m.fields(y0 - halo, x0 - halo, ny + 2 * halo, nx + 2 * halo)
            for v in range(s.theta_view.size):
                for l0 in range(0, s.theta_light.size, layout.dir_chunk):
                    lights = slice(l0, l0 + layout.dir_chunk)
                    block = render_block(fields, halo=halo, theta_view=s.theta_view[v : v + 1],
                                         phi_view=s.phi_view[v : v + 1],
                                         theta_light=s.theta_light[lights],
                                         phi_light=s.phi_light[lights], model=model)
                    np.asarray(block)
    return time.perf_counter() - start


def run(args: argparse.Namespace) -> dict:
    """Time the CLI on each scheduler and the serial kernel reference, in this run."""
    from tasks.sampling import parse_sampling

    s = parse_sampling(args.sampling)
    work = args.size * args.size * s.theta_view.size * s.theta_light.size
    btf = btf_executable()
    tmp = Path(tempfile.mkdtemp(prefix="btf-bench-"))
    rows = []
    try:
        reference = best_of(args.repeat, [
            sys.executable, "-c", "from benchmarks.generate import kernel_reference; "
            f"kernel_reference({args.material!r}, {args.size}, {args.sampling!r})"])
        for scheduler in args.schedulers.split(","):
            out = tmp / f"{scheduler}.zarr"
            m = best_of(args.repeat, [btf, "generate", str(out), "--material", args.material,
                                      "--size", str(args.size), "--sampling", args.sampling,
                                      "--scheduler", scheduler, "--quiet", "--overwrite"])
            stored = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
            rows.append({"scheduler": scheduler, "seconds": m.seconds, "peak_rss": m.peak_rss,
                         "texel_directions_per_s": work / m.seconds,
                         "speedup_vs_serial_kernels": reference.seconds / m.seconds,
                         "stored_bytes": stored})
            shutil.rmtree(out)
        if args.scale_size:
            out = tmp / "scale.zarr"
            m = measure([btf, "generate", str(out), "--material", args.material, "--size",
                         str(args.scale_size), "--sampling", args.sampling, "--quiet"])
            big = args.scale_size**2 * s.theta_view.size * s.theta_light.size
            rows.append({"scheduler": f"threads, size {args.scale_size}", "seconds": m.seconds,
                         "peak_rss": m.peak_rss, "texel_directions_per_s": big / m.seconds,
                         "speedup_vs_serial_kernels": None, "bytes": big * 12,
                         "stored_bytes": sum(f.stat().st_size for f in out.rglob("*")
                                             if f.is_file())})
            shutil.rmtree(out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    command = (f"btf generate OUT --material {args.material} --size {args.size} "
               f"--sampling {args.sampling}")
    return {"suite": SUITE, "command": command, "repeat": args.repeat, "texel_directions": work,
            "bytes": work * 3 * 4, "serial_kernels": {"seconds": reference.seconds,
                                                      "peak_rss": reference.peak_rss},
            "runs": rows, "machine": machine(),
            "git": git_revision()}


def report(result: dict) -> str:
    """Markdown table of a result."""
    mib = 1 << 20
    lines = [f"`{result['command']}`: {result['texel_directions'] / 1e6:.1f} M texel x "
             f"directions, {result['bytes'] / mib:.0f} MiB of float32 radiance; best of "
             f"{result['repeat']} runs each.",
             "",
             "| run | wall s | texel-dirs/s | vs serial kernels | peak RSS | on disk |",
             "|---|---|---|---|---|---|",
             f"| serial kernels (no dask, no zarr; reference) | "
             f"{result['serial_kernels']['seconds']:.2f} | "
             f"{result['texel_directions'] / result['serial_kernels']['seconds'] / 1e6:.1f} M | "
             f"1.00x | {result['serial_kernels']['peak_rss'] / mib:.0f} MiB | - |"]
    for r in result["runs"]:
        ratio = r["speedup_vs_serial_kernels"]
        shown = f"{ratio:.2f}x" if ratio is not None else f"({r['bytes'] / mib:.0f} MiB store)"
        lines.append(f"| btf generate, {r['scheduler']} | {r['seconds']:.2f} | "
                     f"{r['texel_directions_per_s'] / 1e6:.1f} M | {shown} | "
                     f"{r['peak_rss'] / mib:.0f} MiB | {r['stored_bytes'] / mib:.0f} MiB |")
    return "\n".join(lines)


def rates(result: dict) -> dict[str, float]:
    """The rate ``btf run --plan`` uses: texel x directions per core-second (threads)."""
    threads = [r for r in result["runs"] if r["scheduler"] == "threads"]
    if not threads:
        return {}
    best = max(r["texel_directions_per_s"] for r in threads)
    return {"generate_texel_directions_per_core_second": best / result["machine"]["cpus"]}
