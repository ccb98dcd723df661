"""``btf enlarge``: a large BTF from a small full measurement and a few full-size photos.

Paper 000, Algorithm 1 (:mod:`tasks.enlargement`): Texture Optimization guided by the photos,
then the QP that meets them. Its statistical synthesis rounds run with ``--statistics`` only:
measured on four materials and three constraint sets, they raised the eq. (11) error by up to
20% and made the result no more realistic (``tasks/realism.py``; BENCHMARKS.md, enlargement).
Inputs:

- ``SAMPLE_SVD``: the compressed store of the measured patch ``S`` (``btf compress``);
- ``CONSTRAINTS``: a radiance store at the target size holding the constraint photos ``C``:
  any number of (view, light) layers, each matched to the sample's nearest (view, light)
  pair within ``--max-angle`` degrees, or a mean-colour image (``--mean-colour``);
- the sample's place in the photos (``--sample-origin``), or else it is found by normalised
  cross-correlation of the sample's own rendering of the constraint layers against ``C``.

The constraint values are range-reduced like the sample (``log(C + eps)``, or the sample's
colour model: :mod:`tasks.transform`), so that a photo
under sample direction row ``i`` is the linear function ``U_S[i] x`` of a texel's
coefficients ``x``. The result's coefficients are re-factorised (:func:`tasks.svd.refactor`)
into a compressed store whose ``U`` spans the sample's eigen-ABRDFs: ``open_compressed``,
``btf reconstruct``, ``quilt``, ``roller``, ``render`` and ``inspect`` take it like any other.

A target of at most 1024^2 texels is synthesized in memory on the client (its coefficients,
``H x W x K`` float32, and a few working copies must fit: the stage refuses before computing
anything otherwise). A larger one, or any with ``--tile N``, is synthesized as dask graphs level
by level, every level larger than a tile in tiles with halos (:mod:`pipeline.graphs.enlarge`):
memory is bounded by the tile size, and the store is the same on every scheduler.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from pipeline.atomic import atomic_output
from pipeline.errors import BTFError
from pipeline.graphs.enlarge import (
    HALO,
    WHOLE_TEXELS,
    Guide,
    check_photos,
    raise_on_bad_photos,
    synthesize,
    write_factors,
)
from pipeline.params import ParamError, check_seed, option
from pipeline.provenance import provenance
from pipeline.resume import Progress
from pipeline.session import Session
from pipeline.stage import Stage
from pipeline.stores import CompressedStore, RadianceStore, open_store
from pipeline.stores.base import (
    RADIANCE,
    add_array,
    location,
    read_channels,
    read_directions,
)
from pipeline.stores.compressed import create_compressed_store
from tasks.enlargement import (
    METRICS,
    SHRINK_WEIGHTS,
    EnlargementParams,
    choose_shrink,
    enlarge,
    mean_colour_rows,
)
from tasks.photo_regression import range_rows
from tasks.registration import AMBIGUITY, Match, locate
from tasks.sampling import nearest_layer
from tasks.statistical_synthesis import StatisticsParams
from tasks.svd import reconstruct, refactor
from tasks.texture_optimization import (
    TextureOptimizationParams,
    downsample,
)
from tasks.transform import Transform

WORKING_COPIES = 12  # target-sized float32 coefficient arrays held at the peak, about
DEFAULT_TILE = 512  # texels per side of a tile when the target is too large for one task
# Default lambda: a constraint value weighs as much as LAMBDA_SCALE whole ABRDFs' worth of
# values would (rows / constraint values is the paper's "nearly one-to-one", its 20000 for
# 22801 textures and one RGB photo). Measured on generated wood, leather, fabric and a brick
# photo (btf bench enlarge, BENCHMARKS.md): the error outside the sample falls from 1 to 10 to
# 100 and is flat from 100 to 1000.
LAMBDA_SCALE = 100.0
# --regress is 1 by default from this many photos: with ten, the bounded regression lowered the
# error or kept it on every material and seed measured (36 path-traced and shaded rows, four
# generated materials); with three, five and seven a woven fabric's rose (BENCHMARKS.md,
# "The regression's move bounded by the sample's values")
REGRESS_PHOTOS = 10


@dataclasses.dataclass(frozen=True)
class EnlargeParams:
    """Parameters of ``btf enlarge``."""

    sample: str = option(help="compressed store of the measured sample (btf compress)",
                         positional=True, path="in", metavar="SAMPLE_SVD")
    constraints: str = option(help="radiance store of the constraint photos at the target size",
                              positional=True, path="in", metavar="CONSTRAINTS")
    out: str = option(help="output compressed store of the enlarged BTF", positional=True,
                      path="out")
    sample_origin: tuple[int, ...] | None = option(
        None, metavar="Y,X", help="top-left texel of the sample in the photos (default: found "
                                  "by normalised cross-correlation)")
    levels: int = option(3, metavar="N", help="synthesis levels, downsampling 1/2^(N-1) ... 1")
    patch: int = option(4, metavar="N", help="neighbourhood size in texels (the paper: 8; 4 "
                                             "was more accurate here, see BENCHMARKS.md)")
    lambda_: float | None = option(
        None, key="lambda", metavar="L",
        help="weight of a constraint value against one ABRDF value in the search (default: "
             "100 x rows / constraint values, see docs/enlargement.md)")
    iterations: int = option(3, metavar="N", help="EM iterations per level (5 changed neither "
                                                  "error nor realism, see BENCHMARKS.md)")
    search: str = option("coherent", metavar="S", choices=("coherent", "exact"),
                         help="how E-steps find matches: 'coherent' (k-coherence: candidates "
                              "from the neighbours' matches, seeded per level by an exact "
                              "search for a quarter of the neighbourhoods; after the seeds a "
                              "cost per texel that does not grow with the sample) or 'exact' "
                              "(the whole sample for every neighbourhood, every time: the "
                              "paper's)")
    pick: float = option(
        0.5, metavar="F",
        help="share of each texel's last Texture Optimization vote given to the one candidate "
             "texel that fits it best (among those its overlapping matches put there and the "
             "sample texels whose photo values are nearest its own) instead of their "
             "weighted mean: 0 is the paper's mean alone, which blurs texels the photos tell "
             "apart (several photos under different lights); see docs/enlargement.md")
    regress: float | None = option(
        None, metavar="W",
        help="move each texel toward the expected ABRDF given its photo values (a linear fit "
             "of the 64 sample texels, or 2 per photo value if more, nearest in photo "
             "values) by W times the share of their variation the fit explains, then apply "
             "the QP again, each texel no further than its values stay within the range "
             "the sample's texels span in each of its layers (or each channel of 512 evenly "
             "spaced directions of a larger sampling); 0 leaves the result as it was. "
             f"Default: 1 with {REGRESS_PHOTOS} photos (layers of CONSTRAINTS, a "
             "--mean-colour layer not counted) or more, else 0. With ten photos "
             "under different lights, 1 lowered the gap share on every material measured "
             "but a fabric's, which it kept (a path-traced stone: 0.44 -> -0.04; `btf bench "
             "enlarge`: median 0.38 -> 0.28), realism within 0.1 on most and at most 0.3 "
             "worse; with one to seven photos it raised the error on some (a woven "
             "fabric's, whose neighbourhoods tell more than a few photo values): see "
             "docs/enlargement.md")
    shrink: str = option(
        "0", metavar="W", numbers_as_text=True,
        help="move each texel W of the way toward the mean of the 64 sample texels nearest "
             "to it in photo values (a 64th of a smaller sample's; what the photos show of "
             "a texel, averaged over what they "
             "leave open: a slope's direction under one near-top light), then apply the QP "
             "again: less error, less realism. 'auto': the W of 0, 0.25, 0.5, 0.75 and 1 "
             "with the least error on the sample itself (its central quarter enlarged back to "
             "the whole sample under its own photo values, where the truth is known; fewer "
             "--levels if the quarter is too small for them), if it beats 0 there by over "
             "2%%; 0 where --regress moves the texels. Default 0. One "
             "photo of smooth bumps under an unrelated albedo: auto chose 0.75, gap share "
             "0.70 -> 0.64, realism 1.6 -> 3.7 (worse); stone, wood, leather, fabric, brick: "
             "0; see docs/enlargement.md")
    statistics: bool = option(False, help="run the paper's statistical synthesis and QP "
                                          "rounds after Texture Optimization (measured: no "
                                          "more realistic, up to 20%% higher error; see "
                                          "BENCHMARKS.md)")
    no_statistics: bool = option(False, help="one QP of the Texture Optimization result, "
                                             "without statistical synthesis (the default; "
                                             "kept for scripts that say so)")
    statistics_energy: float = option(
        0.999, metavar="F", help="impose statistics on the leading components holding this "
                                 "share of the sample's coefficient variance (1: all)")
    exact_constraints: bool = option(False, help="make the result reproduce the photos exactly "
                                                 "(the paper's QP) rather than to within the "
                                                 "sample's own compression error of them")
    qp_metric: str = option(
        "sample", choices=METRICS,
        help="how the QP measures a texel's departure from the synthesis while it meets the "
             "photos: sample (in the sample's covariance of coefficients: a photo's misfit is "
             "explained by the ways the sample's texels vary together, e.g. albedo or slope, "
             "which change every layer; the default) or plain (the paper's: the shortest "
             "change, mostly in the photos' own layers)")
    rounds: int = option(5, metavar="N", help="at most N rounds of statistics and QP")
    beta: float = option(0.25, metavar="B", help="weight of the statistical synthesis against "
                                                 "Texture Optimization (weight 1) in the QP")
    tol: float = option(0.01, metavar="T", help="stop the rounds below this relative change "
                                                "(measured: about 2 rounds, fewer than 5 "
                                                "were also more accurate)")
    mean_colour: int | None = option(
        None, metavar="K", help="constraint layer K (view-major index) is a mean-colour image "
                                "(mean over the lights of one view), not a photo")
    mean_view: int | None = option(None, metavar="J",
                                   help="the sample view a mean-colour image averages "
                                        "(default: the view closest to the normal)")
    max_angle: float = option(1.0, metavar="DEG", help="largest angle between a constraint "
                                                       "layer's directions and the sample's")
    min_match: float = option(0.9, metavar="R", help="least correlation that locates the "
                                                     "sample in the photos")
    seed: int = option(0, metavar="S", help="seed of the search's random choices")
    tile: int | None = option(None, metavar="N",
                              help="synthesize in tiles of N texels with halos, each level "
                                   "larger than a tile (0: the whole target in memory; "
                                   "default: 0 up to 1024^2 texels, else 512)")
    keep_phases: bool = option(False, help="also store the coefficients after Texture "
                                           "Optimization and after the first statistical "
                                           "synthesis (phase_* variables, for evaluation)")
    overwrite: bool = option(False, record=False, help="replace OUT if it exists")

    def __post_init__(self):
        check_seed(self.seed)
        if self.sample_origin is not None and len(self.sample_origin) != 2:
            raise ParamError("sample_origin", f"expected Y,X, got {self.sample_origin}")
        if self.lambda_ is not None and not self.lambda_ > 0:
            raise ParamError("lambda", f"must be positive, got {self.lambda_}")
        if not 0 <= self.pick <= 1:
            raise ParamError("pick", f"must be in [0, 1], got {self.pick}")
        if self.regress is not None and not 0 <= self.regress <= 1:
            raise ParamError("regress", f"must be in [0, 1], got {self.regress}")
        if self.shrink != "auto" and not 0 <= self.shrink_weight() <= 1:
            raise ParamError("shrink", f"must be 'auto' or in [0, 1], got {self.shrink}")
        if not self.max_angle >= 0:
            raise ParamError("max_angle", f"must be non-negative, got {self.max_angle}")
        if self.tile is not None and self.tile != 0 and self.tile < 2 * HALO * self.patch:
            raise ParamError("tile", f"must be 0 or at least twice the halo of {HALO} "
                                     f"neighbourhoods ({2 * HALO * self.patch} texels), got "
                                     f"{self.tile}")
        if self.keep_phases and self.tile:
            raise ParamError("keep_phases", "is only kept for whole targets (--tile 0)")
        if self.statistics and self.no_statistics:
            raise ParamError("statistics", "--statistics and --no-statistics contradict each "
                                           "other")
        if not -1 <= self.min_match <= 1:
            raise ParamError("min_match", f"must be between -1 and 1, got {self.min_match}")
        self.enlargement()  # the kernels' own checks, under the option names

    def shrink_weight(self) -> float:
        """``--shrink`` as a number (0 for 'auto', which the stage decides)."""
        if self.shrink == "auto":
            return 0.0
        try:
            return float(self.shrink)
        except ValueError:
            raise ParamError("shrink", f"must be 'auto' or a number in [0, 1], got "
                                       f"{self.shrink!r}") from None

    def enlargement(self) -> EnlargementParams:
        """The kernels' parameters."""
        return EnlargementParams(
            texture=TextureOptimizationParams(levels=self.levels, patch=self.patch,
                                              iterations=self.iterations, search=self.search,
                                              pick=self.pick),
            statistics=StatisticsParams() if self.statistics else None,
            rounds=self.rounds, tol=self.tol, beta=self.beta, exact=self.exact_constraints,
            statistics_energy=self.statistics_energy, metric=self.qp_metric,
            regress=self.regress or 0.0, shrink=self.shrink_weight())

    def resolved(self, photos: int) -> EnlargeParams:
        """These parameters with ``--regress``'s default decided by the number of photos."""
        if self.regress is not None:
            return self
        return dataclasses.replace(self, regress=1.0 if photos >= REGRESS_PHOTOS else 0.0)


