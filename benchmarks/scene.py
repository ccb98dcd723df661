"""Scenes: time, bytes read and chunks read against the fraction of layers and region asked.

A generated BTF (``--size``, ``--sampling``) is compressed (``--rank``) and quilted into a
compressed tile set; the compressed store gets a pyramid (``btf pyramid``, 3 levels). The tile
set keeps the sample's eigentextures and its prescriptions, so its levels are computed on the
fly (block means of its tiles' layers). On each source, scenes ask for 1%, 10% and 100% of
the measured layers (over the whole region or surface), and for 1% and 10% of the region's
texels (a square at the origin, every layer), at levels 0 to 3. Each
scene runs in this process (``pipeline.scenes.write_scene``, threads scheduler, zarr
output), so the time is the scene's own, without interpreter start-up and imports; bytes and
chunks are counted at zarr's store (every ``get`` of a chunk key). Ratios are against the
100% request at the same level, measured in the same run; "start-up aside" subtracts the time
of the smallest scene (one direction, one texel) at that level from both.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

from benchmarks.harness import btf_executable, git_revision, machine

SUITE = "scene"
FRACTIONS = (0.01, 0.1)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the suite."""
    parser.add_argument("--size", type=int, default=1024, help="texels per side of the store")
    parser.add_argument("--sampling", default="hemi:12",
                        help="direction sampling (default hemi:12: 144 layers)")
    parser.add_argument("--rank", type=int, default=16, help="components of the compression")
    parser.add_argument("--levels", default="0,1,2,3", help="levels of detail to request")
    parser.add_argument("--repeat", type=int, default=2,
                        help="runs per request; the fastest is reported")


def _btf(*args) -> None:
    subprocess.run([btf_executable(), *map(str, args), "--quiet"], check=True)


def _sources(tmp: Path, args) -> dict[str, Path]:
    m, c, q = tmp / "m.zarr", tmp / "c.zarr", tmp / "q.zarr"
    _btf("generate", m, "--material", "leather", "--size", args.size, "--sampling",
         args.sampling, "--seed", 1)
    _btf("compress", m, c, "--rank", args.rank)
    shutil.rmtree(m)
    _btf("quilt", c, q, "--corners", 2, "--size", 96)
    _btf("pyramid", c, "--levels", 3)
    return {"compressed": c, "tileset": q}


DATA = ("U", "S", "V", "radiance", "pyramid")  # data variables (not coordinates)


class _Reads:
    """Counts chunk reads of data variables and their bytes, at every zarr LocalStore."""

    def __enter__(self):
        from zarr.storage import LocalStore

        self.keys, self.bytes = set(), 0
        self._original = LocalStore.get
        original = self._original

        async def get(store, key, *a, **k):
            buf = await original(store, key, *a, **k)
            if "/c/" in key and key.split("/")[0] in DATA:
                self.keys.add(f"{store.root}/{key}")
                self.bytes += len(buf) if buf is not None else 0
            return buf

        LocalStore.get = get
        return self

    def __exit__(self, *exc):
        from zarr.storage import LocalStore

        LocalStore.get = self._original


def _requests(source: Path, kind: str, size: int) -> list[tuple[str, float, str]]:
    """``(what, fraction, spec text)`` of every request (without level)."""
    import zarr

    g = zarr.open_group(source, mode="r")
    tl, pl, tv, pv = (g[n][...] for n in ("theta_light", "phi_light", "theta_view",
                                          "phi_view"))
    pairs = [[float(tl[li]), float(pl[li]), float(tv[v]), float(pv[v])]
             for v in range(len(tv)) for li in range(len(tl))]

    def spec(directions, side):
        place = (f"size: [{side}, {side}]\n" if kind == "tileset"
                 else f"region: [0, {side}, 0, {side}]\n")
        return (f"source: {source}\ninterpolation: nearest\ndirections:\n"
                + "".join(f"  - {d}\n" for d in directions) + place)

    out = [("all", 1.0, spec(pairs, size)), ("start-up", 0.0, spec(pairs[:1], 1))]
    for f in FRACTIONS:
        k = max(1, round(f * len(pairs)))
        step = len(pairs) / k
        out.append(("layers", k / len(pairs), spec([pairs[int(i * step)] for i in range(k)],
                                                   size)))
        side = max(1, round(size * f**0.5))
        out.append(("region", side**2 / size**2, spec(pairs, side)))
    return out


def _one(spec_text: str, tmp: Path, level: int, repeat: int) -> dict:
    import zarr

    from pipeline.scene_spec import load
    from pipeline.scenes import write_scene
    from pipeline.session import RuntimeOptions, Session

    path = tmp / "scene.yaml"
    path.write_text(spec_text + f"level: {level}\n")
    best = None
    for _ in range(max(1, repeat)):
        out = tmp / "out.zarr"
        with Session(RuntimeOptions(scheduler="threads", quiet=True)) as session, \
                _Reads() as reads:
            start = time.perf_counter()
            write_scene(load(path), str(out), session)
            seconds = time.perf_counter() - start
        chunks = sum(a for a, _ in zarr.open_group(out, mode="r").attrs["reads"].values())
        shutil.rmtree(out)
        row = {"seconds": seconds, "bytes_read": reads.bytes, "chunks_read": len(reads.keys),
               "chunks_planned": chunks}
        if best is None or seconds < best["seconds"]:
            best = row
    return best


def run(args: argparse.Namespace) -> dict:
    """Every source, request and level (see the module)."""
    levels = [int(n) for n in args.levels.split(",")]
    result = {"revision": git_revision(), "machine": machine(), "size": args.size,
              "sampling": args.sampling, "rank": args.rank, "rows": []}
    with tempfile.TemporaryDirectory(prefix="btf-bench-scene-") as name:
        tmp = Path(name)
        sources = _sources(tmp, args)
        for kind, source in sources.items():
            for what, fraction, text in _requests(source, kind, args.size):
                for level in levels:
                    row = _one(text, tmp, level, args.repeat)
                    result["rows"].append({"source": kind, "request": what,
                                           "fraction": fraction, "level": level, **row})
    return result


def report(result: dict) -> str:
    """Markdown table: each request against the 100% request of its source and level."""
    full = {(r["source"], r["level"]): r for r in result["rows"] if r["request"] == "all"}
    start = {(r["source"], r["level"]): r["seconds"] for r in result["rows"]
             if r["request"] == "start-up"}
    lines = [f"{result['size']}^2 texels, {result['sampling']}, rank {result['rank']}, at "
             f"{result['revision']}:", "",
             "| source | request | fraction | level | s | MB read | chunks read | "
             "time / 100% | start-up aside | bytes / 100% | chunks / 100% |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(result["rows"], key=lambda r: (r["source"], r["level"], r["fraction"])):
        f = full[(r["source"], r["level"])]
        s0 = start[(r["source"], r["level"])]
        aside = (r["seconds"] - s0) / (f["seconds"] - s0)
        lines.append(
            f"| {r['source']} | {r['request']} | {r['fraction']:.2%} | {r['level']} | "
            f"{r['seconds']:.2f} | {r['bytes_read'] / 1e6:.1f} | {r['chunks_read']} | "
            f"{r['seconds'] / f['seconds']:.3f} | {aside:.3f} | "
            f"{r['bytes_read'] / max(f['bytes_read'], 1):.3f} | "
            f"{r['chunks_read'] / max(f['chunks_read'], 1):.3f} |")
    return "\n".join(lines)
