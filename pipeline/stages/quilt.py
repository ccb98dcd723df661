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
import math
from pathlib import Path

import psutil

from pipeline.errors import BTFError
from pipeline.graphs.prescriptions import write_tileset
from pipeline.graphs.reference import WEIGHTS_HELP, check_weights, compute_reference, parse_weights
from pipeline.params import ParamError, check_seed, option
from pipeline.planning import Shape, StageEstimate, rate
from pipeline.provenance import provenance
from pipeline.session import Session
from pipeline.stage import Stage, for_scene_option, same_directions
from pipeline.stores import CompressedStore, RadianceStore, open_store
from pipeline.stores.tileset import Placement, TileSet
from tasks.canvas import TERMS
from tasks.corner_tiles import plan_first
from tasks.quilt_layout import (
    commensurate_sizes,
    default_tile,
    layouts,
    overlap_for,
    phase_lattice,
    sample_lattice,
    tile_mismatch,
)
from tasks.quilting import QuiltParams


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
    max_seam: float = option(
        1.3, metavar="R", help="the most any tile border may stand out from the tile's inside "
                               "(seam and structure ratios; tiles are planned again until "
                               "they pass, a bounded number of times, else quilt stops)")
    weights: str = option("1,0.5,0.5", metavar="D,H,R", help=WEIGHTS_HELP)
    view: int | None = option(None, metavar="J",
                              help="view for the reference image (default: closest to normal)")
    for_scene: str | None = for_scene_option()
    overwrite: bool = option(False, record=False, help="replace OUT if it exists")

    def __post_init__(self):
        check_weights(self.weights)
        if self.size is not None and len(self.size) not in (1, 2):
            raise ParamError("size", f"expected H,W or N, got {self.size}")
        check_seed(self.seed)
        if not self.max_seam > 0:
            raise ParamError("max_seam", f"must be positive, got {self.max_seam}")
        if self.block is not None:  # the planner's own checks, under this stage's names
            overlap = overlap_for(self.block) if self.overlap is None else self.overlap
            self.quilt_params(self.block, overlap, self.tile_shape(
                (max(self.block, 1) * 64,) * 2, self.block - overlap))

    @property
    def tile(self) -> tuple[int, int] | None:
        """The given tile size, if any."""
        return None if self.size is None else (self.size[0], self.size[-1])

    def tile_shape(self, sample: tuple[int, int], step: int) -> tuple[int, int]:
        """The tile size for a sample of the given size (without its lattice: for plans)."""
        return self.tile or default_tile(sample, step, None)

    def quilt_params(self, block: int, overlap: int, tile: tuple[int, int],
                     lattice=None) -> QuiltParams:
        """The planner's parameters."""
        try:
            return QuiltParams(block, overlap, self.candidates, self.corners, tile,
                               max_seam=self.max_seam, lattice=lattice)
        except ParamError as exc:
            raise ParamError({"tile": "size"}.get(exc.name, exc.name), exc.message) from None


def quilt(params: QuiltStageParams, session: Session) -> Path:
    """Plan a tile set on the reference image and apply it to every layer."""
    from pipeline.scene_needs import tileset_needs

    # a bad scene spec stops before the planning
    needs = tileset_needs(params.for_scene, params.store, params.out, session, label="quilt")
    _, _, ny, nx, channels = open_store(params.store, RadianceStore, CompressedStore).shape
    sample = (ny, nx)
    if params.block is not None and min(sample) < params.block:
        raise BTFError(f"{params.store}: the sample ({sample[0]} x {sample[1]}) is smaller "
                       f"than a block ({params.block})")
    record = provenance("quilt", params)

    def plan_tiles() -> TileSet:  # not called when a killed run's stored plan is resumed
        maps, view = compute_reference(params.store, weights=parse_weights(params.weights),
                                       view=params.view, session=session)
        plan, qp = _plan(params, maps.reference, sample, channels, session)
        return _tileset(params, plan, qp, maps.reference, view, record, needs)

    return write_tileset(plan_tiles, params.out, source=params.store, session=session,
                         label="quilt", overwrite=params.overwrite, needs=needs, record=record)


