"""``btf inspect``: what a store holds, from its metadata; its values only when asked.

By default only metadata is read (array shapes, chunking, codecs, attrs, bytes on disk from the
file listing, and the small direction coordinates). ``--scan`` reads every data variable chunk
by chunk (:mod:`tasks.stats`), ``--plot`` draws the direction sampling on the hemisphere. Stage
specific summaries are looked up by the store's ``btf_kind`` in :data:`SUMMARIES`, so later
stages add theirs without touching the rest.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.atomic import atomic_output
from pipeline.errors import BTFError
from pipeline.params import option
from pipeline.runtime import Session
from pipeline.store import (
    DIRECTION_COORDS,
    RADIANCE,
    block_regions,
    location,
    open_group,
    read_directions,
)
from tasks.stats import chunk_stats, combine_stats, finalize_stats


@dataclasses.dataclass(frozen=True)
class InspectParams:
    """Parameters of ``btf inspect``."""

    store: str = option(help="zarr store to describe", positional=True, path="in")
    json: bool = option(False, help="print one JSON object instead of text")
    scan: bool = option(False, help="read all data chunk by chunk: min, max, mean, NaN/Inf "
                                    "and negative counts per variable")
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


def _rings(theta: np.ndarray) -> int:
    return len(np.unique(np.round(theta, 3)))


def sampling_summary(group) -> dict[str, Any]:
    """Counts and ranges of a radiance store's view and light directions."""
    d = read_directions(group)
    name = group.attrs.get("sampling") or group.attrs.get("source_sampling")
    out: dict[str, Any] = {"name": name,
                           "views": int(d.theta_view.size), "lights": int(d.theta_light.size),
                           "layers": int(d.theta_view.size * d.theta_light.size)}
    for which in ("view", "light"):
        theta, phi = getattr(d, f"theta_{which}"), getattr(d, f"phi_{which}")
        out[which] = {"theta_min": float(theta.min()), "theta_max": float(theta.max()),
                      "theta_rings": _rings(theta), "phi_min": float(phi.min()),
                      "phi_max": float(phi.max())}
    return out


def _radiance_summary(group) -> dict[str, Any]:
    return {"sampling": sampling_summary(group)} if RADIANCE in group.array_keys() else {}


def _total_energy(group, s: np.ndarray) -> float:
    """``||A||_F^2`` of the compressed matrix (from the stored error), else ``sum S^2``."""
    norm = (group.attrs.get("error") or {}).get("frobenius_norm")
    return float(norm) ** 2 if norm else max(float(np.sum(s**2)), 1e-300)


def _compressed_summary(group) -> dict[str, Any]:
    s = np.asarray(group["S"][:], np.float64)
    energy = np.cumsum(s**2) / _total_energy(group, s)
    nv, nl, ny, nx, nc = group.attrs.get("source_shape", [0] * 5)
    rank = int(s.size)
    original = nv * nl * ny * nx * nc * 4
    factors = (nv * nl * nc + ny * nx + 1) * rank * 4
    stored = sum(int(group[n].nbytes_stored()) for n in ("U", "S", "V"))
    return {
        "sampling": sampling_summary(group),
        "compression": {
            "rank": rank,
            "singular_values": s.tolist(),
            "energy_captured": {str(k): float(energy[k - 1]) for k in
                                sorted({1, 2, 4, 8, 16, 32, 64, 128, 256, rank}) if k <= rank},
            "error": group.attrs.get("error"),
            "svd": group.attrs.get("svd"),
            "transform": group.attrs.get("transform"),
            "original_bytes": original,
            "factor_bytes": factors,
            "ratio": original / factors if factors else None,
            "ratio_on_disk": original / stored if stored else None,
        },
    }


def _tileset_summary(group) -> dict[str, Any]:
    attrs = group.attrs
    source = np.prod(attrs["sample_shape"]) * group["theta_view"].shape[0] * group[
        "theta_light"].shape[0] * group["channel"].shape[0] * 4
    tiles = group["corners"].shape[0]
    return {"sampling": sampling_summary(group),
            "tileset": {"tiles": tiles, "corner_types": attrs.get("corner_types"),
                        "tile_shape": attrs.get("tile_shape"),
                        "sample_shape": attrs.get("sample_shape"),
                        "lattice": attrs.get("lattice"), "planner": attrs.get("quilt")
                        or attrs.get("roller"),
                        "size_vs_source": (tiles * np.prod(attrs["tile_shape"])
                                           / np.prod(attrs["sample_shape"])),
                        "source_bytes": int(source)}}


