"""``btf enlarge``: a large BTF from a small full measurement and a few full-size photos.

Paper 000, Algorithm 1 (:mod:`tasks.enlargement`). Inputs:

- ``SAMPLE_SVD``: the compressed store of the measured patch ``S`` (``btf compress``);
- ``CONSTRAINTS``: a radiance store at the target size holding the constraint photos ``C``:
  any number of (view, light) layers, each matched to the sample's nearest (view, light)
  pair within ``--max-angle`` degrees, or a mean-colour image (``--mean-colour``);
- the sample's place in the photos (``--sample-origin``), or else it is found by normalised
  cross-correlation of the sample's own rendering of the constraint layers against ``C``.

The constraint values are range-reduced like the sample (``log(C + eps)``), so that a photo
under sample direction row ``i`` is the linear function ``U_S[i] x`` of a texel's
coefficients ``x``. The result's coefficients are re-factorised (:func:`tasks.svd.refactor`)
into a compressed store whose ``U`` spans the sample's eigen-ABRDFs: ``open_compressed``,
``btf reconstruct``, ``quilt``, ``roller``, ``render`` and ``inspect`` take it like any other.

Runs on the client, in memory: the coefficients of the target (``H x W x K`` float32) and a few
working copies must fit (the stage refuses before computing anything otherwise).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from pipeline.atomic import atomic_output
from pipeline.errors import BTFError
from pipeline.params import ParamError, check_seed, option
from pipeline.provenance import provenance
from pipeline.session import Session
from pipeline.stores.base import (
    RADIANCE,
    add_array,
    open_group,
    read_channels,
    read_directions,
)
from pipeline.stores.compressed import check_compressed, create_compressed_store
from pipeline.stores.radiance import check_radiance
from tasks.enlargement import EnlargementParams, enlarge, mean_colour_rows
from tasks.registration import locate
from tasks.sampling import nearest_layer
from tasks.statistical_synthesis import StatisticsParams
from tasks.svd import refactor
from tasks.texture_optimization import TextureOptimizationParams

WORKING_COPIES = 12  # target-sized float32 coefficient arrays held at the peak, about
# Default lambda: a constraint value weighs as much as LAMBDA_SCALE whole ABRDFs' worth of
# values would (rows / constraint values is the paper's "nearly one-to-one", its 20000 for
# 22801 textures and one RGB photo). Measured on generated wood, leather, fabric and a brick
# photo (btf bench enlarge, BENCHMARKS.md): the error outside the sample falls from 1 to 10 to
# 100 and is flat from 100 to 1000.
LAMBDA_SCALE = 100.0


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
             "100 x rows / constraint values, see the README)")
    iterations: int = option(5, metavar="N", help="EM iterations per level")
    no_statistics: bool = option(False, help="skip statistical synthesis: one QP of the "
                                             "Texture Optimization result")
    exact_constraints: bool = option(False, help="make the result reproduce the photos exactly "
                                                 "(the paper's QP) rather than to within the "
                                                 "sample's own compression error of them")
    rounds: int = option(5, metavar="N", help="at most N rounds of statistics and QP")
    beta: float = option(0.25, metavar="B", help="weight of the statistical synthesis against "
                                                 "Texture Optimization (weight 1) in the QP")
    tol: float = option(1e-3, metavar="T", help="stop the rounds below this relative change")
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
        if not self.max_angle >= 0:
            raise ParamError("max_angle", f"must be non-negative, got {self.max_angle}")
        if not -1 <= self.min_match <= 1:
            raise ParamError("min_match", f"must be between -1 and 1, got {self.min_match}")
        self.enlargement()  # the kernels' own checks, under the option names

    def enlargement(self) -> EnlargementParams:
        """The kernels' parameters."""
        return EnlargementParams(
            texture=TextureOptimizationParams(levels=self.levels, patch=self.patch,
                                              iterations=self.iterations),
            statistics=None if self.no_statistics else StatisticsParams(),
            rounds=self.rounds, tol=self.tol, beta=self.beta, exact=self.exact_constraints)


@dataclasses.dataclass(frozen=True)
class _Constraints:
    """The constraint values (log domain) and the linear rows they are of the coefficients."""

    values: np.ndarray  # (H, W, G) float32
    rows: np.ndarray  # (G, K)
    layers: list[dict]  # what each constraint layer is, for the attrs and messages