@dataclasses.dataclass(frozen=True)
class _Constraints:
    """The constraint layers: where their values come from and the rows they are of ``x``."""

    guide: Guide
    rows: np.ndarray  # (G, K)
    layers: list[dict]  # what each constraint layer is, for the attrs and messages
    basis: np.ndarray | None  # (R, K): rows of U_S bounding the regression (range_rows)


def _constraints(params: EnlargeParams, group, sample_group, sample_coefficients,
                 transform: Transform, u: np.ndarray) -> _Constraints:
    """Match every constraint layer to the sample (nothing of the photos' pixels is read).

    ``u`` is the sample's ``U``, ``(views, lights, channels, rank)``, as read.
    """
    path = params.constraints
    d, ds = read_directions(group), read_directions(sample_group)
    nv, nl = d.views, d.lights
    nc = group[RADIANCE].shape[-1]
    if params.mean_colour is not None and transform.name != "log":
        raise BTFError(f"{params.sample}: --mean-colour needs a log range reduction (its "
                       f"Jensen offset is of logs); the sample's transform is "
                       f"{transform.name!r}: give photos instead")
    if params.mean_colour is not None and transform.cosine:
        raise BTFError(f"{params.sample}: --mean-colour needs values that are radiance, and "
                       "this sample's are radiance x cos(theta_light) (a DFMF file's cosine "
                       "flag): give photos instead")
    if params.mean_colour is not None and not 0 <= params.mean_colour < nv * nl:
        raise BTFError(f"{path}: --mean-colour {params.mean_colour} is not a layer of the "
                       f"store ({nv * nl} layers, indices 0 to {nv * nl - 1})")
    rows, offsets, described, layers, lit = [], [], [], [], []
    for k in range(nv * nl):
        j, i = divmod(k, nl)
        layers.append((j, i))
        if k == params.mean_colour:
            view = (int(np.argmin(ds.theta_view)) if params.mean_view is None
                    else params.mean_view)
            if not 0 <= view < ds.views:
                raise BTFError(f"{params.sample}: --mean-view {view} is out of range (the "
                               f"sample has {ds.views} views)")
            r, offset, spread = mean_colour_rows(u[view], sample_coefficients)
            rows.append(r)
            offsets += offset.tolist()
            described.append({"layer": k, "kind": "mean colour", "sample_view": view,
                              "jensen_offset": offset.tolist(),
                              "jensen_spread": spread.tolist()})
            continue
        sv, sl, angle = nearest_layer((d.theta_view[j], d.phi_view[j]),
                                      (d.theta_light[i], d.phi_light[i]),
                                      (ds.theta_view, ds.phi_view),
                                      (ds.theta_light, ds.phi_light))
        if angle > params.max_angle:
            raise BTFError(
                f"{path}: layer {k} (view {d.theta_view[j]:g}/{d.phi_view[j]:g}, light "
                f"{d.theta_light[i]:g}/{d.phi_light[i]:g} degrees theta/phi) is not a "
                f"direction of the sample: the nearest, view {sv} ({ds.theta_view[sv]:g}/"
                f"{ds.phi_view[sv]:g}) and light {sl} ({ds.theta_light[sl]:g}/"
                f"{ds.phi_light[sl]:g}), is {angle:.2f} degrees away (--max-angle "
                f"{params.max_angle:g})")
        rows.append(np.asarray(u[sv, sl], np.float64))
        lit.append(ds.theta_light[sl])
        offsets += [0.0] * nc
        described.append({"layer": k, "kind": "photo", "sample_view": sv, "sample_light": sl,
                          "angle_deg": angle})
    # a cosine sample's values are radiance x cos of its layer's light: the photo that layer
    # matches is multiplied alike before it is encoded
    scale = transform.layer_scale(np.asarray(lit))
    guide = Guide(location(path), tuple(layers), tuple(offsets), transform,
                  tuple(group[RADIANCE].shape[2:4]),
                  None if scale is None else tuple(float(1.0 / x) for x in scale))
    basis = (range_rows(u.reshape(-1, u.shape[-1]).astype(np.float32), u.shape[-2])
             if params.regress else None)
    return _Constraints(guide, np.concatenate(rows, axis=0), described, basis)


