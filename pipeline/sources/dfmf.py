"""Bonn's UBO2014 ``.btf`` files (DFMF): a factorization per channel, a compressed store as is.

A DFMF file holds each colour channel's ``U`` and ``S V`` with a colour model
(:mod:`tasks.dfmf`), so ``btf ingest`` makes a compressed store of it without ever expanding it
to radiance (:func:`pipeline.dfmf_io.ingest_dfmf`), and ``btf inspect`` describes it from its
header alone. Bonn's files are told by their suffix or their signature.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.source_report import FLOAT32, heading, sampling_report, texel_lines
from pipeline.sources import SourceFormat
from pipeline.stores.base import Directions
from tasks.dfmf import DFMF, OTHER_SIGNATURES, DfmfError, degrees, joint_u
from tasks.transform import DFMF_MODELS


def guess_can_open(path: Path) -> bool:
    """Whether ``path`` is one of Bonn's ``.btf`` files: by its suffix or its signature.

    A missing ``.btf`` path is claimed too: its reader says it is missing.
    """
    if path.suffix.lower() == ".btf":
        return True
    if not path.is_file():
        return False
    with path.open("rb") as f:
        head = f.read(16)
    return any(head.startswith(sig) for sig in (DFMF, *OTHER_SIGNATURES))


def ingest(params, session) -> Path:
    """``btf ingest FILE.btf OUT``: the file's factors as a compressed store, no expansion.

    With ``--radiance``, every layer decoded into a radiance store instead.
    """
    from pipeline.dfmf_io import ingest_dfmf, ingest_dfmf_radiance

    return (ingest_dfmf_radiance if params.radiance else ingest_dfmf)(params, session)


def describe(path: Path) -> dict[str, Any]:
    """What ``btf inspect`` says of a DFMF file: from its header, and whether ingest takes it."""
    from pipeline.dfmf_io import DFMF_MODEL_WORDS, dfmf_colour_note, read_header

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
        "sampling": sampling_report(d),
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


def lines(report: dict[str, Any]) -> list[str]:
    """The text of a :func:`describe` report."""
    from dask.utils import format_bytes

    from pipeline.stores.compressed import dfmf_lines

    m, g = report["colour_model"], report["ingest"]
    f = g["factor_bytes"]
    out = [heading(report), *texel_lines(report),
           f"colour model {m['number']}: {m['what']} (the store's transform {m['transform']})",
           f"  {m['formula']}",
           *dfmf_lines(report["dfmf"]),
           f"colour: {report['colour']}",
           f"btf ingest makes a compressed store of rank {g['rank_at_most']} at most (the "
           "channels' components" + (", and one for the colour mean" if g["mean_component"]
                                     else "")
           + f"): U {format_bytes(f['U'])}, S {format_bytes(f['S'])}, V "
           f"{format_bytes(f['V'])} (float32, {format_bytes(g['bytes'])}); as float32 "
           f"radiance it would be {format_bytes(g['radiance_bytes'])}"]
    if g["refused"]:
        out.append(f"  but btf ingest refuses this file today: {g['refused']}")
    return out


FORMAT = SourceFormat(
    "dfmf",
    "FILE.btf, a Bonn UBO2014 DFMF file: becomes a compressed store without expansion, its "
    "factors exactly, with its colour model (--radiance: its layers decoded, a radiance "
    "store)",
    "a .btf file (Bonn DFMF)",
    suffixes=(".btf",), guess_can_open=guess_can_open,
    describe=describe, lines=lines, ingest=ingest)