def _read_constraints(params: EnlargeParams, group, sample_group, sample_coefficients,
                      eps: float) -> _Constraints:
    path = params.constraints
    d, ds = read_directions(group), read_directions(sample_group)
    u = sample_group["U"]
    nv, nl = d.views, d.lights
    layers = group[RADIANCE]
    if params.mean_colour is not None and not 0 <= params.mean_colour < nv * nl:
        raise BTFError(f"{path}: --mean-colour {params.mean_colour} is not a layer of the "
                       f"store ({nv * nl} layers, indices 0 to {nv * nl - 1})")
    values, rows, described = [], [], []
    for k in range(nv * nl):
        j, i = divmod(k, nl)
        layer = np.asarray(layers[j, i], np.float32)
        bad = ~np.isfinite(layer)
        if bad.any():
            y, x, c = np.argwhere(bad)[0]
            raise BTFError(f"{path}: variable 'radiance' has {int(bad.sum())} NaN or Inf "
                           f"value(s) in layer {k} (view {j}, light {i}), the first at y={y}, "
                           f"x={x}, channel={c}")
        if (layer < 0).any():
            y, x, c = np.argwhere(layer < 0)[0]
            raise BTFError(f"{path}: variable 'radiance' has negative values in layer {k} "
                           f"(view {j}, light {i}), the first at y={y}, x={x}, channel={c}; "
                           "log(radiance + eps) needs radiance >= 0")
        logs = np.log(layer + np.float32(eps))
        if k == params.mean_colour:
            view = (int(np.argmin(ds.theta_view)) if params.mean_view is None
                    else params.mean_view)
            if not 0 <= view < ds.views:
                raise BTFError(f"{params.sample}: --mean-view {view} is out of range (the "
                               f"sample has {ds.views} views)")
            r, offset, spread = mean_colour_rows(u[view], sample_coefficients)
            values.append(logs - offset.astype(np.float32))
            rows.append(r)
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
        values.append(logs)
        rows.append(np.asarray(u[sv, sl], np.float64))
        described.append({"layer": k, "kind": "photo", "sample_view": sv, "sample_light": sl,
                          "angle_deg": angle})
    return _Constraints(np.concatenate(values, axis=-1), np.concatenate(rows, axis=0),
                        described)


def _place_sample(params: EnlargeParams, constraints: _Constraints,
                  sample_coefficients: np.ndarray, session: Session) -> tuple[int, int, dict]:
    h, w = sample_coefficients.shape[:2]
    big_h, big_w = constraints.values.shape[:2]
    if params.sample_origin is not None:
        y, x = params.sample_origin
        if not (0 <= y <= big_h - h and 0 <= x <= big_w - w):
            raise BTFError(f"{params.constraints}: --sample-origin {y},{x} puts the {h} x {w} "
                           f"sample outside the {big_h} x {big_w} photos")
        return y, x, {"origin": [y, x], "given": True}
    rendered = sample_coefficients @ constraints.rows.T.astype(np.float32)
    match = locate(rendered, constraints.values)
    session.log(f"enlarge: the sample matches the photos at {match.y},{match.x} (correlation "
                f"{match.score:.4f}; best elsewhere {match.runner_up:.4f})")
    if match.score < params.min_match:
        raise BTFError(f"{params.constraints}: the sample's constraint layers do not match the "
                       f"photos convincingly anywhere (best correlation {match.score:.3f} at "
                       f"{match.y},{match.x}, below --min-match {params.min_match:g}); give "
                       "--sample-origin Y,X if you know where it is")
    return match.y, match.x, {"origin": [match.y, match.x], "given": False,
                              "correlation": match.score, "runner_up": match.runner_up}


