"""``btf reference`` and ``btf quilt``: seamless variation tile sets (paper 003).

``reference`` computes the reference image of a radiance or compressed store from the layers of
the view closest to the normal, one spatial block and block of lights at a time
(:mod:`tasks.reference`), and writes its maps as one EXR file.

``quilt`` plans a tile set on the reference image (:func:`tasks.quilting.plan_tiles`, on the
client: planning is sequential by nature), stores every tile's prescription, and applies them to
every layer: one task per (view, block of lights) reads whole layers of that block, as many at
a time as a memory budget allows (:data:`pipeline.tileset.APPLY_BUDGET`), and writes every
tile's layers. From a compressed store it applies them to the eigentextures instead and
the result is a compressed tile set.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import psutil

from pipeline.atomic import atomic_output
from pipeline.errors import BTFError
from pipeline.images import write_exr
from pipeline.params import ParamError, check_seed, option
from pipeline.provenance import provenance
from pipeline.runtime import Session
from pipeline.store import RADIANCE, Directions, open_group
from pipeline.tileset import open_layers, write_tileset
from tasks.canvas import TERMS
from tasks.quilting import QuiltParams, plan_tiles
from tasks.reference import ReferenceMaps, combine_light_sums, light_sums, reference_maps
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


def _sums_task(layers: np.ndarray, lights: np.ndarray):
    return light_sums(np.asarray(layers), lights)


def compute_reference(path: str | Path, *, weights: tuple[float, float, float],
                      view: int | None, session: Session) -> tuple[ReferenceMaps, int]:
    """The reference maps of a store, and the view they were computed from."""
    import dask

    ds = open_layers(path)
    d = Directions.of(ds)
    if view is None:
        view = int(np.argmin(d.theta_view))
    elif not 0 <= view < d.theta_view.size:
        raise BTFError(f"{path}: --view {view} is out of range (the store has "
                       f"{d.theta_view.size} views)")
    rad = ds[RADIANCE].data[view]
    lights = direction_vectors(d.theta_light, d.phi_light)
    lch, ych, xch, _ = rad.chunks
    ny, nx = rad.shape[1:3]
    blocks, where = [], []
    l_starts = np.cumsum((0, *lch))
    y_starts, x_starts = np.cumsum((0, *ych)), np.cumsum((0, *xch))
    for i in range(len(ych)):
        for j in range(len(xch)):
            ys = slice(int(y_starts[i]), int(y_starts[i + 1]))
            xs = slice(int(x_starts[j]), int(x_starts[j + 1]))
            parts = [dask.delayed(_sums_task, pure=True)(
                rad[int(l_starts[k]) : int(l_starts[k + 1]), ys, xs],
                lights[int(l_starts[k]) : int(l_starts[k + 1])]) for k in range(len(lch))]
            blocks.append(dask.delayed(combine_light_sums, pure=True)(parts))
            where.append((ys, xs))
    session.log(f"reference: {len(blocks)} spatial blocks x {len(lch)} light blocks of view "
                f"{view} of {path}")
    results = session.compute(*blocks)
    sums = np.empty((ny, nx, results[0].shape[-1]), np.float64)
    for (ys, xs), block in zip(where, results, strict=True):
        sums[ys, xs] = block
    if not np.isfinite(sums).all():
        raise BTFError(f"{path}: variable 'radiance' has NaN or Inf values in view {view}")
    return reference_maps(sums, weights=weights), view


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


@dataclasses.dataclass(frozen=True)
class QuiltStageParams:
    """Parameters of ``btf quilt``."""

    store: str = option(help="radiance or compressed store (the sample)", positional=True,
                        path="in", metavar="IN")
    out: str = option(help="output tile-set store (a .zarr directory)", positional=True,
                      path="out")
    block: int = option(32, metavar="B", help="patch size in texels (even)")
    overlap: int = option(8, metavar="O", help="overlap of neighbouring patches in texels")
    candidates: int = option(5, metavar="K",
                             help="a patch is drawn from the K best matching ones")
    corners: int = option(1, metavar="V", help="corner types: V^4 tiles (1: one periodic "
                                               "texture)")
    size: tuple[int, ...] | None = option(
        None, metavar="H,W", help="tile size in texels, multiples of B - O (default: the "
                                  "sample's size rounded down to such a multiple)")
    seed: int = option(0, metavar="S", help="seed of the random choices")
    weights: str = option("1,0.5,0.5", metavar="D,H,R", help=WEIGHTS_HELP)
    view: int | None = option(None, metavar="J",
                              help="view for the reference image (default: closest to normal)")
    overwrite: bool = option(False, record=False, help="replace OUT if it exists")

    def __post_init__(self):
        check_weights(self.weights)
        if self.size is not None and len(self.size) not in (1, 2):
            raise ParamError("size", f"expected H,W or N, got {self.size}")
        check_seed(self.seed)
        try:  # the planner's own checks; its messages start with the parameter's name
            self.quilt_params((max(self.block, 1) * 64,) * 2)
        except ValueError as exc:
            name = str(exc).split()[0]
            raise ParamError("size" if name == "tile" else name, str(exc)) from None

    def tile_shape(self, sample: tuple[int, int]) -> tuple[int, int]:
        """The tile size for a sample of the given size."""
        step = self.block - self.overlap
        if self.size is None:
            return tuple(max(2 * step, (n // step) * step) for n in sample)
        return (self.size[0], self.size[-1])

    def quilt_params(self, sample: tuple[int, int]) -> QuiltParams:
        """The planner's parameters for a sample of the given size."""
        return QuiltParams(self.block, self.overlap, self.candidates, self.corners,
                           self.tile_shape(sample))


