"""The reference image of a store, which guides quilting (paper 003, section 2.2).

Computed from the layers of the view closest to the normal: per-texel sums over every light
(:mod:`tasks.reference`), reduced over blocks of lights by
:func:`pipeline.graphs.reductions.light_sums`, then the maps. ``btf reference`` writes it;
``btf quilt`` and ``btf roller --image reference`` plan on it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.errors import BTFError
from pipeline.graphs.reductions import layer_light_sums, light_sums
from pipeline.params import ParamError
from pipeline.session import Session
from pipeline.stores import CompressedStore, RadianceStore, lazy_layers, open_store
from tasks.reference import ReferenceMaps, reference_maps
from tasks.sampling import direction_vectors

WEIGHTS_HELP = "weights D,H,R of the diffuse, height and reflectance maps in the reference image"


def check_weights(text: str) -> None:
    """Raise :class:`ParamError` for ``weights`` that :func:`parse_weights` refuses."""
    try:
        parse_weights(text)
    except ValueError as exc:
        raise ParamError("weights", str(exc)) from None


def parse_weights(text: str) -> tuple[float, float, float]:
    """``"1,0.5,0.5"`` as three non-negative floats, not all zero."""
    try:
        values = tuple(float(t) for t in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or min(values) < 0 or sum(values) <= 0:
        raise ValueError(f"expected three non-negative numbers D,H,R, not all 0, got {text!r}")
    return values


def compute_reference(path: str | Path, *, weights: tuple[float, float, float],
                      view: int | None, session: Session) -> tuple[ReferenceMaps, int]:
    """The reference maps of a store, and the view they were computed from."""
    store = open_store(path, RadianceStore, CompressedStore)
    d = store.directions
    if view is None:
        view = int(np.argmin(d.theta_view))
    elif not 0 <= view < d.theta_view.size:
        raise BTFError(f"{path}: --view {view} is out of range (the store has "
                       f"{d.theta_view.size} views)")
    lights = direction_vectors(d.theta_light, d.phi_light)
    if isinstance(store, CompressedStore):  # layers reconstructed in tasks
        sums, blocks = layer_light_sums(lazy_layers(store, None)[view], lights)
    else:
        sums, blocks = light_sums(path, view, lights)
    session.log(f"reference: {blocks[1] * blocks[2]} spatial blocks x {blocks[0]} light blocks "
                f"of view {view} of {path}")
    (sums,) = session.compute(sums)
    if not np.isfinite(sums).all():
        raise BTFError(f"{path}: variable 'radiance' has NaN or Inf values in view {view}")
    return reference_maps(sums, weights=weights), view