def _fit_summary(group) -> dict[str, Any]:
    attrs = group.attrs
    return {"sampling": sampling_summary(group),
            "fit": {"rotations": len(attrs["rotations"]), "elevations": len(attrs["elevations"]),
                    "parameters": attrs["parameters"], "error": attrs.get("fit_error"),
                    "size_ratio": attrs.get("size_ratio")}}


def _surface_summary(group) -> dict[str, Any]:
    attrs = group.attrs
    return {"surface": {key: attrs.get(key) for key in ("tileset", "light", "view", "origin",
                                                          "seed")}
            | {"shape": list(group[RADIANCE].shape)}}


# Stage-specific summaries by btf_kind; later stages register theirs here.
SUMMARIES: dict[str, Callable[[Any], dict[str, Any]]] = {
    "btf": _radiance_summary,
    "abtf": _radiance_summary,
    "compressed": _compressed_summary,
    "tileset": _tileset_summary,
    "compressed-tileset": _tileset_summary,
    "hls-fit": _fit_summary,
    "surface": _surface_summary,
}


def describe(path: str | Path) -> dict[str, Any]:
    """Metadata report of a store (no data is read beyond coordinate arrays)."""
    group = open_group(path)
    variables = {name: _variable(group[name]) for name in sorted(group.array_keys())}
    nbytes = sum(v["bytes"] for v in variables.values())
    stored = sum(v["stored_bytes"] for v in variables.values())
    attrs = dict(group.attrs)
    report = {
        "path": str(path),
        "kind": attrs.get("btf_kind", "unknown"),
        "source": attrs.get("source"),
        "variables": variables,
        "total": {"bytes": nbytes, "stored_bytes": stored,
                  "ratio": nbytes / stored if stored else None},
        "attrs": attrs,
    }
    summary = SUMMARIES.get(report["kind"])
    if summary is not None:
        report.update(summary(group))
    return report


def _shard_summary(store: str, name: str, region: tuple[slice, ...]) -> np.ndarray:
    import zarr

    try:
        block = zarr.open_array(store, path=name, mode="r")[region]
    except Exception as exc:  # re-raised with the chunk's key, whatever the codec raised
        where = ", ".join(f"{r.start}:{r.stop}" for r in region)
        raise BTFError(f"{store}: variable {name!r}, block [{where}] is unreadable: "
                       f"{type(exc).__name__}: {exc}") from None
    return chunk_stats(block)


def scan(path: str | Path, session: Session) -> dict[str, dict[str, Any]]:
    """Statistics of every numeric array, one task per shard (memory: one shard per worker)."""
    import dask

    group = open_group(path)
    names = [n for n in sorted(group.array_keys()) if group[n].dtype.kind in "fiu"
             and n not in DIRECTION_COORDS]
    tasks = {}
    for name in names:
        array = group[name]
        tasks[name] = [dask.delayed(_shard_summary, pure=True)(location(path), name, region)
                       for region in block_regions(array)]
    session.log(f"scan: {len(names)} variable(s) of {path}")
    results = session.compute(*(t for name in names for t in tasks[name]))
    out, k = {}, 0
    for name in names:
        n = len(tasks[name])
        out[name] = finalize_stats(combine_stats(np.stack(results[k : k + n])))
        k += n
    return out