def quilt(params: QuiltStageParams, session: Session) -> Path:
    """Plan a tile set on the reference image and apply it to every layer."""
    layers = open_layers(params.store)[RADIANCE]
    sample = (layers.sizes["y"], layers.sizes["x"])
    try:
        qp = params.quilt_params(sample)
        if min(sample) < params.block:
            raise ValueError(f"the sample ({sample[0]} x {sample[1]}) is smaller than a block")
    except ValueError as exc:
        raise BTFError(f"{params.store}: {exc}") from None
    need = qp.plan_bytes(sample, layers.sizes["channel"])
    available = psutil.virtual_memory().available
    if need > 0.8 * available:
        raise BTFError(f"{params.store}: planning {qp.corners ** 4} tiles of {qp.tile[0]} x "
                       f"{qp.tile[1]} texels needs about {need / 2**30:.1f} GiB, more than the "
                       f"{available / 2**30:.1f} GiB available: use fewer --corners or a "
                       "smaller --size")
    session.log(f"quilt: planning {qp.corners ** 4} tile(s) of {qp.tile[0]} x {qp.tile[1]} "
                f"texels on the {sample[0]} x {sample[1]} reference image (about "
                f"{need / 2**20:.0f} MiB)")
    maps, view = compute_reference(params.store, weights=parse_weights(params.weights),
                                   view=params.view, session=session)
    try:
        plan = plan_tiles(maps.reference, qp, seed=params.seed)
    except ValueError as exc:
        raise BTFError(f"{params.store}: {exc}") from None
    group = open_group(params.store)
    attrs = {
        "source": "quilt",
        "quilt": {**dataclasses.asdict(qp), "seed": params.seed,
                  "weights": list(parse_weights(params.weights)), "reference_view": view},
        "corner_types": qp.corners,
        "seed": params.seed,
        "placements": [{"canvas": p.canvas, "window": list(p.window),
                        "source": list(p.source), "flags": list(p.flags)}
                       for p in plan.placements],
        "provenance": provenance("quilt", params),
    }
    index = [t.index.reshape(-1, TERMS) for t in plan.tiles]
    weight = [t.weight.reshape(-1, TERMS) for t in plan.tiles]
    corners = plan.corners
    del plan  # the canvases' values and the strips are not needed any more
    with atomic_output(params.out, directory=True, overwrite=params.overwrite) as tmp:
        write_tileset(params.store, tmp, group=group, index=index, weight=weight,
                      tile_shape=qp.tile, reference=maps.reference, corners=corners,
                      attrs=attrs, session=session, label="quilt", output=params.out)
    return Path(params.out)
