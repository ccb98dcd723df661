"""``btf quilt``: seamless variation tile sets (paper 003).

Plans a tile set on the reference image (:func:`tasks.quilting.plan_tiles`, on the client:
planning is sequential by nature), stores every tile's prescription, and applies them to every
layer (:mod:`pipeline.graphs.prescriptions`): one task per (view, block of lights) reads whole
layers of that block, as many at a time as a memory budget allows, and writes every tile's
layers. From a compressed store it applies them to the eigentextures instead and the result is
a compressed tile set.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import psutil

from pipeline.errors import BTFError
from pipeline.graphs.prescriptions import write_tileset
from pipeline.params import ParamError, check_seed, option
from pipeline.provenance import provenance
from pipeline.session import Session
from pipeline.stages.reference import WEIGHTS_HELP, check_weights, compute_reference, parse_weights
from pipeline.stores import open_layers
from pipeline.stores.base import RADIANCE
from pipeline.stores.tileset import TileSet
from tasks.canvas import TERMS
from tasks.quilting import QuiltParams, choose_block, overlap_for, plan_tiles


@dataclasses.dataclass(frozen=True)
class QuiltStageParams:
    """Parameters of ``btf quilt``."""

    store: str = option(help="radiance or compressed store (the sample)", positional=True,
                        path="in", metavar="IN")
    out: str = option(help="output tile-set store (a .zarr directory)", positional=True,
                      path="out")
    block: int | None = option(
        None, metavar="B", help="patch size in texels (even; default: one period of the "
                                "sample's lattice, within 16-96, or 32 without a clear lattice)")
    overlap: int | None = option(None, metavar="O", help="overlap of neighbouring patches in "
                                                         "texels (default: a quarter of B)")
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
    for_scene: str | None = option(
        None, metavar="SCENE.yaml", path="in",
        help="apply the plan only to the layers this scene spec (or a run config's scene: "
             "section) reads of OUT (radiance sources; the eigentextures of a compressed "
             "one serve every layer); the others stay unwritten")
    overwrite: bool = option(False, record=False, help="replace OUT if it exists")

    def __post_init__(self):
        check_weights(self.weights)
        if self.size is not None and len(self.size) not in (1, 2):
            raise ParamError("size", f"expected H,W or N, got {self.size}")
        check_seed(self.seed)
        if self.block is not None:  # the planner's own checks, under this stage's names
            self.quilt_params((max(self.block, 1) * 64,) * 2, self.block, self.overlap)

    def tile_shape(self, sample: tuple[int, int], step: int) -> tuple[int, int]:
        """The tile size for a sample of the given size."""
        if self.size is None:
            return tuple(max(2 * step, (n // step) * step) for n in sample)
        return (self.size[0], self.size[-1])

    def quilt_params(self, sample: tuple[int, int], block: int, overlap: int | None
                     ) -> QuiltParams:
        """The planner's parameters for a sample of the given size and the block."""
        overlap = overlap_for(block) if overlap is None else overlap
        try:
            return QuiltParams(block, overlap, self.candidates, self.corners,
                               self.tile_shape(sample, block - overlap))
        except ParamError as exc:
            raise ParamError({"tile": "size"}.get(exc.name, exc.name), exc.message) from None


def quilt(params: QuiltStageParams, session: Session) -> Path:
    """Plan a tile set on the reference image and apply it to every layer."""
    from pipeline.stages.scene import tileset_needs

    # a bad scene spec stops before the planning
    needs = tileset_needs(params.for_scene, params.store, params.out, session, label="quilt")
    layers = open_layers(params.store)[RADIANCE]
    sample = (layers.sizes["y"], layers.sizes["x"])
    if params.block is not None and min(sample) < params.block:
        raise BTFError(f"{params.store}: the sample ({sample[0]} x {sample[1]}) is smaller "
                       f"than a block ({params.block})")
    maps, view = compute_reference(params.store, weights=parse_weights(params.weights),
                                   view=params.view, session=session)
    block, overlap = params.block, params.overlap
    if block is None:
        tile = None if params.size is None else (params.size[0], params.size[-1])
        block, auto_overlap, why = choose_block(maps.reference, tile=tile)
        overlap = auto_overlap if overlap is None else overlap
        session.log(f"quilt: block {block}, overlap {overlap}: {why}")
        if min(sample) < block:
            raise BTFError(f"{params.store}: the sample ({sample[0]} x {sample[1]}) is smaller "
                           f"than a block ({block}); give a smaller --block")
    try:
        qp = params.quilt_params(sample, block, overlap)
    except ParamError as exc:  # with the automatic block: name the option to give
        raise BTFError(f"--{exc.name} (with --block {block}): {exc.message}") from None
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
    try:
        plan = plan_tiles(maps.reference, qp, seed=params.seed)
    except ValueError as exc:
        raise BTFError(f"{params.store}: {exc}") from None
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
    if needs is not None:
        attrs["computed_for_scene"] = needs.record(params.for_scene)
    tiles = TileSet(index=[t.index.reshape(-1, TERMS) for t in plan.tiles],
                    weight=[t.weight.reshape(-1, TERMS) for t in plan.tiles],
                    tile_shape=qp.tile, corners=plan.corners, reference=maps.reference,
                    attrs=attrs)
    del plan  # the canvases' values and the strips are not needed any more
    return write_tileset(tiles, params.out, source=params.store, session=session,
                         label="quilt", overwrite=params.overwrite, needs=needs)
