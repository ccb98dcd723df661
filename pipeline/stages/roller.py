"""``btf roller``: periodicity detection and double toroidal tiles (paper 004).

The lattice is detected on one grey-scale image (:mod:`tasks.periodicity`): the perpendicularly
lit layer (the light and view closest to the normal; ``--image reference`` uses quilting's
reference image instead). The tiles are planned on the same image in colour
(:mod:`tasks.roller`), and their prescriptions are applied to every layer, or to the
eigentextures of a compressed store, by the machinery quilting uses
(:func:`pipeline.graphs.prescriptions.write_tileset`); with ``--for-scene`` only to the layers
that scene reads. The result is a tile set that ``btf render`` lays on surfaces of any size
with pure gathers.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

from pipeline.errors import BTFError
from pipeline.graphs.blocks import read_chunks
from pipeline.graphs.prescriptions import write_tileset
from pipeline.graphs.reference import compute_reference
from pipeline.params import ParamError, check_seed, option
from pipeline.provenance import provenance
from pipeline.session import Session
from pipeline.stage import Stage, for_scene_option, same_directions
from pipeline.stores import CompressedStore, RadianceStore, lazy_layers, open_store
from pipeline.stores.tileset import Placement, TileSet
from tasks.periodicity import Lattice, detect_lattice
from tasks.reference import luminance
from tasks.roller import RollerParams, plan_roller

LOW_CONFIDENCE = "the texture shows no clear periodicity"


@dataclasses.dataclass(frozen=True)
class RollerStageParams:
    """Parameters of ``btf roller``."""

    store: str = option(help="radiance or compressed store (the sample)", positional=True,
                        path="in", metavar="IN")
    out: str | None = option(None, help="output tile-set store (not needed with --detect-only)",
                             positional=True, path="out")
    detect_only: bool = option(False, help="only detect and print the periodicity vectors")
    json: bool = option(False, record=False,
                        help="with --detect-only: print one JSON object (u, v as [dy, dx], "
                             "angles_deg, lengths_px, confidence, periodic, message)")
    tiles: int = option(1, metavar="N", help="tiles with identical borders and different "
                                             "content, chosen per lattice cell by a hash")
    periods: tuple[int, ...] | None = option(
        None, metavar="A,B", help="periods of u and v per tile edge (default: a tile of at most "
                                  "a quarter of the sample)")
    seed: int = option(0, metavar="S", help="seed recorded for rendering (placement of tiles)")
    band: int = option(4, metavar="PX", help="half-width of the band the cuts may use")
    max_seam: float = option(
        1.3, metavar="R", help="the most a tile border may stand out from what the sample has "
                               "there (seam and structure ratios); other tile sizes are tried "
                               "until one passes, else roller stops")
    min_confidence: float = option(0.5, metavar="C",
                                   help="refuse to build tiles below this confidence")
    image: str = option("layer", choices=("layer", "reference"),
                        help="image to analyse: the perpendicularly lit layer, or quilting's "
                             "reference image")
    for_scene: str | None = for_scene_option()
    overwrite: bool = option(False, record=False, help="replace OUT if it exists")

    def __post_init__(self):
        if not self.detect_only and self.out is None:
            raise ParamError("out", "is required (unless --detect-only)")
        if self.detect_only and self.for_scene is not None:
            raise ParamError("for_scene", "makes no sense with --detect-only (no tiles)")
        if self.json and not self.detect_only:
            raise ParamError("json", "only goes with --detect-only")
        check_seed(self.seed)
        if self.periods is not None and len(self.periods) != 2:
            raise ParamError("periods", f"expected A,B, got {self.periods}")
        self.roller_params()  # the planner's own checks (ParamError naming the option)

    def roller_params(self) -> RollerParams:
        """The planner's parameters."""
        return RollerParams(tiles=self.tiles, periods=self.periods, band=self.band,
                            max_seam=self.max_seam)


def analysis_image(path: str, image: str, session: Session) -> tuple[np.ndarray, str]:
    """The colour image the roller analyses, and a description of it."""
    if image == "reference":
        maps, view = compute_reference(path, weights=(1.0, 0.5, 0.5), view=None,
                                       session=session)
        return maps.reference.astype(np.float64), f"the reference image of view {view}"
    store = open_store(path, RadianceStore, CompressedStore)
    d = store.directions
    view = int(np.argmin(d.theta_view))
    light = int(np.argmin(d.theta_light))
    (layer,) = session.compute(lazy_layers(store, read_chunks)[view, light])
    return (np.asarray(layer, np.float64),
            f"view {view}, light {light} (theta {d.theta_light[light]:.0f} deg)")


