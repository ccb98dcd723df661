"""What a scene needs of the store it reads: its layers, its level-n window, their weights.

Shared by ``btf scene`` (which reads exactly that), by the stages that make the store a scene
will read and can restrict their work to it (``--for-scene`` of reconstruct, quilt and roller)
and by the run planner (:mod:`pipeline.config`), so that none of them imports another stage.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from pipeline.scene_spec import SceneSpec, load
from pipeline.session import Session


def resolve(spec: SceneSpec, d) -> tuple[Any, np.ndarray, list]:
    """Requested directions ``(n, 4)``, their ``(direction, layer)`` weights and the layers.

    ``d`` holds the source's measured :class:`~pipeline.stores.base.Directions`. ``all``
    gives every measured layer, view-major, with identity weights.
    """
    from scipy import sparse

    from tasks.directions import pair_weights

    if spec.directions is None:
        layers = [(v, li) for v in range(d.views) for li in range(d.lights)]
        rows = np.array([[d.theta_light[li], d.phi_light[li], d.theta_view[v], d.phi_view[v]]
                         for v, li in layers])
        return rows, sparse.identity(len(layers), format="csr"), layers
    terms = pair_weights((d.theta_light, d.phi_light), (d.theta_view, d.phi_view),
                         spec.directions, spec.interpolation)
    layers = sorted({(v, li) for t in terms for v, li, _ in t})
    column = {pair: k for k, pair in enumerate(layers)}
    entries = [(i, column[(v, li)], w) for i, t in enumerate(terms) for v, li, w in t]
    rows, cols, values = (np.array(x) for x in zip(*entries, strict=True))
    weights = sparse.csr_matrix((values, (rows, cols)), shape=(len(terms), len(layers)))
    weights.sort_indices()
    return spec.directions, weights, layers


@dataclasses.dataclass(frozen=True)
class Needs:
    """What a scene needs of the store it reads: layers, and level-0 texels (None: all)."""

    layers: frozenset
    window: tuple[int, int, int, int] | None
    of: int  # layers of the store

    def keeps(self, view: int, lights: range, ys: slice | None = None,
              xs: slice | None = None) -> bool:
        """Whether a block of one view, some lights and texels holds anything needed."""
        if not any((view, li) in self.layers for li in lights):
            return False
        if self.window is None or ys is None:
            return True
        y0, y1, x0, x1 = self.window
        return ys.start < y1 and ys.stop > y0 and xs.start < x1 and xs.stop > x0

    def record(self, spec_path: str) -> dict:
        """The ``computed_for_scene`` attribute of a store restricted to these needs."""
        return {"scene": spec_path, "layers": sorted([list(p) for p in self.layers]),
                "of_layers": self.of, "region": None if self.window is None
                else list(self.window)}


def needs_of(spec: SceneSpec, directions, shape: tuple[int, int] | None = None) -> Needs:
    """The layers (and, for a bounded source of ``shape``, level-0 texels) a scene reads.

    ``directions`` are those of the store the scene will read (the same as its producer's
    input: reconstruct and quilt keep them).
    """
    _, _, layers = resolve(spec, directions)
    window = None
    if shape is not None:
        f = 2**spec.level
        y0, y1, x0, x1 = level_window(spec, *shape, spec.level)
        window = (y0 * f, y1 * f, x0 * f, x1 * f)
    return Needs(frozenset(layers), window, directions.views * directions.lights)


def spec_for_output(for_scene: str, out: str) -> SceneSpec:
    """The ``--for-scene`` spec of a stage writing ``out``; its error unless it reads ``out``."""
    import os

    spec = load(for_scene)
    if os.path.abspath(spec.source) != os.path.abspath(out):
        raise spec.error("source", f"the scene reads {spec.source}, not this stage's output "
                                   f"{out}")
    return spec


def tileset_needs(for_scene: str | None, store: str, out: str, session: Session, *,
                  label: str) -> Needs | None:
    """The layers a ``--for-scene`` spec reads of a tile set ``out`` made from ``store``.

    None (every layer) without a spec, or for a compressed source: the tiles' eigentextures
    serve every layer. Raises the spec's error when it reads another store than ``out``.
    """
    from pipeline.stores import CompressedStore, open_store

    if for_scene is None:
        return None
    spec = spec_for_output(for_scene, out)
    source = open_store(store)
    if isinstance(source, CompressedStore):
        session.log(f"{label}: the scene cannot restrict a compressed source: the tiles' "
                    "eigentextures serve every layer")
        return None
    needs = needs_of(spec, source.directions)
    session.log(f"{label}: applying the prescriptions only to the {len(needs.layers)} of "
                f"{needs.of} layers {for_scene} needs")
    return needs


def level_window(spec: SceneSpec, ny: int, nx: int, level: int,
                  session: Session | None = None) -> tuple[int, int, int, int]:
    """Level-n texels of a bounded source's region (the whole store without one).

    A region that does not fall on whole level-n texels is widened to them, and cut at the
    edge texels the level leaves out; the log says so.
    """
    y0, y1, x0, x1 = spec.region or (0, ny, 0, nx)
    if y1 > ny or x1 > nx:
        raise spec.error("region", f"{list(spec.region)} reaches beyond the source's {ny} x "
                                   f"{nx} texels")
    f = 2**level
    ly, lx = ny // f, nx // f
    if ly < 1 or lx < 1:
        raise spec.error("level", f"level {level} would shrink the source's {ny} x {nx} "
                                  "texels below one texel")
    window = (y0 // f, min(-(-y1 // f), ly), x0 // f, min(-(-x1 // f), lx))
    if window[1] <= window[0] or window[3] <= window[2]:
        raise spec.error("region", f"{list(spec.region)} lies in the edge texels that level "
                                   f"{level} leaves out (its {ly} x {lx} texels cover "
                                   f"{ly * f} x {lx * f} of level 0)")
    if session is not None:
        asked = f"region {list(spec.region)}" if spec.region else f"the whole {ny} x {nx}"
        say_widened(session, asked, level, window, (y0, y1, x0, x1))
    return window


def say_widened(session: Session, asked: str, level: int, window, wanted) -> None:
    """Log it when the level-n ``window`` does not cover exactly the level-0 texels wanted."""
    f = 2**level
    covered = [c * f for c in window]
    if covered != list(wanted):
        cut = (", cut at the edge the level leaves out"
               if covered[1] < wanted[1] or covered[3] < wanted[3] else "")
        session.log(f"scene: {asked} at level {level} is the level's texels {list(window)}, "
                    f"which cover {covered} of level 0 (whole {f} x {f} blocks{cut})")
