"""BTF enlargement, paper 000, Algorithm 1: a large BTF from a small full measurement.

Everything happens on eigentexture coefficients: a texel of the sample ``S ~ U_S Sigma_S
V_S^T`` is the column of ``Sigma_S V_S^T`` (``K`` values), and any texel of the result is
another such column, so the result is ``U_S`` with new coefficients (the sample's ABRDF basis,
new texture). Constraint images are in the log domain of the compression, where a photo under
sample direction row ``i`` of ``U_S`` is the linear function ``U_S[i] x`` of the coefficients.

1. Texture Optimization (:mod:`tasks.texture_optimization`) on the sample's coefficients
   guided by the constraint images gives ``R``;
2. until the relative change of a round is below ``tol`` (at most ``rounds`` rounds):
   statistical synthesis (:mod:`tasks.statistical_synthesis`) of ``R`` gives ``R'``, and the
   per-texel QP (:mod:`tasks.constrained_blend`) between ``R`` and ``R'`` under ``A x = b``
   gives the next ``R``;
3. with ``regress``, each texel of ``R`` is moved toward the expected coefficients given its
   constraint values (a local linear regression fitted on the sample, by ``regress`` times
   the share of variation it explains there, :mod:`tasks.photo_regression`), and the QP
   applied again;
4. with ``shrink``, each texel of ``R`` is moved that share of the way toward the mean of
   the sample texels nearest to it in constraint values (:func:`photo_mean`: the expected
   coefficients given what the photos show, where they leave the texel open), and the QP
   applied again; :func:`choose_shrink` picks the share on the sample itself, its central
   quarter enlarged back to the whole sample, where the truth is known;
5. the result is the last ``R``, which meets the constraints to within the sample's own
   compression error of the constraint layers (the QP's damping, chosen by the discrepancy
   principle, see :mod:`tasks.constrained_blend`), or exactly with ``exact`` (the paper's
   QP; up to nearly dependent rows, and in the least-squares sense for more rows than
   components). (The paper returns ``R'`` without the constraint channels; at convergence the
   two agree, and ``R`` is the one that keeps the constraints.)

**Mean-colour constraints** (paper eq. 10, the mean radiance over the lights of one view) are
not linear in the log domain: ``log(mean_l radiance_l + eps) = logsumexp_l(U_l x) - log L``.
They are approximated by the linear row ``mean_l U_l`` (the mean of the log radiance) with
the target lowered by the Jensen gap ``logsumexp - mean``, averaged over the sample's texels
(:func:`mean_colour_rows`). The gap varies between texels; the spread over the sample is
reported as the approximation's cost.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from tasks.constrained_blend import ConstraintProjector, blend, sample_covariance
from tasks.errors import InvalidParameter
from tasks.photo_regression import ValueRange
from tasks.statistical_synthesis import StatisticsParams, impose_statistics, sample_statistics
from tasks.texture_optimization import TextureOptimizationParams, texture_optimization

METRICS = ("sample", "plain")
SHRINK_WEIGHTS = (0.0, 0.25, 0.5, 0.75, 1.0)  # the shares choose_shrink tries
NEAREST = 64  # sample texels a photo_mean averages (fewer in a sample of under 64^2 texels)
# choose_shrink keeps 0 unless a share lowers the error on the sample by more than this: one
# inner problem's errors move by about 1% from seed to seed and between near choices
# (BENCHMARKS.md, "Lambda chosen inside the sample"), and a stone's 0.6% gain there was a
# loss at full size
SHRINK_MARGIN = 0.02


@dataclass(frozen=True)
class EnlargementParams:
    """Algorithm 1's settings: Texture Optimization, statistics (None: skipped), QP rounds."""

    texture: TextureOptimizationParams = field(default_factory=TextureOptimizationParams)
    statistics: StatisticsParams | None = field(default_factory=StatisticsParams)
    rounds: int = 5
    tol: float = 1e-3
    alpha: float = 1.0
    beta: float = 1.0
    statistics_channels: int | None = None  # None: the components holding statistics_energy
    statistics_energy: float = 0.999
    exact: bool = False  # enforce A x = b exactly instead of to the sample's compression error
    metric: str = "sample"  # the QP's metric: "sample" (the sample's covariance) or "plain"
    regress: float = 0.0  # share of the photos' local regression after the rounds (then a QP)
    shrink: float = 0.0  # share of the way to photo_mean after that (then a QP)

    def __post_init__(self):
        if self.rounds < 1:
            raise InvalidParameter("rounds", f"rounds must be at least 1, got {self.rounds}")
        if not self.tol >= 0:
            raise InvalidParameter("tol", f"tol must be non-negative, got {self.tol}")
        if not self.alpha >= 0:
            raise InvalidParameter("alpha", f"alpha must be non-negative, got {self.alpha}")
        if not 0 < self.statistics_energy <= 1:
            raise InvalidParameter("statistics_energy", f"statistics_energy must be in (0, 1], "
                                                        f"got {self.statistics_energy}")
        if self.metric not in METRICS:
            raise InvalidParameter("metric", f"metric must be one of {', '.join(METRICS)}, "
                                             f"got {self.metric!r}")
        if not 0 <= self.regress <= 1:
            raise InvalidParameter("regress", f"regress must be in [0, 1], got {self.regress}")
        if not 0 <= self.shrink <= 1:
            raise InvalidParameter("shrink", f"shrink must be in [0, 1], got {self.shrink}")
        if not self.beta >= 0 or self.alpha + self.beta <= 0:
            raise InvalidParameter("beta", f"beta must be non-negative (and alpha + beta > 0), "
                                           f"got {self.beta}")


