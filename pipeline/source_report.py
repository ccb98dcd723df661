"""What ``btf inspect`` says of a measured source before it is ingested.

A DFMF ``.btf`` file is described from its header (:func:`pipeline.dfmf_io.read_header`); the
image formats through the source ``btf ingest`` would open
(:func:`pipeline.source_formats.open_layers`): a zip's central directory and first image, a
folder's listing and image headers, a BIG file's chunk table. No other image is decoded. The
report says the format, the size, the texels, channels and directions (the sampling named
where it is a measured database's), the colour reading ingest would apply, and the store
ingest would make with its size.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import BTFError
from pipeline.layer_files import MANIFEST
from pipeline.stores.base import Directions
from tasks.sampling import known_sampling

FLOAT32 = 4  # bytes of a stored value: every store ingest makes holds float32


def _directions(d: Directions) -> dict[str, Any]:
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


def _dfmf(path: Path) -> dict[str, Any]:
    from pipeline.dfmf_io import read_header
    from pipeline.source_formats import DFMF_MODEL_WORDS, dfmf_colour_note
    from tasks.dfmf import DfmfError, degrees, joint_u
    from tasks.transform import DFMF_MODELS

    header = read_header(path)
    d = Directions(*degrees(header.theta_view, header.phi_view),
                   *degrees(header.theta_light, header.phi_light))
    ks = [b.k for b in header.channels]
    # models 0 and 12 keep the file's channels (as ingest does); the others become RGB
    channels = (list(header.channel_names) if header.colour_model in (0, 12)
                else ["R", "G", "B"])
    refused = None
    # ingest's own combination of the channels, on one (view, light) row: whether it refuses
    # the colour model (and flags) and whether a colour mean adds a component
    one = dataclasses.replace(header, theta_view=header.theta_view[:1],
                              phi_view=header.phi_view[:1], theta_light=header.theta_light[:1],
                              phi_light=header.phi_light[:1])
    try:
        _, mean = joint_u(one, [np.zeros((1, k)) for k in ks])
    except DfmfError as exc:
        refused, mean = str(exc), False
    rank = sum(ks) + mean
    nc = len(channels)
    factors = {"U": d.views * d.lights * nc * rank * FLOAT32, "S": rank * FLOAT32,
               "V": header.height * header.width * rank * FLOAT32}
    name, formula = DFMF_MODELS[header.colour_model]
    meta = header.metadata()
    xml = header.xml.strip()
    return {
        "format": "Bonn DFMF file (UBO2014 .btf)",
        "file_bytes": path.stat().st_size,
        "height": header.height, "width": header.width, "channels": channels,
        "sampling": _directions(d),
        "colour_model": {"number": header.colour_model,
                         "what": DFMF_MODEL_WORDS.get(header.colour_model, formula),
                         "transform": name, "formula": formula},
        "dfmf": {**meta, "scalar_type": header.channels[0].dtype.name,
                 "xml_characters": len(header.xml),
                 "xml_first_line": xml.splitlines()[0] if xml else ""},
        "colour": dfmf_colour_note(header.colour_model, cosine=header.cosine),
        "ingest": {"store": "compressed", "rank_at_most": rank, "mean_component": bool(mean),
                   "factor_bytes": factors, "bytes": sum(factors.values()),
                   "radiance_bytes": d.views * d.lights * header.height * header.width * nc
                   * FLOAT32, "refused": refused},
    }


def _images(path: Path) -> dict[str, Any]:
    from pipeline.archive_sources import BigReader, ZipReader
    from pipeline.source_formats import colour_note, open_layers

    source = open_layers(path)  # ingest's defaults
    d, info, reader = source.directions, source.info, source.reader
    keys = [e.key for row in source.grid for e in row]
    if isinstance(reader, ZipReader):
        kind = "RGBE (.hdr)" if str(keys[0]).lower().endswith(".hdr") else "JPEG"
        size, origin = path.stat().st_size, "the member names"
    elif isinstance(reader, BigReader):
        kind = f"{source.attrs.get('data_type', '?')}, {len(info.channels)} plane(s)"
        size, origin = path.stat().st_size, f"its list of directions: {source.attrs['directions']}"
    else:
        kind = "/".join(sorted({Path(k).suffix.lstrip(".").upper() for k in keys}))
        size = sum(Path(k).stat().st_size for k in keys)
        origin = (MANIFEST if (path / MANIFEST).is_file()
                  else "the file names" + (", a folder per view"
                                           if Path(keys[0]).parent != path else ""))
    shape = [d.views, d.lights, info.height, info.width, len(info.channels)]
    return {
        "format": source.attrs.get("format", "images"),
        "file_bytes": size,
        "images": {"count": len(keys), "kind": kind, "first": source.first.name,
                   "directions_from": origin},
        "height": info.height, "width": info.width, "channels": list(info.channels),
        "sampling": _directions(d),
        "colour": colour_note(source),
        "ingest": {"store": "radiance", "shape": shape, "dtype": "float32",
                   "bytes": int(np.prod(shape)) * FLOAT32},
        "attrs": source.attrs,
    }


def describe_source(path: str | Path) -> dict[str, Any]:
    """The report of a measured source: format, size, directions, colour, what ingest makes.

    Raises
    ------
    BTFError
        Naming the file: a missing path, a file of no known format, a corrupt header (what
        the format's reader refuses).
    """
    from pipeline.dfmf_io import is_bonn_file

    path = Path(path)
    if not path.exists():
        raise BTFError(f"{path}: no such file, folder or store")
    report = _dfmf(path) if is_bonn_file(path) else _images(path)
    return {"path": str(path), "kind": "source", **report}


def format_source(report: dict[str, Any]) -> str:
    """Human-readable text of a :func:`describe_source` report."""
    from dask.utils import format_bytes

    from pipeline.stores.base import sampling_lines
    from pipeline.stores.compressed import dfmf_lines

    s = report["sampling"]
    lines = [f"{report['path']}: {report['format']}, {format_bytes(report['file_bytes'])} "
             "(a source: btf ingest reads it into a store)"]
    if "images" in report:
        i = report["images"]
        lines.append(f"  {i['count']} images ({i['kind']}), the first {i['first']}; directions "
                     f"from {i['directions_from']}")
    lines.append(f"  texels {report['height']} x {report['width']} (height x width), channels "
                 f"{','.join(report['channels'])}")
    lines += sampling_lines(s)
    if not s["name"]:
        lines += [f"  {which}s are {s[which]['sampling']}'s directions"
                  for which in ("view", "light") if s[which]["sampling"]]
    if "colour_model" in report:
        m = report["colour_model"]
        lines.append(f"colour model {m['number']}: {m['what']} (the store's transform "
                     f"{m['transform']})")
        lines.append(f"  {m['formula']}")
        lines += dfmf_lines(report["dfmf"])
    lines.append(f"colour: {report['colour']}")
    g = report["ingest"]
    if g["store"] == "radiance":
        v, li, h, w, c = g["shape"]
        lines.append(f"btf ingest makes a radiance store of {v} views x {li} lights x {h} x {w} "
                     f"texels x {c} channels, {g['dtype']}: {format_bytes(g['bytes'])} "
                     "uncompressed")
    else:
        f = g["factor_bytes"]
        lines.append(f"btf ingest makes a compressed store of rank {g['rank_at_most']} at most "
                     "(the channels' components"
                     + (", and one for the colour mean" if g["mean_component"] else "")
                     + "): U "
                     f"{format_bytes(f['U'])}, S {format_bytes(f['S'])}, V "
                     f"{format_bytes(f['V'])} (float32, {format_bytes(g['bytes'])}); as float32 "
                     f"radiance it would be {format_bytes(g['radiance_bytes'])}")
        if g["refused"]:
            lines.append(f"  but btf ingest refuses this file today: {g['refused']}")
    return "\n".join(lines)