def _locate(guide: Guide, rendered: np.ndarray) -> tuple[Match, int]:
    """Best placement of the sample's rendering in the photos, coarse to fine.

    The photos are searched at the scale at which they hold at most WHOLE_TEXELS texels (and
    the sample keeps 8 texels a side), then at full resolution near the coarse answer, and
    near every other place that matches as well (a periodic sample; at most MAX_ALIKE).
    """
    (h, w), (big_h, big_w) = rendered.shape[:2], guide.shape
    factor = 1
    while (big_h // factor) * (big_w // factor) > WHOLE_TEXELS and min(h, w) // factor >= 16:
        factor *= 2
    coarse = locate(downsample(rendered, factor),
                    guide.region(factor, 0, -(-big_h // factor), 0, -(-big_w // factor)))
    if factor == 1:
        return coarse, factor

    def near(cy: int, cx: int) -> Match:
        y0, x0 = max(0, (cy - 2) * factor), max(0, (cx - 2) * factor)
        y1, x1 = min(big_h, (cy + 2) * factor + h), min(big_w, (cx + 2) * factor + w)
        found = locate(rendered, guide.region(1, y0, y1, x0, x1))
        return Match(found.y + y0, found.x + x0, found.score, found.runner_up)

    fine = near(coarse.y, coarse.x)
    alike, seen = [], {(fine.y, fine.x)}
    for m in (near(y, x) for y, x, _ in coarse.alike):  # kept if as good at full resolution
        if m.score >= fine.score - AMBIGUITY and (m.y, m.x) not in seen:
            alike.append((m.y, m.x, m.score))
            seen.add((m.y, m.x))
    return Match(fine.y, fine.x, fine.score, coarse.runner_up, tuple(alike)), factor


def _place_sample(params: EnlargeParams, constraints: _Constraints,
                  sample_coefficients: np.ndarray, session: Session) -> tuple[int, int, dict]:
    h, w = sample_coefficients.shape[:2]
    big_h, big_w = constraints.guide.shape
    if params.sample_origin is not None:
        y, x = params.sample_origin
        if not (0 <= y <= big_h - h and 0 <= x <= big_w - w):
            raise BTFError(f"{params.constraints}: --sample-origin {y},{x} puts the {h} x {w} "
                           f"sample outside the {big_h} x {big_w} photos")
        return y, x, {"origin": [y, x], "given": True}
    rendered = sample_coefficients @ constraints.rows.T.astype(np.float32)
    rendered -= np.asarray(constraints.guide.offsets, np.float32)
    match, factor = _locate(constraints.guide, rendered)
    session.log(f"enlarge: the sample matches the photos at {match.y},{match.x} (correlation "
                f"{match.score:.4f}; best elsewhere {match.runner_up:.4f})")
    if match.score < params.min_match:
        raise BTFError(f"{params.constraints}: the sample's constraint layers do not match the "
                       f"photos convincingly anywhere (best correlation {match.score:.3f} at "
                       f"{match.y},{match.x}, below --min-match {params.min_match:g}); give "
                       "--sample-origin Y,X if you know where it is")
    (y, x), ambiguous = (((match.y, match.x), None) if not match.ambiguous() else
                         _ambiguity(params, constraints.guide, rendered, match, session))
    placement = {"origin": [y, x], "given": False, "correlation": match.score,
                 "runner_up": match.runner_up, "search_scale": factor}
    if ambiguous:
        placement["ambiguous"] = ambiguous
    return y, x, placement


def _ambiguity(params: EnlargeParams, guide: Guide, rendered: np.ndarray, match: Match,
               session: Session) -> tuple[tuple[int, int], dict]:
    """Several places match equally (a periodic sample): go on only if the choice cannot matter.

    Correlation does not see a gain or an offset, so of the places the one where the photos
    are nearest to the sample's rendering is taken (its misfit is the sample's own
    compression error). The sample's constraint values are the photos' at its place and
    nothing else of the place is used; so if the photos at every such place are those of the
    chosen one to within that misfit, any of them gives the same result to that accuracy.
    Otherwise they would give different results, and the user must say which.
    """
    h, w = rendered.shape[:2]
    places = [(match.y, match.x), *((y, x) for y, x, _ in match.alike)]
    windows = [guide.region(1, y, y + h, x, x + w) for y, x in places]
    misfits = [float(np.sqrt(np.mean((rendered - window) ** 2))) for window in windows]
    pick = int(np.argmin(misfits))
    differ = [float(np.sqrt(np.mean((window - windows[pick]) ** 2))) for window in windows]
    worst = int(np.argmax(differ))
    (y, x), misfit = places[pick], misfits[pick]
    where = (f"the sample matches the photos equally well at {len(places)} places, "
             + ", ".join(f"{py},{px}" for py, px in places)
             + f" (correlation {match.score:.4f} within {AMBIGUITY:g}: it repeats)")
    if differ[worst] > misfit:
        raise BTFError(f"{params.constraints}: {where}, and the photos differ there (at "
                       f"{places[worst][0]},{places[worst][1]} by {differ[worst]:.3g} RMS in "
                       f"the log domain from {y},{x}, where the sample fits them best, more "
                       f"than its own misfit of {misfit:.3g}), so these places would give "
                       "different results; give --sample-origin Y,X to say where the sample "
                       "was measured")
    exact = differ[worst] == 0
    session.log(f"enlarge: note: {where}; the photos there differ by at most "
                f"{differ[worst]:.3g} RMS (log domain), no more than the sample's own misfit "
                f"to them ({misfit:.3g}), so every such place gives the sample the same "
                f"constraint values {'exactly' if exact else f'to within {differ[worst]:.3g}'}"
                f" and the result does not depend on the choice{'' if exact else ' beyond that'}"
                f"; using {y},{x} (--sample-origin to choose)")
    return (y, x), {"places": [list(p) for p in places], "photos_differ_rms": differ[worst],
                    "sample_misfit_rms": misfit}


def _whole(params, session, constraints, coefficients, sample_values, lam):
    """The whole target in memory on the client (:func:`tasks.enlargement.enlarge`)."""
    import psutil

    big_h, big_w = constraints.guide.shape
    rank = coefficients.shape[-1]
    need = WORKING_COPIES * big_h * big_w * rank * 4
    available = psutil.virtual_memory().available
    if need > 0.8 * available:
        raise BTFError(f"{params.constraints}: enlarging to {big_h} x {big_w} texels at rank "
                       f"{rank} in memory needs about {need / 2**30:.1f} GiB, more than the "
                       f"{available / 2**30:.1f} GiB available; use --tile N")
    values = constraints.guide.region(1, 0, big_h, 0, big_w)
    result = enlarge(coefficients, sample_values, values, constraints.rows,
                     params=params.enlargement(), guide_weight=float(np.sqrt(lam)),
                     seed=params.seed, basis=constraints.basis)
    report = {"seconds": result.seconds, "rounds": result.rounds, "changes": result.changes,
              "constraint_residual_rms": result.residual_rms,
              "sample_constraint_residual_rms": result.noise, "damping": result.damping,
              "constraint_rank": result.constraint_rank, "energy": result.energy}
    return result.coefficients, report, result


def _check_inputs(params: EnlargeParams, group, sample_group, sample: tuple[int, int],
                  target: tuple[int, int]) -> None:
    """Refuse photos of other channels or smaller than the sample, and too many levels."""
    (h, w), (big_h, big_w) = sample, target
    if read_channels(group) != read_channels(sample_group):
        raise BTFError(f"{params.constraints}: channels {read_channels(group)} differ from the "
                       f"sample's {read_channels(sample_group)}")
    if big_h < h or big_w < w:
        raise BTFError(f"{params.constraints}: the photos ({big_h} x {big_w}) are smaller than "
                       f"the sample ({h} x {w}); enlargement needs photos at the target size")
    factor = 2 ** (params.levels - 1)  # texture_optimization.downsample keeps partial blocks
    coarsest = (-(-h // factor), -(-w // factor))
    if min(coarsest) < params.patch:
        raise BTFError(f"{params.sample}: the sample ({h} x {w}) is {coarsest[0]} x "
                       f"{coarsest[1]} at the coarsest of --levels {params.levels}, smaller than "
                       f"a neighbourhood (--patch {params.patch}): use fewer levels or a smaller "
                       "patch")


def _output_attrs(params: EnlargeParams, sample_group, shape: list[int], rank: int) -> dict:
    """The enlarged store's attrs before synthesis: its source, transform and provenance."""
    attrs = {
        "source": "enlarge",
        "source_btf_kind": sample_group.attrs.get("source_btf_kind"),
        "source_shape": shape,
        "transform": sample_group.attrs["transform"],
        "svd": {"rank": rank, "method": "enlargement (paper 000, Algorithm 1), re-factorised"},
        "provenance": provenance("enlarge", params),
    }
    for key in ("source_sampling", "source_material"):
        if key in sample_group.attrs:
            attrs[key] = sample_group.attrs[key]
    return attrs


def _open_inputs(params: EnlargeParams):
    """The sample's compressed group and the photos' radiance group, checked."""
    sample = open_store(params.sample, CompressedStore)
    photos = open_store(params.constraints, RadianceStore)
    return sample.group, photos.group


def _guide_weight(params: EnlargeParams, m: int, g: int) -> float:
    """Lambda: ``--lambda``, or :data:`LAMBDA_SCALE` x rows (``m``) / constraint values."""
    return params.lambda_ if params.lambda_ is not None else LAMBDA_SCALE * m / g


def _shrink(params: EnlargeParams, session: Session, constraints: _Constraints,
            coefficients: np.ndarray, sample_values: np.ndarray, lam: float, u: np.ndarray,
            transform: Transform) -> tuple[EnlargeParams, dict]:
    """``--shrink`` decided (``auto``: by :func:`tasks.enlargement.choose_shrink`), and how.

    ``u`` is the sample's ``U``, ``(views, lights, channels, rank)``: the error on the sample
    is measured in the radiance of the rows :func:`tasks.photo_regression.range_rows` picks.
    """
    if params.shrink != "auto":
        return params, {"weight": params.shrink_weight(), "given": True}
    if params.regress:
        session.log("enlarge: --shrink auto: 0 (the photos' regression moves the texels)")
        return dataclasses.replace(params, shrink="0"), {"weight": 0.0, "given": False,
                                                          "skipped": "--regress is on"}
    rows = range_rows(u.reshape(-1, u.shape[-1]), u.shape[-2])

    def radiance(c: np.ndarray) -> np.ndarray:
        return reconstruct(rows, np.ones(rows.shape[-1]), c, transform=transform).T

    choice = choose_shrink(coefficients, sample_values, constraints.rows,
                           params=params.enlargement(), guide_weight=float(np.sqrt(lam)),
                           seed=params.seed, radiance=radiance)
    if choice.skipped:
        session.log(f"enlarge: --shrink auto: 0 ({choice.skipped})")
    else:
        session.log("enlarge: --shrink auto: " + f"{choice.weight:g} (error on the sample at "
                    + " / ".join(f"{w:g}" for w in SHRINK_WEIGHTS) + ": "
                    + " / ".join(f"{choice.errors[w]:.4g}" for w in SHRINK_WEIGHTS)
                    + f"; {choice.seconds:.1f} s)")
    return (dataclasses.replace(params, shrink=f"{choice.weight:g}"),
            {"weight": choice.weight, "given": False, "seconds": choice.seconds,
             "errors": {f"{w:g}": e for w, e in choice.errors.items()},
             **({"skipped": choice.skipped} if choice.skipped else {})})


def _tile(params: EnlargeParams, big_h: int, big_w: int) -> int:
    """``--tile``, or 0 (whole, in memory) up to :data:`WHOLE_TEXELS`, else the default tile."""
    return params.tile if params.tile is not None else (
        0 if big_h * big_w <= WHOLE_TEXELS else DEFAULT_TILE)


def _create_output(tmp, sample_group, attrs: dict, big_h: int, big_w: int, rank: int,
                   tile: int):
    """The output compressed store, or the one a killed tiled run left (its tiles are kept)."""
    return Progress(tmp).skeleton(lambda: create_compressed_store(
        tmp, directions=read_directions(sample_group),
        channels=read_channels(sample_group), ny=big_h, nx=big_w, rank=rank,
        chunk=tile or sample_group["V"].chunks[0], dir_chunk=sample_group["U"].chunks[1],
        attrs=attrs))


def _enlarge_tiled(params: EnlargeParams, session: Session, out, tmp, constraints: _Constraints,
                   coefficients, sample_values, lam: float, u: np.ndarray, tile: int):
    """Synthesize in tiles as dask graphs and write ``V``; returns the report, ``U`` and ``S``.

    ``u`` is the sample's ``U`` as ``(rows, rank)``.
    """
    report = synthesize(out, tmp, constraints.guide, constraints.rows, coefficients,
                        sample_values, params=params.enlargement(),
                        guide_weight=float(np.sqrt(lam)), seed=params.seed,
                        tile=tile, session=session, basis=constraints.basis)
    new_u, new_s = write_factors(out, tmp, u, tile=tile, session=session)
    return report, new_u, new_s


def _enlarge_whole(params: EnlargeParams, session: Session, out, constraints: _Constraints,
                   coefficients, sample_values, lam: float, u: np.ndarray):
    """Synthesize in memory and write ``V`` (and phases); returns the report, ``U`` and ``S``.

    ``u`` is the sample's ``U`` as ``(rows, rank)``.
    """
    rank = u.shape[-1]
    big_h, big_w = constraints.guide.shape
    result_coefficients, report, result = _whole(params, session, constraints,
                                                 coefficients, sample_values, lam)
    new_u, new_s, new_v, basis = refactor(u, result_coefficients.reshape(-1, rank))
    out["V"][...] = new_v.reshape(big_h, big_w, rank).astype(np.float32)
    if params.keep_phases:
        _keep_phases(out, result, basis, rank)
    return report, new_u, new_s


def _log_times(session: Session, report: dict) -> None:
    """Log the phases' seconds and the constraint residual against the sample's own."""
    session.log("enlarge: " + ", ".join(f"{k.replace('_', ' ')} {v:.1f} s"
                                        for k, v in report["seconds"].items())
                + f"; constraint residual (RMS, log domain) "
                f"{report['constraint_residual_rms']:.3g} (the sample's own: "
                f"{report['sample_constraint_residual_rms']:.3g})")


def enlarge_stage(params: EnlargeParams, session: Session) -> Path:
    """Enlarge the sample under the constraint photos; write a compressed store."""
    sample_group, group = _open_inputs(params)
    asked = params  # the provenance: a rerun's parameters as given are the same again
    if params.regress is None:
        photos = int(np.prod(group[RADIANCE].shape[:2])) - (params.mean_colour is not None)
        params = params.resolved(photos)
        session.log(f"enlarge: {photos} photo(s): the photos' regression "
                    + ("on (--regress 1; --regress 0 turns it off)" if params.regress else
                       f"off (on by default from {REGRESS_PHOTOS} photos; --regress W sets it)"))
    u = np.asarray(sample_group["U"][...], np.float64)
    nv, nl, nc, rank = u.shape
    s = np.asarray(sample_group["S"][...], np.float64)
    coefficients = (np.asarray(sample_group["V"][...], np.float32) * s.astype(np.float32))
    h, w = coefficients.shape[:2]
    big_h, big_w = group[RADIANCE].shape[2:4]
    _check_inputs(params, group, sample_group, (h, w), (big_h, big_w))
    transform = Transform.from_attrs(sample_group.attrs["transform"])
    constraints = _constraints(params, group, sample_group, coefficients, transform, u)
    raise_on_bad_photos(session.compute(*check_photos(constraints.guide)), params.constraints,
                        constraints.guide)
    y0, x0, placement = _place_sample(params, constraints, coefficients, session)
    sample_values = constraints.guide.region(1, y0, y0 + h, x0, x0 + w)
    m = nv * nl * nc
    g = len(constraints.guide.offsets)
    lam = _guide_weight(params, m, g)
    start = time.perf_counter()
    params, shrink = _shrink(params, session, constraints, coefficients, sample_values, lam,
                             u, transform)
    tile = _tile(params, big_h, big_w)
    session.log(f"enlarge: {h} x {w} sample at rank {rank} -> {big_h} x {big_w} under "
                f"{len(constraints.layers)} constraint layer(s) ({g} values per texel, lambda "
                f"{lam:g}){f' in tiles of {tile}' if tile else ''} -> {params.out}")
    attrs = _output_attrs(asked, sample_group, [nv, nl, big_h, big_w, nc], rank)
    # a resumed tiled run keeps its finished tiles only if --shrink auto decides as before
    resume = {**attrs["provenance"], "shrink_weight": shrink["weight"]} if tile else None
    with atomic_output(params.out, directory=True, overwrite=params.overwrite,
                       resume=resume) as tmp, \
            session.blas_pinned_in_tasks():
        # a killed tiled run's finished tiles are kept (see synthesize), if they read back
        Progress(tmp).distrust_damaged(lambda line: session.log(f"enlarge: {line}"))
        out = _create_output(tmp, sample_group, attrs, big_h, big_w, rank, tile)
        if tile:
            report, new_u, new_s = _enlarge_tiled(params, session, out, tmp, constraints,
                                                  coefficients, sample_values, lam,
                                                  u.reshape(m, rank), tile)
        else:
            report, new_u, new_s = _enlarge_whole(params, session, out, constraints,
                                                  coefficients, sample_values, lam,
                                                  u.reshape(m, rank))
        out["U"][...] = new_u.reshape(nv, nl, nc, rank).astype(np.float32)
        out["S"][...] = new_s.astype(np.float32)
        if "seconds" in shrink:
            report["seconds"]["shrink_choice"] = shrink["seconds"]
        report["seconds"]["total"] = time.perf_counter() - start
        out.attrs["enlargement"] = {
            "sample": params.sample, "constraints": params.constraints, "sample_shape": [h, w],
            "placement": placement, "constraint_layers": constraints.layers, "lambda": lam,
            "parameters": dataclasses.asdict(params.enlargement()), "shrink": shrink,
            **report}
    _log_times(session, report)
    return Path(params.out)


def _keep_phases(out, result, basis, rank) -> None:
    phases = {"texture_optimization": result.texture_optimization,
              "statistics": result.statistics}
    for name, phase in phases.items():
        if phase is not None:  # in the output's basis: radiance exp(U c) - eps
            add_array(out, f"phase_{name}", shape=phase.shape, dims=("y", "x", "component"),
                      chunks=out["V"].chunks,
                      attrs={"long_name": f"coefficients S V^T after {name}"})[...] = (
                (phase.reshape(-1, rank) @ basis).reshape(phase.shape))


STAGE = Stage("enlarge", EnlargeParams, enlarge_stage,
              "a large BTF from a small compressed sample and full-size photos (paper 000)",
              "Synthesize the eigentextures of a BTF at the size of the constraint photos from "
              "a compressed sample (its eigen-ABRDFs stay): Texture Optimization guided by the "
              "photos (multi-level EM, PCA-reduced exact search), statistical synthesis on a "
              "steerable pyramid, and a per-texel QP that makes the result reproduce the "
              "photos, alternated until the change is below --tol. Each photo layer is matched "
              "to the sample's nearest direction; the sample's place in the photos is found "
              "by normalised cross-correlation unless --sample-origin gives it. The output is "
              "a compressed store that btf reconstruct, quilt, roller and inspect take.",
              makes_store=True,
              whole=("Texture Optimization synthesizes the whole target; its eigentextures "
                     "serve every layer"))
