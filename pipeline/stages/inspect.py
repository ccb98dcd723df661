"""``btf inspect``: what a store holds, from its metadata; its values only when asked.

Given a measured source (a ``.btf``, ``.zip`` or ``.big`` file, a folder of images) rather
than a store, its format describes it from its headers (:mod:`pipeline.sources`).

By default only metadata is read (array shapes, chunking, codecs, attrs, bytes on disk from the
file listing, and the small direction coordinates). ``--scan`` reads every data variable block
by block (:func:`pipeline.graphs.reductions.statistics`), ``--plot`` draws the direction
sampling on the hemisphere. Stage specific summaries come from the store's kind
(:data:`pipeline.stores.KINDS`), so a new kind of store brings its own.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from pipeline import checksums
from pipeline.atomic import atomic_output
from pipeline.checksums import ChecksumError
from pipeline.errors import BTFError
from pipeline.graphs.reductions import bad_chunks, read_array, statistics
from pipeline.params import option
from pipeline.session import Session
from pipeline.sources import formats_help
from pipeline.stage import Stage
from pipeline.stores import KINDS, CompressedStore, open_store
from pipeline.stores.base import DIRECTION_COORDS, location
from pipeline.stores.compressed import total_energy
from pipeline.stores.levels import levels_of


@dataclasses.dataclass(frozen=True)
class InspectParams:
    """Parameters of ``btf inspect``."""

    store: str = option(help="zarr store to describe, or a measured source to look at before "
                             "ingesting it: one of the formats listed above",
                        positional=True, path="in")
    json: bool = option(False, help="print one JSON object instead of text")
    scan: bool = option(False, help="read all data chunk by chunk: min, max, mean, NaN/Inf "
                                    "and negative counts per variable; every chunk's checksum "
                                    "is verified, and in a store btf completed every chunk "
                                    "must be there: bad or missing chunks are listed (exit "
                                    "status 1)")
    plot: str | None = option(None, path="out", metavar="FILE",
                              help="draw the direction sampling on the hemisphere (a PNG file; "
                                   "an existing file is replaced)")
    report: str | None = option(None, path="out", metavar="FILE",
                                help="also write the JSON report to FILE (an existing file is "
                                     "replaced)")


def _codecs(array) -> list[str]:
    out = []
    for codec in (*array.filters, array.serializer, *array.compressors):
        if codec is None:
            continue
        spec = codec.to_dict()
        config = spec.get("configuration") or {}
        shown = ", ".join(f"{k}={v}" for k, v in config.items() if k not in ("typesize",
                                                                             "blocksize"))
        out.append(f"{spec['name']}({shown})" if shown else spec["name"])
    return out


def _variable(array) -> dict[str, Any]:
    nbytes = int(np.prod(array.shape)) * array.dtype.itemsize
    stored = int(array.nbytes_stored())
    return {
        "dims": list(array.metadata.dimension_names or ()),
        "shape": list(array.shape),
        "dtype": str(array.dtype),
        "chunks": list(array.chunks),
        "shards": list(array.shards) if array.shards else None,
        "codecs": _codecs(array),
        "bytes": nbytes,
        "stored_bytes": stored,
        "ratio": nbytes / stored if stored else None,
    }


def describe(path: str | Path) -> dict[str, Any]:
    """Metadata report of a store (no data is read beyond coordinate arrays)."""
    store = open_store(path, checked=False)  # what is wrong with it is reported, not raised
    group = store.group
    variables = {name: _variable(group[name]) for name in sorted(group.array_keys())}
    nbytes = sum(v["bytes"] for v in variables.values())
    stored = sum(v["stored_bytes"] for v in variables.values())
    attrs = store.attrs
    report = {
        "path": str(path),
        "kind": store.kind or "unknown",
        "source": attrs.get("source"),
        "variables": variables,
        "total": {"bytes": nbytes, "stored_bytes": stored,
                  "ratio": nbytes / stored if stored else None},
        "attrs": attrs,
    }
    if store.kind is not None:
        report.update(store.summary(group))
    levels = levels_of(group)
    if levels:
        report["levels"] = levels
    return report


def scan(path: str | Path, session: Session) -> dict[str, dict[str, Any]]:
    """Statistics of every numeric array, read once block by block (memory: a few blocks)."""
    group = open_store(path, checked=False).group
    names = [n for n in sorted(group.array_keys()) if group[n].dtype.kind in "fiu"
             and n not in DIRECTION_COORDS]
    session.log(f"scan: {len(names)} variable(s) of {path}")
    try:
        (lazy,) = session.compute({n: statistics(read_array(path, n)) for n in names})
    except BTFError as exc:
        from pipeline import completeness

        missing = isinstance(exc, checksums.MissingChunkError)
        if not (missing or isinstance(exc, ChecksumError)):
            raise
        session.log(f"scan: a chunk {'is missing' if missing else 'failed its checksum'}; "
                    "reading every chunk to list the bad ones")
        (bad,) = session.compute(bad_chunks(path, names))
        lacking = {k for keys in completeness.missing(location(path)).values() for k in keys}
        listed = [f"  {n} {checksums.chunk_name(group[n], c)}"
                  + (" (missing)" if completeness.object_key(group[n], c) in lacking else "")
                  for n in names for c in bad[n]]
        raise BTFError(f"{path}: {len(listed)} chunk(s) fail their checksum, cannot be decoded "
                       f"or are missing (variable, chunk grid index and the values it holds):\n"
                       + "\n".join(listed) + "\n" + (checksums.RESTORE if not lacking else (
                           "chunks changed or were lost after btf wrote them: restore the "
                           "store from a good copy or write it again"))) from None
    out = {}
    for name in names:
        s = {k: float(v) for k, v in lazy[name].items()}
        has = s["finite"] > 0
        out[name] = {"count": int(np.prod(group[name].shape)), "nan": int(s["nan"]),
                     "inf": int(s["inf"]), "negative": int(s["negative"]),
                     "min": s["min"] if has else None, "max": s["max"] if has else None,
                     "mean": s["sum"] / s["finite"] if has else None}
    return out


def plot_sampling(path: str | Path, out: str | Path) -> None:
    """Draw light and view directions on the hemisphere (polar: radius theta, angle phi).

    For a compressed store, a third panel draws the singular values and the energy captured.
    """
    from matplotlib.figure import Figure

    store = open_store(path, checked=False)
    group = store.group
    d = store.directions
    compressed = isinstance(store, CompressedStore)
    panels = 3 if compressed else 2
    fig = Figure(figsize=(4.6 * panels, 4.6), layout="constrained")
    if compressed:
        s = np.asarray(group["S"][:], np.float64)
        ax = fig.add_subplot(1, 3, 3)
        ax.semilogy(np.arange(1, s.size + 1), s, "o-", ms=3, label="singular value")
        ax.set_xlabel("component")
        ax.set_ylabel("singular value")
        twin = ax.twinx()
        twin.plot(np.arange(1, s.size + 1), np.cumsum(s**2) / total_energy(group, s), "C1-",
                  label="cumulative energy")
        twin.set_ylim(0, 1.02)
        twin.set_ylabel("cumulative energy (fraction of ||A||_F^2)")
        ax.set_title(f"spectrum (rank {s.size})", fontsize=9)
    for k, which in enumerate(("light", "view")):
        ax = fig.add_subplot(1, panels, k + 1, projection="polar")
        theta, phi = getattr(d, f"theta_{which}"), getattr(d, f"phi_{which}")
        ax.scatter(np.radians(phi), theta, s=14, c=theta, cmap="viridis", vmin=0, vmax=90)
        ax.set_ylim(0, 90)
        ax.set_yticks([15, 30, 45, 60, 75, 90])
        ax.set_title(f"{len(theta)} {which} directions (radius: theta in degrees)", fontsize=9)
    fig.suptitle(f"{Path(path).name}: direction sampling")
    with atomic_output(out, directory=False, overwrite=True) as tmp:
        fig.savefig(tmp, format="png")


def format_report(report: dict[str, Any]) -> str:
    """Human-readable text of a :func:`describe` (and scan) report."""
    from dask.utils import format_bytes

    lines = [f"{report['path']}: {report['kind']} store"
             + (f", made by {report['source']}" if report.get("source") else "")]
    for name, v in report["variables"].items():
        dims = ", ".join(f"{d} {n}" for d, n in zip(v["dims"], v["shape"], strict=False))
        ratio = f" ({v['ratio']:.2f}x)" if v["ratio"] else ""
        layout = f"chunks {tuple(v['chunks'])}"
        if v["shards"]:
            layout += f" in shards {tuple(v['shards'])}"
        lines.append(f"  {name:<12} {v['dtype']:<8} ({dims})")
        lines.append(f"  {'':<12} {layout}; {' + '.join(v['codecs'])}; "
                     f"{format_bytes(v['bytes'])} -> {format_bytes(v['stored_bytes'])} on "
                     f"disk{ratio}")
    t = report["total"]
    ratio = f" (compression {t['ratio']:.2f}x)" if t["ratio"] else ""
    lines.append(f"  total: {format_bytes(t['bytes'])} in memory, "
                 f"{format_bytes(t['stored_bytes'])} on disk{ratio}")
    kind = KINDS.get(report["kind"])
    if kind is not None:
        lines += kind.lines(report)
    if report.get("levels"):
        lines.append("levels of detail: " + ", ".join(
            f"{v['level']}: {' x '.join(map(str, v['shape']))} ({v['path']})"
            for v in report["levels"]))
    attrs = report["attrs"]
    for key in ("material", "shading"):
        if key in attrs:
            lines.append(f"{key}: " + ", ".join(f"{k}={v}" for k, v in attrs[key].items()))
    if "provenance" in attrs:
        p = attrs["provenance"]
        lines.append(f"made by: {p.get('command')} (version {p.get('version')})")
    if attrs.get("computed_for_scene"):
        only = attrs["computed_for_scene"]
        lines.append(f"computed only for the scene {only['scene']}: {len(only['layers'])} of "
                     f"{only['of_layers']} layers"
                     + (f", texels {only['region']}" if only.get("region") else "")
                     + "; the rest is unwritten (NaN)")
    if "scan" in report:
        lines.append("scan:")
        lines.append(f"  {'variable':<12} {'min':>11} {'max':>11} {'mean':>11} {'NaN':>8} "
                     f"{'Inf':>6} {'negative':>9}")
        for name, s in report["scan"].items():
            def num(x):
                return f"{x:11.4g}" if x is not None else f"{'-':>11}"
            lines.append(f"  {name:<12} {num(s['min'])} {num(s['max'])} {num(s['mean'])} "
                         f"{s['nan']:>8} {s['inf']:>6} {s['negative']:>9}")
    return "\n".join(lines)


def is_source(path: str | Path) -> bool:
    """Whether ``path`` names a measured source (a file, a folder of images), not a store.

    A folder with ``zarr.json`` (or zarr v2's ``.zgroup``) is a store; a folder is a source
    when it or its subfolders hold EXR/PNG images or a manifest; a missing path is a store
    when named ``*.zarr`` or a URL, else a source.
    """
    from pipeline import storage
    from pipeline.images import IMAGE_SUFFIXES
    from pipeline.layer_files import MANIFEST

    if storage.is_url(str(path)):
        return False
    path = Path(path)
    if path.is_file():
        return True
    if not path.is_dir():
        return path.suffix.lower() != ".zarr"
    if (path / storage.ROOT).exists() or (path / ".zgroup").exists():
        return False
    folders = [path, *(d for d in path.iterdir() if d.is_dir())]
    return (path / MANIFEST).is_file() or any(
        f.suffix.lower() in IMAGE_SUFFIXES for d in folders for f in d.iterdir())


def _inspect_source(params: InspectParams) -> dict[str, Any]:
    """Describe a measured source (``btf inspect FILE.btf|ARCHIVE.zip|FOLDER|FILE.big``)."""
    from pipeline.sources import describe_source, format_source

    for flag in ("scan", "plot"):
        if getattr(params, flag):
            raise BTFError(f"{params.store}: --{flag} reads a store; a measured source is "
                           f"described from its headers (ingest it first: btf ingest "
                           f"{params.store} OUT.zarr)")
    report = describe_source(params.store)
    _print(params, report, format_source)
    return report


def _print(params: InspectParams, report: dict[str, Any], text) -> None:
    """Print ``report`` as JSON or as ``text(report)``; write it to ``--report``."""
    dumped = json.dumps(report, indent=2, default=str)
    if params.report:
        with atomic_output(params.report, directory=False, overwrite=True) as tmp:
            tmp.write_text(dumped + "\n")
    print(dumped if params.json else text(report), file=sys.stdout, flush=True)


def inspect(params: InspectParams, session: Session) -> dict[str, Any]:
    """Describe a store or a measured source; print the report (text or JSON), write files."""
    if is_source(params.store):
        return _inspect_source(params)
    try:
        report = describe(params.store)
    except BTFError as exc:
        if Path(params.store).is_dir() and not any(
                (Path(params.store) / name).exists() for name in ("zarr.json", ".zgroup")):
            raise BTFError(f"{exc}; nor a measured source (no .exr or .png images or "
                           "manifest.csv in it or its subfolders)") from None
        raise
    if params.scan:
        report["scan"] = scan(params.store, session)
    if params.plot:
        if not all(open_store(params.store, checked=False).has(n) for n in DIRECTION_COORDS):
            raise BTFError(f"{params.store}: no direction coordinates to plot")  # not a BTF
        plot_sampling(params.store, params.plot)
    _print(params, report, format_report)
    return report


STAGE = Stage("inspect", InspectParams, inspect,
              "describe a store (metadata; --scan reads the data) or a source before ingest",
              "Describe a store from its metadata: kind, variables, dims, dtypes, chunks, "
              "codecs, bytes in memory and on disk, direction sampling and provenance (and for "
              "a store ingested from a .btf file its colour model and the file's header). "
              "--scan reads the data chunk by chunk for min/max/mean and NaN/Inf/negative "
              "counts. Given a measured source instead, describe it without ingesting it, from "
              "its headers and names only: format, file size, texels, channels, directions "
              "(views x lights, the sampling named when it is ubo2014's or ubo2003's), for a "
              ".btf file its colour model, components, scalar type, cosine flag and "
              "descriptive header, the colour reading btf ingest would apply (and the option "
              "that changes it) and the store it would make, with its size. The formats of a "
              "source:\n" + formats_help() + "\nSee docs/formats.md.")