@dataclass
class EnlargementResult:
    """The enlarged coefficients, the intermediate results and how they were reached."""

    coefficients: np.ndarray  # (H, W, K) float32: after the last QP
    texture_optimization: np.ndarray  # (H, W, K): column (1) of the paper's Table 1
    statistics: np.ndarray | None  # (H, W, K): the first round's statistical synthesis, (2)
    seconds: dict[str, float] = field(default_factory=dict)
    rounds: int = 0
    changes: list[float] = field(default_factory=list)
    residual: float = 0.0  # relative ||A x - b|| after the last QP
    residual_rms: float = 0.0  # RMS of A x - b after the last QP (log domain)
    noise: float = 0.0  # the RMS residual the QP leaves: the sample's own (0: exact)
    damping: list[float] = field(default_factory=list)  # per round
    energy: list[list[float]] = field(default_factory=list)
    constraint_rank: int = 0


def enlarge(sample: np.ndarray, sample_constraints: np.ndarray,
            target_constraints: np.ndarray, rows: np.ndarray, *, params: EnlargementParams,
            guide_weight: float, seed: int = 0,
            basis: np.ndarray | None = None) -> EnlargementResult:
    """Enlarge a sample's coefficients to the constraint images' size (Algorithm 1).

    Parameters
    ----------
    sample
        ``(h, w, K)`` coefficients ``Sigma_S V_S^T`` of the sample, per texel.
    sample_constraints, target_constraints
        ``(h, w, G)`` and ``(H, W, G)`` constraint values (log domain) of the sample's texels
        and of the target's: one value per constraint image and channel.
    rows
        ``(G, K)``: the linear function of the coefficients each constraint value is
        (``U_S`` rows; :func:`mean_colour_rows` for a mean colour).
    guide_weight
        ``sqrt(lambda)``, the weight of a constraint value in Texture Optimization.
    basis
        ``(R, K)``: rows of ``U_S`` (:func:`tasks.photo_regression.range_rows`) in which the
        regression's move keeps every texel within the sample's range (None: unbounded).
    """
    sample = np.asarray(sample, np.float32)
    target_constraints = np.asarray(target_constraints, np.float32)
    shape = target_constraints.shape[:2]
    projector = qp_projector(rows, sample, params)
    noise = 0.0 if params.exact else projector.rms_residual(sample, sample_constraints)
    start = time.perf_counter()
    to = texture_optimization(sample, sample_constraints, target_constraints, shape=shape,
                              params=params.texture, guide_weight=guide_weight, seed=seed)
    seconds = {"texture_optimization": time.perf_counter() - start}
    statistics = None if params.statistics is None else sample_statistics(
        sample, shape, params=params.statistics, channels=statistics_channels(sample, params))
    rounds = refine(to.coefficients, target_constraints, projector, noise=noise,
                    params=params, statistics=statistics)
    if params.regress:
        start = time.perf_counter()
        bounds = None if basis is None else ValueRange.of(sample, basis)
        rounds.coefficients = regressed(rounds.coefficients, sample, sample_constraints,
                                        target_constraints, projector, noise=noise,
                                        params=params, bounds=bounds)
        seconds["regression"] = time.perf_counter() - start
    if params.shrink:
        start = time.perf_counter()
        rounds.coefficients = shrunk(rounds.coefficients, sample, sample_constraints,
                                     target_constraints, projector, noise=noise, params=params)
        seconds["shrink"] = time.perf_counter() - start
    return EnlargementResult(
        coefficients=rounds.coefficients, texture_optimization=to.coefficients,
        statistics=rounds.first_statistics, seconds={**seconds, **rounds.seconds},
        rounds=len(rounds.changes), changes=rounds.changes,
        residual=projector.residual(rounds.coefficients, target_constraints),
        residual_rms=projector.rms_residual(rounds.coefficients, target_constraints),
        noise=noise, damping=rounds.damping, energy=to.energy, constraint_rank=projector.rank)