def describe(lattice: Lattice) -> str:
    """The lattice as lines of text."""
    lines = []
    for name, vec, length, angle in zip("uv", (lattice.u, lattice.v), lattice.lengths_px,
                                        lattice.angles_deg, strict=True):
        lines.append(f"  {name} = [dy, dx] = [{vec[0]:.2f}, {vec[1]:.2f}]: {length:.2f} px "
                     f"at {angle:.2f} deg")
    return "\n".join(lines)


def roller(params: RollerStageParams, session: Session) -> Path | None:
    """Detect the lattice and, unless ``--detect-only``, write a roller tile set."""
    from pipeline.scene_needs import tileset_needs

    # a bad scene spec stops before the analysis
    needs = tileset_needs(params.for_scene, params.store, params.out, session, label="roller")
    image, what = analysis_image(params.store, params.image, session)
    gray = luminance(image) if image.shape[-1] == 3 else image.mean(axis=-1)
    try:
        lattice = detect_lattice(gray)
    except ValueError as exc:
        raise BTFError(f"{params.store}: {exc}") from None
    periodic = lattice.confidence >= params.min_confidence
    message = ("periodic" if periodic else
               f"{LOW_CONFIDENCE} (confidence {lattice.confidence:.2f} < {params.min_confidence}"
               f"); the roller would repeat an arbitrary crop: use btf quilt for it")
    if params.detect_only:
        if params.json:
            print(json.dumps({**lattice.as_dict(), "periodic": periodic, "message": message}))
        else:
            print(f"{params.store}: lattice of {what}:\n{describe(lattice)}\n"
                  f"  confidence {lattice.confidence:.2f}: {message}")
        if not periodic:
            print(f"btf roller: {params.store}: {message}", file=sys.stderr)
        return None
    if not periodic:
        raise BTFError(f"{params.store}: {message} (--min-confidence sets the threshold)")
    session.log(f"roller: lattice of {what}:\n{describe(lattice)}\n  confidence "
                f"{lattice.confidence:.2f}")
    try:
        plan = plan_roller(image, lattice.u, lattice.v, params.roller_params())
    except ValueError as exc:
        raise BTFError(f"{params.store}: {exc}") from None
    h, w, _ = plan.hnf
    session.log(f"roller: {params.tiles} tile(s) spanned by U = {plan.U}, V = {plan.V} "
                f"({plan.periods[0]} x {plan.periods[1]} periods, {plan.area} texels, stored "
                f"{h} x {w}) at {plan.origin}; borders: seam {plan.check[0]:.2f}, structure "
                f"{plan.check[1]:.2f} of the sample's own variation")
    attrs = {
        "source": "roller",
        "roller": {**dataclasses.asdict(params.roller_params()), "seed": params.seed,
                   "cut_u": plan.cut_u.tolist(), "cut_v": plan.cut_v.tolist()},
        "border_check": {"bound": params.max_seam, "seam": round(plan.check[0], 4),
                         "structure": round(plan.check[1], 4)},
        "provenance": provenance("roller", params),
    }
    if needs is not None:
        attrs["computed_for_scene"] = needs.record(params.for_scene)
    tiles = TileSet(index=list(plan.index), weight=list(plan.weight),
                    tile_shape=plan.tile_shape, reference=image.astype(np.float32),
                    corners=np.zeros((params.tiles, 4), np.int64), attrs=attrs,
                    placement=Placement("lattice", 1, params.seed, {
                        **lattice.as_dict(), "U": list(plan.U), "V": list(plan.V),
                        "periods": list(plan.periods), "hnf": list(plan.hnf),
                        "origin": list(plan.origin),
                        "offsets": [list(o) for o in plan.offsets], "image": what}),
                    representative=plan.representative.astype(np.int64))
    return write_tileset(tiles, params.out, source=params.store, session=session,
                         label="roller", overwrite=params.overwrite, needs=needs)


STAGE = Stage("roller", RollerStageParams, roller,
              "detect the periodicity lattice and build double toroidal tiles (paper 004)",
              "Detect the two periodicity vectors u, v (any direction) of the perpendicularly "
              "lit layer from its Fourier spectrum and autocorrelation (--detect-only prints "
              "them; --json as one object). Otherwise cut a tile spanned by whole periods "
              "along the cheapest paths through the overlap error (scipy's Dijkstra) so it "
              "repeats seamlessly on the lattice, optionally N tiles with identical borders "
              "(--tiles), and apply it to every layer (or to the eigentextures of a "
              "compressed store). btf render lays the tiles on surfaces of any size.",
              makes_store=True,
              for_scene=True, directions=same_directions)
