"""Scaling: each stage on one core and on two, threads and processes, in the same run.

One stage command per row (generate, compress, a tiled enlarge, quilt with its plan applied to
every layer), each run in a fresh process under every configuration: dask's ``synchronous``
scheduler, ``threads`` with ``--workers 1`` and ``2``, and ``processes`` with ``--workers 2``.
Configurations alternate within each repeat, and the fastest of ``--repeat`` is kept for
each, so the machine's drift falls on all of them alike. The speed-up is against ``threads``
on one worker: what a second core brings to that stage. The inputs (a generated store, a
crop of it as the measured sample, its compression and a one-light photo of the whole) are
made once, before the timings.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path

from benchmarks.harness import (
    btf_executable,
    chosen_stages,
    generate_store,
    git_revision,
    machine,
    measure,
)

SUITE = "scaling"
CONFIGS = {"synchronous": ["--scheduler", "synchronous"],
           "threads, 1 worker": ["--scheduler", "threads", "--workers", "1"],
           "threads, 2 workers": ["--scheduler", "threads", "--workers", "2"],
           "processes, 2 workers": ["--scheduler", "processes", "--workers", "2"]}
STAGES = ("generate", "compress", "enlarge", "quilt")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the suite."""
    parser.add_argument("--size", type=int, default=512,
                        help="texels per side of the generated store (default 512)")
    parser.add_argument("--sampling", default="abtf:24,8",
                        help="its directions (default abtf:24,8: 192 lights)")
    parser.add_argument("--repeat", type=int, default=3,
                        help="runs of each stage and configuration; the fastest is kept "
                             "(default 3)")
    parser.add_argument("--stages", default=",".join(STAGES),
                        help=f"comma-separated, of {', '.join(STAGES)} (default: all)")


def commands(tmp: Path, size: int, sampling: str) -> dict[str, list[str]]:
    """Each stage's command (without its scheduling options), reading the prepared inputs."""
    half, quarter = size // 2, size // 4
    tile = max(48, half - half % 24)  # quilt's tiles: a multiple of block - overlap = 24
    return {
        "generate": ["generate", str(tmp / "out.zarr"), "--material", "wood", "--size",
                     str(size), "--sampling", sampling],
        "compress": ["compress", str(tmp / "base.zarr"), str(tmp / "out.zarr"), "--rank", "16"],
        "enlarge": ["enlarge", str(tmp / "sample_svd.zarr"), str(tmp / "photo.zarr"),
                    str(tmp / "out.zarr"), "--tile", str(half), "--seed", "1"],
        "quilt": ["quilt", str(tmp / "base.zarr"), str(tmp / "out.zarr"), "--block", "32",
                  "--seed", "1", "--size", f"{tile},{tile}"],
        "_sample": ["crop", str(tmp / "base.zarr"), str(tmp / "sample.zarr"), "--region",
                    f"{quarter}:{quarter + half},{quarter}:{quarter + half}"],
        "_photo": ["crop", str(tmp / "base.zarr"), str(tmp / "photo.zarr"), "--light", "0"],
        "_svd": ["compress", str(tmp / "sample.zarr"), str(tmp / "sample_svd.zarr"), "--rank",
                 "16"],
    }


def run(args: argparse.Namespace) -> dict:
    """Every chosen stage under every configuration, alternating, fastest of ``repeat``."""
    import subprocess

    stages = chosen_stages(args.stages, STAGES, SUITE)
    btf = btf_executable()
    tmp = Path(tempfile.mkdtemp(prefix="btf-bench-scaling-"))
    best: dict[tuple[str, str], dict] = {}
    try:
        generate_store(tmp / "base.zarr", "wood", args.size, args.sampling)
        argv = commands(tmp, args.size, args.sampling)
        for step in ("_sample", "_photo", "_svd"):
            subprocess.run([btf, *argv[step], "--quiet"], check=True)
        for _ in range(max(1, args.repeat)):
            for stage in stages:
                for config, options in CONFIGS.items():
                    shutil.rmtree(tmp / "out.zarr", ignore_errors=True)
                    m = measure([btf, *argv[stage], *options, "--quiet"])
                    key = (stage, config)
                    if key not in best or m.seconds < best[key]["seconds"]:
                        best[key] = {"stage": stage, "config": config, "seconds": m.seconds,
                                     "peak_rss": m.peak_rss}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    shown = {s: "btf " + " ".join(Path(a).name if "/" in a else a for a in argv[s])
             for s in stages}
    return {"suite": SUITE, "size": args.size, "sampling": args.sampling,
            "repeat": args.repeat, "commands": shown, "runs": list(best.values()),
            "machine": machine(), "git": git_revision()}


def report(result: dict) -> str:
    """Markdown table of a result: seconds, speed-up over one thread, peak RSS."""
    mib = 1 << 20
    runs = {(r["stage"], r["config"]): r for r in result["runs"]}
    lines = [f"{result['size']}^2 texels, `{result['sampling']}`, fastest of "
             f"{result['repeat']} runs each, {result['machine']['cpus']} cores; the speed-up is "
             "over threads on one worker.", "",
             "| stage | " + " | ".join(CONFIGS) + " | speed-up, threads 2 / processes 2 |",
             "|---|" + "---|" * (len(CONFIGS) + 1)]
    for stage in result["commands"]:
        one = runs[(stage, "threads, 1 worker")]["seconds"]
        cells = [f"{runs[(stage, c)]['seconds']:.2f} s, {runs[(stage, c)]['peak_rss'] / mib:.0f}"
                 " MiB" for c in CONFIGS]
        lines.append(f"| {stage} | " + " | ".join(cells) + " | "
                     f"{one / runs[(stage, 'threads, 2 workers')]['seconds']:.2f}x / "
                     f"{one / runs[(stage, 'processes, 2 workers')]['seconds']:.2f}x |")
    lines += ["", "Commands (scheduling options added per column):", ""]
    lines += [f"- {stage}: `{command}`" for stage, command in result["commands"].items()]
    return "\n".join(lines)