def _tileset(params: QuiltStageParams, plan, qp: QuiltParams, reference,
             view: int, record: dict, needs) -> TileSet:
    """The planned tile set with the store's record of how it was planned."""
    attrs = {
        "source": "quilt",
        "quilt": {**dataclasses.asdict(qp), "seed": params.seed,
                  "weights": list(parse_weights(params.weights)), "reference_view": view},
        "border_check": {"bound": qp.max_seam, "tiles": [c.to_dict() for c in plan.checks]},
        "placements": [{"canvas": p.canvas, "window": list(p.window),
                        "source": list(p.source), "flags": list(p.flags)}
                       for p in plan.placements],
        "provenance": record,
    }
    if needs is not None:
        attrs["computed_for_scene"] = needs.record(params.for_scene)
    return TileSet(index=[t.index.reshape(-1, TERMS) for t in plan.tiles],
                   weight=[t.weight.reshape(-1, TERMS) for t in plan.tiles],
                   tile_shape=qp.tile, corners=plan.corners, reference=reference,
                   attrs=attrs, placement=Placement("corners", qp.corners, params.seed))


def _plan(params: QuiltStageParams, reference, sample: tuple[int, int], channels: int,
          session: Session):
    """The tile set's plan and its parameters: the first layout whose borders pass."""
    lattice = sample_lattice(reference)
    if lattice is not None:
        session.log(f"quilt: the sample repeats every {lattice.lengths_px[0]:.1f} and "
                    f"{lattice.lengths_px[1]:.1f} texels (confidence {lattice.confidence:.2f})")

    def candidates():
        for layout in layouts(reference, block=params.block, overlap=params.overlap,
                              tile=params.tile, lattice=lattice):
            if min(sample) < layout.block:
                raise BTFError(f"{params.store}: the sample ({sample[0]} x {sample[1]}) is "
                               f"smaller than a block ({layout.block})"
                               + ("; give a smaller --block" if params.block is None else ""))
            if layout.why != "given":
                session.log(f"quilt: block {layout.block}, overlap {layout.overlap}: "
                            f"{layout.why}")
            try:
                qp = params.quilt_params(layout.block, layout.overlap, layout.tile,
                                         phase_lattice(lattice, sample))
            except ParamError as exc:  # with the automatic block: name the option to give
                raise BTFError(f"--{exc.name} (with --block {layout.block}): {exc.message}"
                               ) from None
            _check_phase(params, qp, lattice, session)
            _check_memory(params, qp, sample, channels, session)
            yield qp

    try:
        plan, qp = plan_first(reference, candidates(), seed=params.seed,
                              on_failure=lambda exc: session.log(f"quilt: {exc}"),
                              progress=lambda line: session.log(f"quilt: {line}"),
                              threads=planning_threads(session))
    except ValueError as exc:  # SeamError too: the last layout's
        raise BTFError(f"{params.store}: {exc}") from None
    worst = max(plan.checks, key=lambda c: c.figures.worst)
    session.log(f"quilt: every tile border within {qp.max_seam}x of its tile's inside "
                f"(worst {worst.tile}: {worst.figures.worst_line()}; up to "
                f"{max(c.plans for c in plan.checks)} plan(s) of a tile's interior)")
    return plan, qp


def planning_threads(session: Session) -> int:
    """Tiles the client plans at once: ``--workers``, else one per core; one when synchronous.

    The plan is the same for any number (:func:`tasks.corner_tiles.plan_tiles`).
    """
    if session.options.scheduler == "synchronous":
        return 1
    return session.options.local_workers()


def _check_phase(params: QuiltStageParams, qp: QuiltParams, lattice, session: Session):
    """Warn when a given tile size is out of phase with the sample's lattice."""
    if lattice is None or params.tile is None:
        return
    mismatch = tile_mismatch(qp.tile, lattice)
    if max(mismatch) <= 1.0:
        return
    sizes = [commensurate_sizes(n, qp.step, axis, lattice) for axis, n in enumerate(qp.tile)]
    hint = (f"; sizes that close: {sizes[0][0]},{sizes[1][0]}" if sizes[0] and sizes[1]
            else "")
    session.log(f"quilt: warning: a {qp.tile[0]} x {qp.tile[1]} tile is out of phase with "
                f"the sample's lattice by {mismatch[0]:.1f} x {mismatch[1]:.1f} texels, so its "
                f"borders break the pattern and may not pass the border check{hint}")