def plot_sampling(path: str | Path, out: str | Path) -> None:
    """Draw light and view directions on the hemisphere (polar: radius theta, angle phi).

    For a compressed store, a third panel draws the singular values and the energy captured.
    """
    from matplotlib.figure import Figure

    group = open_group(path)
    d = read_directions(group)
    compressed = group.attrs.get("btf_kind") == "compressed"
    panels = 3 if compressed else 2
    fig = Figure(figsize=(4.6 * panels, 4.6), layout="constrained")
    if compressed:
        s = np.asarray(group["S"][:], np.float64)
        ax = fig.add_subplot(1, 3, 3)
        ax.semilogy(np.arange(1, s.size + 1), s, "o-", ms=3, label="singular value")
        ax.set_xlabel("component")
        ax.set_ylabel("singular value")
        twin = ax.twinx()
        twin.plot(np.arange(1, s.size + 1), np.cumsum(s**2) / _total_energy(group, s), "C1-",
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


def _size(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    raise AssertionError


def format_report(report: dict[str, Any]) -> str:
    """Human-readable text of a :func:`describe` (and scan) report."""
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
                     f"{_size(v['bytes'])} -> {_size(v['stored_bytes'])} on disk{ratio}")
    t = report["total"]
    ratio = f" (compression {t['ratio']:.2f}x)" if t["ratio"] else ""
    lines.append(f"  total: {_size(t['bytes'])} in memory, {_size(t['stored_bytes'])} on "
                 f"disk{ratio}")
    if "sampling" in report:
        s = report["sampling"]
        lines.append(f"sampling: {s['name'] or 'unnamed'}: {s['views']} view(s) x "
                     f"{s['lights']} light(s) = {s['layers']} layers")
        for which in ("view", "light"):
            w = s[which]
            lines.append(f"  {which:<5} theta {w['theta_min']:.1f}-{w['theta_max']:.1f} deg on "
                         f"{w['theta_rings']} ring(s), phi {w['phi_min']:.1f}-"
                         f"{w['phi_max']:.1f} deg")
    if "compression" in report:
        c = report["compression"]
        s = c["singular_values"]
        err = c["error"] or {}
        lines.append(f"compression: rank {c['rank']}, {c['ratio']:.1f}x smaller than the "
                     f"float32 radiance ({c['ratio_on_disk']:.1f}x on disk)")
        lines.append(f"  singular values {s[0]:.4g} ... {s[-1]:.4g}; share of ||A||^2 captured: "
                     + ", ".join(f"{k}: {v:.6f}" for k, v in c["energy_captured"].items()))
        if "log_relative_frobenius" in err:
            lines.append(f"  relative error (log domain): {err['log_relative_frobenius']:.4g}"
                         + (f"; average ABRDF RMSE (linear): {err['abrdf_rmse']:.4g}"
                            if "abrdf_rmse" in err else ""))
        if c["svd"]:
            lines.append("  " + ", ".join(f"{k}={v}" for k, v in c["svd"].items()))
    if "tileset" in report:
        t = report["tileset"]
        lines.append(f"tile set: {t['tiles']} tile(s) of {t['tile_shape'][0]} x "
                     f"{t['tile_shape'][1]} texels, {t['corner_types']} corner type(s), from a "
                     f"{t['sample_shape'][0]} x {t['sample_shape'][1]} sample "
                     f"({t['size_vs_source']:.2f}x its texels)")
        lat = t["lattice"]
        if lat:
            for name, vec, n, a in zip("uv", (lat["u"], lat["v"]), lat["lengths_px"],
                                       lat["angles_deg"], strict=True):
                lines.append(f"  lattice {name} = [{vec[0]:.2f}, {vec[1]:.2f}] ({n:.2f} px at "
                             f"{a:.1f} deg)")
            lines.append(f"  confidence {lat['confidence']:.2f}; each tile spans U = {lat['U']}, "
                         f"V = {lat['V']} ({lat['periods'][0]} x {lat['periods'][1]} periods), "
                         f"stored as {lat['hnf'][0]} x {lat['hnf'][1]} (Hermite layout, shear "
                         f"{lat['hnf'][2]})")
        lines.append(f"  size relative to the sample: 1 : {1 / t['size_vs_source']:.2f}")
    if "fit" in report:
        f = report["fit"]
        err = f["error"] or {}
        ratio = f["size_ratio"] or 1.0
        size = (f"{ratio:.2f}x smaller than" if ratio >= 1 else f"{1 / ratio:.2f}x larger than")
        lines.append(f"HLS fit: {f['rotations']} rotations x {f['elevations']} elevations, "
                     f"{f['parameters']} parameters per rotation; {size} the input; error "
                     f"(linear RGB) RMSE {err.get('rmse', 0):.4g}, max {err.get('max', 0):.4g}")
    if "surface" in report:
        f = report["surface"]
        lines.append(f"surface: {f['shape'][0]} x {f['shape'][1]} texels of light {f['light']}"
                     f", view {f['view']} at {tuple(f['origin'])}, seed {f['seed']}, from "
                     f"{f['tileset']}")
    attrs = report["attrs"]
    for key in ("material", "shading"):
        if key in attrs:
            lines.append(f"{key}: " + ", ".join(f"{k}={v}" for k, v in attrs[key].items()))
    if "provenance" in attrs:
        p = attrs["provenance"]
        lines.append(f"made by: {p.get('command')} (version {p.get('version')})")
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


def inspect(params: InspectParams, session: Session) -> dict[str, Any]:
    """Describe a store; print the report (text or JSON) and write the optional files."""
    report = describe(params.store)
    if params.scan:
        report["scan"] = scan(params.store, session)
    if params.plot:
        if not set(DIRECTION_COORDS) <= set(open_group(params.store).array_keys()):
            raise BTFError(f"{params.store}: no direction coordinates to plot")  # not a BTF
        plot_sampling(params.store, params.plot)
    text = json.dumps(report, indent=2, default=str)
    if params.report:
        with atomic_output(params.report, directory=False, overwrite=True) as tmp:
            tmp.write_text(text + "\n")
    print(text if params.json else format_report(report), file=sys.stdout, flush=True)
    return report