def enlarge_stage(params: EnlargeParams, session: Session) -> Path:
    """Enlarge the sample under the constraint photos; write a compressed store."""
    import psutil

    sample_group = open_group(params.sample)
    check_compressed(sample_group, params.sample)
    group = open_group(params.constraints)
    check_radiance(group, params.constraints)
    u = np.asarray(sample_group["U"][...], np.float64)
    nv, nl, nc, rank = u.shape
    s = np.asarray(sample_group["S"][...], np.float64)
    coefficients = (np.asarray(sample_group["V"][...], np.float32) * s.astype(np.float32))
    h, w = coefficients.shape[:2]
    big_h, big_w = group[RADIANCE].shape[2:4]
    if read_channels(group) != read_channels(sample_group):
        raise BTFError(f"{params.constraints}: channels {read_channels(group)} differ from the "
                       f"sample's {read_channels(sample_group)}")
    if big_h < h or big_w < w:
        raise BTFError(f"{params.constraints}: the photos ({big_h} x {big_w}) are smaller than "
                       f"the sample ({h} x {w}); enlargement needs photos at the target size")
    need = WORKING_COPIES * big_h * big_w * rank * 4
    available = psutil.virtual_memory().available
    if need > 0.8 * available:
        raise BTFError(f"{params.constraints}: enlarging to {big_h} x {big_w} texels at rank "
                       f"{rank} needs about {need / 2**30:.1f} GiB in memory, more than the "
                       f"{available / 2**30:.1f} GiB available (enlargement is not tile-parallel "
                       "yet); use smaller photos or a lower rank")
    eps = float(sample_group.attrs["transform"]["eps"])
    constraints = _read_constraints(params, group, sample_group, coefficients, eps)
    y0, x0, placement = _place_sample(params, constraints, coefficients, session)
    m = nv * nl * nc
    g = constraints.values.shape[-1]
    lam = params.lambda_ if params.lambda_ is not None else LAMBDA_SCALE * m / g
    session.log(f"enlarge: {h} x {w} sample at rank {rank} -> {big_h} x {big_w} under "
                f"{len(constraints.layers)} constraint layer(s) ({g} values per texel, lambda "
                f"{lam:g}) -> {params.out}")
    start = time.perf_counter()
    result = enlarge(coefficients, constraints.values[y0 : y0 + h, x0 : x0 + w],
                     constraints.values, constraints.rows, params=params.enlargement(),
                     guide_weight=float(np.sqrt(lam)), seed=params.seed)
    session.log("enlarge: " + ", ".join(f"{k.replace('_', ' ')} {v:.1f} s"
                                          for k, v in result.seconds.items())
                + f"; {result.rounds} round(s), constraint residual (RMS, log domain) "
                f"{result.residual_rms:.3g} (the sample's own: {result.noise:.3g})")
    new_u, new_s, new_v, basis = refactor(u.reshape(m, rank),
                                          result.coefficients.reshape(-1, rank))
    attrs = {
        "source": "enlarge",
        "source_btf_kind": sample_group.attrs.get("source_btf_kind"),
        "source_shape": [nv, nl, big_h, big_w, nc],
        "transform": sample_group.attrs["transform"],
        "svd": {"rank": rank, "method": "enlargement (paper 000, Algorithm 1), re-factorised"},
        "enlargement": {"sample": params.sample, "constraints": params.constraints,
                        "sample_shape": [h, w], "placement": placement,
                        "constraint_layers": constraints.layers, "lambda": lam,
                        "parameters": dataclasses.asdict(params.enlargement()),
                        "seconds": {**result.seconds, "total": time.perf_counter() - start},
                        "rounds": result.rounds, "changes": result.changes,
                        "constraint_residual": result.residual,
                        "constraint_residual_rms": result.residual_rms,
                        "sample_constraint_residual_rms": result.noise,
                        "damping": result.damping,
                        "constraint_rank": result.constraint_rank,
                        "energy": result.energy},
        "provenance": provenance("enlarge", params),
    }
    for key in ("source_sampling", "source_material"):
        if key in sample_group.attrs:
            attrs[key] = sample_group.attrs[key]
    with atomic_output(params.out, directory=True, overwrite=params.overwrite) as tmp:
        out = create_compressed_store(
            tmp, directions=read_directions(sample_group), channels=read_channels(sample_group),
            ny=big_h, nx=big_w, rank=rank, chunk=sample_group["V"].chunks[0],
            dir_chunk=sample_group["U"].chunks[1], attrs=attrs)
        out["U"][...] = new_u.reshape(nv, nl, nc, rank).astype(np.float32)
        out["S"][...] = new_s.astype(np.float32)
        out["V"][...] = new_v.reshape(big_h, big_w, rank).astype(np.float32)
        if params.keep_phases:
            phases = {"texture_optimization": result.texture_optimization,
                      "statistics": result.statistics}
            for name, phase in phases.items():
                if phase is not None:  # in the output's basis: radiance exp(U c) - eps
                    add_array(out, f"phase_{name}", shape=phase.shape,
                              dims=("y", "x", "component"), chunks=out["V"].chunks,
                              attrs={"long_name": f"coefficients S V^T after {name}"})[...] = (
                        (phase.reshape(-1, rank) @ basis).reshape(phase.shape))
    return Path(params.out)
