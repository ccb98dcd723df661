"""The relighting page: its size, its time from open to first frame and per frame, in chromium.

A generated BTF (``--size``, ``--sampling``) is compressed (``--rank``) and written as a page
by ``btf view``. Debian's chromium (headless, WebGL2 on SwiftShader: the CPU, no GPU) opens it
``--repeat`` times; "first frame" is the page's own clock from navigation start to its first
frame drawn (and read back, which waits for it), "frame" the time of each of ``--frames`` frames
while the light moves around the hemisphere (blend weights, uniforms, draw, finish), and a
quarter as many of the sphere (every pixel its own blend of measured pairs). The
reference, measured in the same run, is numpy rebuilding and tone-mapping the same layer on
the CPU (``tasks.svd.reconstruct_layers`` + ``tasks.tonemap.tonemap``), as ``btf reconstruct``
and the report do.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import BROWSER_FLAGS, btf_executable, git_revision, machine

SUITE = "view"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the suite."""
    parser.add_argument("--size", type=int, default=512, help="texels per side of the store")
    parser.add_argument("--sampling", default="hemi:9",
                        help="direction sampling of the store (default hemi:9: 81 layers)")
    parser.add_argument("--rank", type=int, default=16, help="components shown")
    parser.add_argument("--repeat", type=int, default=3, help="page loads; median reported")
    parser.add_argument("--frames", type=int, default=60, help="frames timed per load")


def _btf(*args) -> None:
    subprocess.run([btf_executable(), *map(str, args), "--quiet"], check=True)


def _reference(store: Path, rank: int, repeat: int) -> float:
    """Seconds numpy takes to rebuild and tone-map one layer of the page's size (median)."""
    import zarr

    from tasks.svd import reconstruct_layers
    from tasks.tonemap import to_uint8, tonemap
    from tasks.transform import Transform

    g = zarr.open_group(store, mode="r")
    u, s, v = g["U"][0, 0][None, ..., :rank], g["S"][:rank], g["V"][..., :rank]
    t = Transform.from_attrs(g.attrs["transform"])
    times = []
    for _ in range(max(repeat, 5)):
        start = time.perf_counter()
        to_uint8(tonemap(reconstruct_layers(u, s, v, transform=t)[0], scale=1.0))
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def _frames(tab, frames: int, mode: str) -> list[float]:
    """Milliseconds of ``frames`` frames in ``mode`` while the light moves round."""
    ms = tab.evaluate(f"""() => {{
        const v = window.btfView, out = [];
        for (let i = 0; i < {frames}; i++) {{
            v.set([15 + 60 * (i % 7) / 7, (360 * i / {frames}) % 360], null, null, "{mode}");
            out.push(v.frames[v.frames.length - 1]);
        }}
        return out;
    }}""")
    return [float(x) for x in ms]


def _load(browser, page: Path, frames: int) -> tuple[float, list[float], list[float]]:
    """Time to the first frame; swatch frames; sphere frames (a quarter as many, 2 or more)."""
    tab = browser.new_page()
    tab.goto(page.as_uri())
    tab.wait_for_function("window.btfView !== undefined && window.btfView.firstFrameMs !== null")
    first = tab.evaluate("window.btfView.firstFrameMs")
    swatch = _frames(tab, frames, "swatch")
    sphere = _frames(tab, max(2, frames // 4), "sphere")[1:]  # the first compiles the shader
    tab.close()
    return float(first), swatch, sphere


def run(args) -> dict:
    """Make the page, load it in chromium, time it."""
    from playwright.sync_api import sync_playwright

    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        raise SystemExit("btf bench view needs Debian's chromium (apt-get install chromium)")
    with tempfile.TemporaryDirectory(prefix="btf-bench-view-") as tmp:
        tmp = Path(tmp)
        m, c, page = tmp / "m.zarr", tmp / "c.zarr", tmp / "v.html"
        _btf("generate", m, "--material", "leather", "--size", args.size, "--sampling",
             args.sampling, "--seed", 1)
        _btf("compress", m, c, "--rank", args.rank)
        start = time.perf_counter()
        _btf("view", c, page, "--rank", args.rank)
        write_s = time.perf_counter() - start
        reference = _reference(c, args.rank, args.repeat)
        firsts, frames, spheres = [], [], []
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=exe, args=BROWSER_FLAGS)
            for _ in range(args.repeat):
                first, ms, sphere = _load(browser, page, args.frames)
                firsts.append(first)
                frames += ms
                spheres += sphere
            browser.close()
        return {"machine": machine(), "revision": git_revision(), "size": args.size,
                "sampling": args.sampling, "rank": args.rank,
                "page_mb": page.stat().st_size / 2**20,
                "write_s": write_s, "first_frame_ms": firsts, "frame_ms": frames,
                "sphere_frame_ms": spheres,
                "numpy_layer_ms": reference * 1000}


def report(r: dict) -> str:
    """A Markdown table for BENCHMARKS.md."""
    frames = np.array(r["frame_ms"])
    numpy_ms = r["numpy_layer_ms"]
    return "\n".join([
        f"btf view, {r['size']}^2 texels, {r['sampling']}, rank {r['rank']} "
        f"(at {r['revision']}, {r['machine']['cpus']} cores, {r['machine']['when']}):",
        "",
        "| page MB | btf view s | open to first frame ms (median, worst) | frame ms (median, "
        "p95) | sphere frame ms (median) | numpy layer ms | frame / numpy layer |",
        "|---|---|---|---|---|---|---|",
        f"| {r['page_mb']:.1f} | {r['write_s']:.1f} | {np.median(r['first_frame_ms']):.0f}, "
        f"{max(r['first_frame_ms']):.0f} | {np.median(frames):.1f}, "
        f"{np.percentile(frames, 95):.1f} | "
        f"{np.median(r.get('sphere_frame_ms') or [np.nan]):.0f} | {numpy_ms:.1f} | "
        f"{np.median(frames) / numpy_ms:.2f} |",
    ])