def _check_memory(params: QuiltStageParams, qp: QuiltParams, sample: tuple[int, int],
                  channels: int, session: Session) -> None:
    """Refuse a plan that cannot fit in the memory available."""
    need = qp.plan_bytes(sample, channels)
    available = psutil.virtual_memory().available
    if need > 0.8 * available:
        raise BTFError(f"{params.store}: planning {qp.corners ** 4} tiles of {qp.tile[0]} x "
                       f"{qp.tile[1]} texels needs about {need / 2**30:.1f} GiB, more than the "
                       f"{available / 2**30:.1f} GiB available: use fewer --corners or a "
                       "smaller --size")
    session.log(f"quilt: planning {qp.corners ** 4} tile(s) of {qp.tile[0]} x {qp.tile[1]} "
                f"texels on the {sample[0]} x {sample[1]} reference image (about "
                f"{need / 2**20:.0f} MiB)")



def _estimate(params, shapes: dict) -> tuple[StageEstimate, Shape]:
    from tasks.canvas import TERMS

    src = shapes[params.store]
    nv, nl, ny, nx, nc = src.radiance
    block = params.block or 32
    overlap = params.overlap if params.overlap is not None else block // 4
    th, tw = params.tile_shape((ny, nx), block - overlap)
    tiles = params.corners**4
    compressed = src.kind == "compressed"
    values = src.rank if compressed else nv * nl * nc
    # a compressed source's tile set copies the sample's V and keeps the prescriptions
    prescriptions = tiles * th * tw * TERMS * 8
    # tiles (or the sample's V) in the source's type: float16 stores make float16 tile sets
    out = (ny * nx * values if compressed else tiles * th * tw * values) * src.itemsize \
        + prescriptions
    # planning compares every tile position with every sample position: measured time grows
    # with their product (16 tiles of 1008^2 on a 1024^2 sample: 14.5 min, estimated 16.9)
    plan_seconds, source = rate("quilt_plan_seconds_per_texel_pair")
    per_core, _ = rate("quilt_values_per_core_second")
    side = src.side
    spatial = math.ceil(th / side) * math.ceil(tw / side)
    groups = max(1, math.ceil(nl / src.dir_chunk)) * nv
    tasks = math.ceil(ny / src.chunk) if compressed else tiles * spatial * groups
    task_bytes = (2 * src.chunk * nx * values * 4 if compressed
                  else 3 * side * side * min(values, src.dir_chunk * nc) * 4 + th * tw * TERMS * 8)
    plan = StageEstimate("quilt", "", bytes_read=ny * nx * 3 * 4 + out, bytes_written=out,
                         tasks=tasks, passes=1, input_reads=1, task_bytes=task_bytes,
                         client_bytes=ny * nx * 3 * 4 * 4 + prescriptions,
                         core_seconds=(ny * nx * values if compressed
                                       else tiles * th * tw * values) / per_core,
                         serial_seconds=tiles * th * tw * ny * nx * plan_seconds,
                         rate_source=source,
                         option="--size (smaller tiles)",
                         note=f"{tiles} tile(s) of {th} x {tw}"
                         + (", compressed: the sample's V and the prescriptions" if compressed
                            else ""))
    kind = "compressed-tileset" if compressed else "tileset"
    return plan, Shape(kind, (), 0, 0)


STAGE = Stage("quilt", QuiltStageParams, quilt,
              "plan a seamless tile set on the reference image and apply it to every layer",
              "Periodic image quilting planned on the reference image (paper 003: corners, "
              "edges, interior; K best candidates by masked SSD; cyclic minimum-error boundary "
              "cut with border flags; Gaussian-blurred blending) for V corner types (V^4 "
              "tiles; V=1: one periodic texture). The plan compiles to one sparse "
              "prescription per tile, stored, and applied identically to every layer (or to "
              "the eigentextures of a compressed store). Tiles are planned on this machine, "
              "--workers at once (one with the synchronous scheduler); the plan is the same "
              "for any number.", makes_store=True,
              estimate=_estimate, for_scene=True, directions=same_directions)
