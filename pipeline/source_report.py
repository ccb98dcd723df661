"""What ``btf inspect`` says of a measured source before it is ingested: the shared parts.

Each format (:mod:`pipeline.sources`) describes its own sources from their headers: a DFMF
file's header, a zip's central directory and first image, a folder's listing and image
headers, a BIG file's chunk table; no other image is decoded. The report says the format, the
size, the texels, channels and directions (the sampling named where it is a measured
database's), the colour reading ingest would apply, and the store ingest would make with its
size. This module holds what the formats' reports share: the directions' summary, the whole
report of an image format (:func:`layers_report`, :func:`layers_lines`) and the lines every
report begins with.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pipeline.layer_sources import LayerSource
from pipeline.stores.base import Directions
from tasks.sampling import known_sampling


def sampling_report(d: Directions) -> dict[str, Any]:
    """Counts, ranges and the recognised sampling of ``d`` (the keys of a store's summary)."""
    name = known_sampling(d.theta_view, d.phi_view, d.theta_light, d.phi_light)
    out: dict[str, Any] = {"name": name, "views": d.views, "lights": d.lights,
                           "layers": d.views * d.lights}
    for which in ("view", "light"):
        theta, phi = getattr(d, f"theta_{which}"), getattr(d, f"phi_{which}")
        out[which] = {"theta_min": float(theta.min()), "theta_max": float(theta.max()),
                      "theta_rings": len(np.unique(np.round(theta, 3))),
                      "phi_min": float(phi.min()), "phi_max": float(phi.max()),
                      # the sampling this axis alone is (an ABTF's lights, say)
                      "sampling": name or known_sampling(theta, phi, theta, phi)}
    return out


FLOAT32 = 4  # bytes of a float32 value (a DFMF file's factors become float32 factors)


def layers_report(source: LayerSource, *, kind: str, file_bytes: int,
                  directions_from: str) -> dict[str, Any]:
    """The report of an image format's source, opened with ingest's defaults.

    ``kind`` names its images, ``file_bytes`` is what it takes on disk, ``directions_from``
    says where its directions come from (the format knows these three).
    """
    d, info = source.directions, source.info
    shape = [d.views, d.lights, info.height, info.width, len(info.channels)]
    return {
        "format": source.attrs.get("format", "images"),
        "file_bytes": file_bytes,
        "images": {"count": sum(len(row) for row in source.grid), "kind": kind,
                   "first": source.first.name, "directions_from": directions_from},
        "height": info.height, "width": info.width, "channels": list(info.channels),
        "sampling": sampling_report(d),
        "colour": source.colour_note,
        "ingest": {"store": "radiance", "shape": shape, "dtype": info.precision,
                   "bytes": int(np.prod(shape)) * np.dtype(info.precision).itemsize},
        "attrs": source.attrs,
    }


def heading(report: dict[str, Any]) -> str:
    """The first line of a source's report: path, format, size."""
    from dask.utils import format_bytes

    return (f"{report['path']}: {report['format']}, {format_bytes(report['file_bytes'])} "
            "(a source: btf ingest reads it into a store)")


def texel_lines(report: dict[str, Any]) -> list[str]:
    """The texels, channels and directions of a source's report."""
    from pipeline.stores.base import sampling_lines

    s = report["sampling"]
    lines = [f"  texels {report['height']} x {report['width']} (height x width), channels "
             f"{','.join(report['channels'])}"]
    lines += sampling_lines(s)
    if not s["name"]:
        lines += [f"  {which}s are {s[which]['sampling']}'s directions"
                  for which in ("view", "light") if s[which]["sampling"]]
    return lines


def layers_lines(report: dict[str, Any]) -> list[str]:
    """The text of a :func:`layers_report`."""
    from dask.utils import format_bytes

    i, g = report["images"], report["ingest"]
    v, li, h, w, c = g["shape"]
    return [heading(report),
            f"  {i['count']} images ({i['kind']}), the first {i['first']}; directions from "
            f"{i['directions_from']}",
            *texel_lines(report),
            f"colour: {report['colour']}",
            f"btf ingest makes a radiance store of {v} views x {li} lights x {h} x {w} texels x "
            f"{c} channels, {g['dtype']}: {format_bytes(g['bytes'])} uncompressed"]

