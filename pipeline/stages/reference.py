"""``btf reference``: the reference image that guides quilting (paper 003, section 2.2).

The reference image of a radiance or compressed store is computed from the layers of the view
closest to the normal: per-texel sums over every light (:mod:`tasks.reference`), reduced over
blocks of lights by :func:`pipeline.graphs.reductions.light_sums`, then the maps. ``btf quilt``
and ``btf roller --image reference`` plan on the same image
(:func:`pipeline.graphs.reference.compute_reference`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from pipeline.atomic import atomic_output
from pipeline.graphs.reference import WEIGHTS_HELP, check_weights, compute_reference, parse_weights
from pipeline.images import write_exr
from pipeline.params import option
from pipeline.session import Session
from pipeline.stage import Stage
from tasks.reference import ReferenceMaps


def write_reference(maps: ReferenceMaps, path: str | Path) -> None:
    """All maps of a reference image as one EXR file (``diffuse.R``, ``height.Y``, ...)."""
    planes = [maps.diffuse, maps.height[..., None], maps.reflectance[..., None], maps.normal,
              maps.reference]
    names = ("diffuse.R", "diffuse.G", "diffuse.B", "height.Y", "reflectance.Y", "normal.X",
             "normal.Y", "normal.Z", "reference.R", "reference.G", "reference.B")
    write_exr(path, np.concatenate(planes, axis=-1), names)


@dataclasses.dataclass(frozen=True)
class ReferenceParams:
    """Parameters of ``btf reference``."""

    store: str = option(help="radiance or compressed store", positional=True, path="in",
                        metavar="IN")
    out: str = option(help="EXR file for the maps and the reference image", positional=True,
                      path="out")
    weights: str = option("1,0.5,0.5", metavar="D,H,R", help=WEIGHTS_HELP)
    view: int | None = option(None, metavar="J",
                              help="view to use (default: the one closest to the normal)")
    overwrite: bool = option(False, record=False, help="replace OUT if it exists")

    def __post_init__(self):
        check_weights(self.weights)


def reference(params: ReferenceParams, session: Session) -> Path:
    """Write the reference maps of a store as EXR."""
    maps, view = compute_reference(params.store, weights=parse_weights(params.weights),
                                   view=params.view, session=session)
    with atomic_output(params.out, directory=False, overwrite=params.overwrite) as tmp:
        write_reference(maps, tmp)
    session.log(f"reference: maps of view {view} -> {params.out}")
    return Path(params.out)


STAGE = Stage("reference", ReferenceParams, reference,
              "write the reference image that guides quilting (paper 003, 2.2)",
              "Compute, from all layers of the view closest to the normal, the diffuse map, "
              "a normal map from the strongest response per texel, the height map integrated "
              "from it (Frankot-Chellappa), a reflectance map from two normal estimates with "
              "different exponents, and their weighted combination; write them as one EXR.")