def regressed(x: np.ndarray, sample: np.ndarray, sample_constraints: np.ndarray,
              target_constraints: np.ndarray, projector: ConstraintProjector, *, noise: float,
              params: EnlargementParams, bounds: ValueRange | None = None) -> np.ndarray:
    """``x`` moved toward the photos' local regression, then the QP.

    The regression (:func:`tasks.photo_regression.local_regression`) is fitted on the sample's
    texels; each texel moves ``params.regress`` times the share of its neighbours' variation
    the fit explains, and with ``bounds`` no further than where one of its values would leave
    the sample's range (:meth:`~tasks.photo_regression.ValueRange.share`). The QP
    (:func:`tasks.constrained_blend.blend` of the moved ``x`` alone) meets the constraints
    again as the rounds left them. ``x`` itself for ``regress`` 0.
    """
    if params.regress == 0 or not target_constraints.shape[-1]:
        return x
    from tasks.photo_regression import local_regression

    estimate, explained = local_regression(sample, sample_constraints, target_constraints)
    move = (np.float32(params.regress) * explained)[..., None] * (estimate - x)
    if bounds is not None:
        move *= bounds.share(x, move)[..., None]
    moved = x + move
    return blend(moved, moved, target_constraints, projector, noise=noise)[0]


def photo_mean(sample: np.ndarray, sample_constraints: np.ndarray,
               target_constraints: np.ndarray) -> np.ndarray:
    """Each target texel's mean of the sample texels nearest to it in constraint values.

    The :data:`NEAREST` nearest (a 64th of the sample's texels if fewer, at least one), in the
    log domain of the constraint values: an estimate of the coefficients given what the
    photos show, which averages over what they leave open (a slope's direction under one
    near-top light). ``(H, W, K)`` float32, computed a block of texels at a time.
    """
    from scipy.spatial import cKDTree

    flat = np.asarray(sample, np.float32).reshape(-1, sample.shape[-1])
    keys = np.asarray(sample_constraints, np.float64).reshape(len(flat), -1)
    queries = np.asarray(target_constraints, np.float64).reshape(-1, keys.shape[-1])
    k = max(1, min(NEAREST, len(flat) // 64))
    tree = cKDTree(keys)
    out = np.zeros((len(queries), flat.shape[-1]), np.float32)
    for a in range(0, len(queries), 16384):
        _, near = tree.query(queries[a : a + 16384], k=k)
        near = np.reshape(near, (len(near), k))
        for j in range(k):  # summed a neighbour at a time: a block's K values, not k x K
            out[a : a + 16384] += flat[near[:, j]]
    out /= np.float32(k)
    return out.reshape(*target_constraints.shape[:2], -1)


def shrunk(x: np.ndarray, sample: np.ndarray, sample_constraints: np.ndarray,
           target_constraints: np.ndarray, projector: ConstraintProjector, *, noise: float,
           params: EnlargementParams) -> np.ndarray:
    """``x`` moved ``params.shrink`` of the way to :func:`photo_mean`, then the QP.

    ``x`` itself for ``shrink`` 0 or no constraint values.
    """
    if params.shrink == 0 or not target_constraints.shape[-1]:
        return x
    mean = photo_mean(sample, sample_constraints, target_constraints)
    moved = x + np.float32(params.shrink) * (mean - x)
    return blend(moved, moved, target_constraints, projector, noise=noise)[0]


@dataclass(frozen=True)
class ShrinkChoice:
    """What :func:`choose_shrink` chose, and from what."""

    weight: float
    errors: dict[float, float]  # per share tried: the error where the truth is known
    seconds: float
    skipped: str | None = None  # why nothing was tried (weight 0)


def choose_shrink(sample: np.ndarray, sample_constraints: np.ndarray, rows: np.ndarray, *,
                  params: EnlargementParams, guide_weight: float, seed: int,
                  radiance: Callable[[np.ndarray], np.ndarray],
                  basis: np.ndarray | None = None) -> ShrinkChoice:
    """The share of :func:`shrunk` with the least error on a problem whose truth is known.

    The sample's central quarter (half its size in each direction) is enlarged back to the
    whole sample under the sample's own constraint values, with ``params`` (``shrink`` 0);
    each of :data:`SHRINK_WEIGHTS` is applied to the result, and the one whose texels outside
    the quarter (at most 8,192 of them, evenly spread) are nearest the sample's own wins
    if it beats 0 (the result kept) by more than :data:`SHRINK_MARGIN`.
    ``radiance`` maps coefficients ``(N, K)`` to the radiance the error is measured in
    ``(N, R)`` (rows of the sample's choosing); the error is the mean over texels of each
    texel's RMS, as eq. (11). Too small a sample for a neighbourhood at one level: weight 0.
    """
    start = time.perf_counter()
    h, w = sample.shape[:2]
    inner = (slice(h // 4, h // 4 + h // 2), slice(w // 4, w // 4 + w // 2))
    texture = params.texture
    levels = texture.levels
    while levels > 1 and -(-(min(h, w) // 2) // 2 ** (levels - 1)) < texture.patch:
        levels -= 1
    if min(h // 2, w // 2) < texture.patch or not sample_constraints.shape[-1]:
        return ShrinkChoice(0.0, {}, time.perf_counter() - start,
                            skipped=f"a {h // 2} x {w // 2} quarter of the sample is smaller "
                                    f"than a neighbourhood ({texture.patch} texels)"
                            if sample_constraints.shape[-1] else "no constraint values")
    inner_params = replace(params, shrink=0.0, texture=replace(texture, levels=levels))
    result = enlarge(sample[inner], sample_constraints[inner], sample_constraints, rows,
                     params=inner_params, guide_weight=guide_weight, seed=seed, basis=basis)
    projector = qp_projector(rows, sample[inner], params)
    noise = 0.0 if params.exact else projector.rms_residual(sample[inner],
                                                            sample_constraints[inner])
    mean = photo_mean(sample[inner], sample_constraints[inner], sample_constraints)
    outside = np.ones((h, w), bool)
    outside[inner] = False
    picked = np.flatnonzero(outside)  # at most about 8192 of them, evenly spread
    picked = picked[:: -(-len(picked) // 8192)]
    truth = radiance(np.asarray(sample, np.float32).reshape(h * w, -1)[picked])
    errors = {}
    for weight in SHRINK_WEIGHTS:
        moved = result.coefficients + np.float32(weight) * (mean - result.coefficients)
        if weight:
            moved = blend(moved, moved, sample_constraints, projector, noise=noise)[0]
        diff = radiance(moved.reshape(h * w, -1)[picked]) - truth
        errors[weight] = float(np.mean(np.sqrt(np.mean(diff**2, axis=1))))
    best = min(SHRINK_WEIGHTS, key=lambda weight: errors[weight])
    if errors[best] >= (1 - SHRINK_MARGIN) * errors[0.0]:
        best = 0.0
    return ShrinkChoice(best, errors, time.perf_counter() - start)


def qp_projector(rows: np.ndarray, sample: np.ndarray,
                 params: EnlargementParams) -> ConstraintProjector:
    """The QP's projector: in the sample's covariance metric, or plain (``params.metric``)."""
    return ConstraintProjector.of(
        rows, metric=sample_covariance(sample) if params.metric == "sample" else None)


def statistics_channels(sample: np.ndarray, params: EnlargementParams) -> int:
    """How many leading coefficient channels statistical synthesis imposes statistics on.

    ``params.statistics_channels`` if given, else the fewest leading channels holding
    ``statistics_energy`` of the sample's coefficient variance over its texels (the channels
    are ``Sigma V^T``, in decreasing singular value): the rest carry too little to be seen,
    and cost as much each.
    """
    if params.statistics_channels is not None:
        return min(params.statistics_channels, sample.shape[-1])
    flat = np.asarray(sample, np.float64).reshape(-1, sample.shape[-1])
    variance = flat.var(axis=0)
    total = float(variance.sum())
    if total <= 0:
        return 1
    share = np.cumsum(variance) / total
    return int(min(np.searchsorted(share, params.statistics_energy * (1 - 1e-12)) + 1,
                   len(share)))


@dataclass
class Rounds:
    """Where the rounds of statistics and QP ended, and how they went."""

    coefficients: np.ndarray
    first_statistics: np.ndarray | None
    changes: list[float]
    damping: list[float]
    seconds: dict[str, float]


def refine(r: np.ndarray, target_constraints: np.ndarray, projector: ConstraintProjector, *,
           noise: float, params: EnlargementParams, statistics) -> Rounds:
    """Algorithm 1's loop: statistical synthesis of ``R``, then the QP between the two.

    ``statistics`` are the sample's measured channel statistics
    (:func:`tasks.statistical_synthesis.sample_statistics`), or None: one QP of ``R`` alone.
    """
    first, changes, dampings = None, [], []
    seconds = {"statistics": 0.0, "qp": 0.0}
    for _ in range(params.rounds):
        start = time.perf_counter()
        r_stats = r if statistics is None else impose_statistics(
            r, statistics, iterations=params.statistics.iterations)
        seconds["statistics"] += time.perf_counter() - start
        if first is None and statistics is not None:
            first = r_stats
        start = time.perf_counter()
        new, damping = blend(r, r_stats, target_constraints, projector, alpha=params.alpha,
                             beta=params.beta, noise=noise)
        seconds["qp"] += time.perf_counter() - start
        dampings.append(damping)
        norm = float(np.linalg.norm(r))
        changes.append(float(np.linalg.norm(new - r)) / norm if norm else 0.0)
        r = new
        if statistics is None or changes[-1] < params.tol:
            break
    return Rounds(r, first, changes, dampings, seconds)


def mean_colour_rows(rows: np.ndarray, sample: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                    np.ndarray]:
    """Linear stand-in for a mean-colour constraint of one view (see the module).

    ``rows`` are ``U_S``'s rows of that view, ``(lights, channels, K)``; ``sample`` the
    sample's coefficients ``(..., K)``. Returns the rows ``(channels, K)`` (the mean over
    lights), the offset ``(channels,)`` to subtract from ``log(mean colour + eps)`` (the
    Jensen gap averaged over the sample), and the gap's standard deviation over the sample
    ``(channels,)``: the error the approximation makes on the sample's own texels.
    """
    from scipy.special import logsumexp

    rows = np.asarray(rows, np.float64)
    flat = np.asarray(sample, np.float32).reshape(-1, rows.shape[-1])
    lights = rows.shape[0]
    step = max(1, (16 << 20) // (8 * rows.shape[0] * rows.shape[1]))  # texels per 16 MiB
    gaps = []
    for k in range(0, len(flat), step):
        logs = np.einsum("lck,nk->nlc", rows, flat[k : k + step])  # log(radiance + eps)
        gaps.append(logsumexp(logs, axis=1) - np.log(lights) - logs.mean(axis=1))  # >= 0
    gap = np.concatenate(gaps)
    return rows.mean(axis=0), gap.mean(axis=0), gap.std(axis=0)
