"""BTF enlargement's kernels (paper 000): the QP, Texture Optimization, statistical synthesis."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy import ndimage

from tasks.constrained_blend import ConstraintProjector, blend
from tasks.enlargement import mean_colour_rows
from tasks.registration import locate
from tasks.statistical_synthesis import (
    StatisticsParams,
    central_autocorrelation,
    impose,
    impose_statistics,
    measure,
    sample_statistics,
)
from tasks.svd import refactor
from tasks.texture_optimization import (
    SampleLevel,
    TextureOptimizationParams,
    leading_components,
    pick_vote,
    texture_optimization,
)


def _kkt(a, b, m):
    """min ||x - m||^2 s.t. A x = b by the KKT system (least squares for inconsistent rows)."""
    k, r = a.shape[1], a.shape[0]
    kkt = np.block([[2 * np.eye(k), a.T], [a, np.zeros((r, r))]])
    rhs = np.concatenate([2 * m, b])
    return np.linalg.lstsq(kkt, rhs, rcond=None)[0][:k]


@pytest.mark.parametrize("case", ["full row rank", "rank deficient", "more rows than K"])
def test_the_qp_matches_a_kkt_solve_and_meets_the_constraints(case):
    rng = np.random.default_rng(3)
    k = 8
    if case == "full row rank":
        a = rng.standard_normal((3, k))
    elif case == "rank deficient":
        base = rng.standard_normal((2, k))
        a = np.vstack([base, base[0] + base[1], 2 * base[1]])  # 4 rows of rank 2
    else:
        a = rng.standard_normal((12, k))
    b1, b2 = rng.standard_normal((2, 50, k))
    if case == "rank deficient":  # consistent right-hand sides, as for duplicate photos
        b = rng.standard_normal((50, k)) @ a.T
    else:
        b = rng.standard_normal((50, a.shape[0]))
    projector = ConstraintProjector.of(a)
    x, damping = blend(b1, b2, b, projector, alpha=1.0, beta=3.0)
    assert damping == 0.0
    m = (b1 + 3 * b2) / 4
    for t in range(50):
        if case == "more rows than K":  # least squares: the closest point to b A can reach
            expected = np.linalg.lstsq(a, b[t], rcond=None)[0]
        else:
            expected = _kkt(a, b[t], m[t])
        assert np.allclose(x[t], expected, atol=1e-5)
    if case != "more rows than K":
        assert np.abs(x @ a.T - b).max() <= 1e-5 * np.abs(b).max()
    assert projector.rank == {"full row rank": 3, "rank deficient": 2,
                              "more rows than K": k}[case]


def test_the_damped_qp_leaves_the_asked_residual_and_is_the_tikhonov_minimiser():
    rng = np.random.default_rng(4)
    a = rng.standard_normal((3, 6)) * np.array([[1.0], [0.3], [0.01]])  # one weak direction
    m = rng.standard_normal((400, 6))
    b = m @ a.T + 0.5 * rng.standard_normal((400, 3))
    projector = ConstraintProjector.of(a)
    x, damping = blend(m, m, b, projector, noise=0.1)
    assert damping > 0
    assert projector.rms_residual(x, b) == pytest.approx(0.1, rel=1e-6)
    # the minimiser of ||x - m||^2 + ||A x - b||^2 / damping, per texel
    lhs = np.eye(6) + a.T @ a / damping
    direct = np.linalg.solve(lhs, (m + (b @ a) / damping).T).T
    assert np.allclose(x, direct, atol=1e-5)
    exact, _ = blend(m, m, b, projector)
    # damping keeps the result far closer to m than the exact projection does
    assert np.linalg.norm(x - m) < 0.75 * np.linalg.norm(exact - m)


def _covariance(rng, k):
    basis = rng.standard_normal((k, k))
    return basis @ np.diag(np.geomspace(4.0, 0.01, k)) @ basis.T


@pytest.mark.parametrize("damping", [0.0, 0.3])
def test_the_qp_in_a_covariance_metric_is_the_conditional_mean(damping):
    rng = np.random.default_rng(11)
    k = 7
    a = rng.standard_normal((3, k))
    sigma = _covariance(rng, k)
    m = rng.standard_normal((40, k))
    b = rng.standard_normal((40, 3))
    projector = ConstraintProjector.of(a, metric=sigma)
    x = projector.project(m, b, damping=damping)
    # m + Sigma A^T (A Sigma A^T + damping I)^-1 (b - A m): the Gaussian conditional mean
    gain = sigma @ a.T @ np.linalg.inv(a @ sigma @ a.T + damping * np.eye(3))
    assert np.allclose(x, m + (b - m @ a.T) @ gain.T, atol=1e-8)
    if damping == 0:
        assert np.abs(x @ a.T - b).max() < 1e-8
    # the identity metric is the paper's QP
    plain = ConstraintProjector.of(a).project(m, b, damping=damping)
    assert np.allclose(ConstraintProjector.of(a, metric=np.eye(k)).project(m, b,
                                                                           damping=damping),
                       plain, atol=1e-10)
    assert not np.allclose(x, plain, atol=1e-3)


def test_the_prior_damping_finds_the_scale_and_beats_the_plain_qp_on_texels_of_that_prior():
    """Texels drawn around ``m`` with covariance ``c Sigma`` and seen through noisy photos."""
    rng = np.random.default_rng(12)
    k, texels, noise = 8, 20000, 0.05
    sigma = _covariance(rng, k)
    a = rng.standard_normal((4, k))
    worst = 0.0
    for c in (0.02, 0.5):
        m = rng.standard_normal((texels, k))
        truth = m + rng.multivariate_normal(np.zeros(k), c * sigma, texels)
        b = truth @ a.T + noise * rng.standard_normal((texels, 4))
        projector = ConstraintProjector.of(a, metric=sigma)
        damping = projector.prior_damping(m, b, noise)
        assert damping == pytest.approx(noise**2 / c, rel=0.1)
        x, used = blend(m, m, b, projector, noise=noise)
        assert used == damping
        plain, _ = blend(m, m, b, ConstraintProjector.of(a), noise=noise)
        error, plain_error = (float(np.sqrt(np.mean((y - truth) ** 2))) for y in (x, plain))
        worst = max(worst, error / plain_error)
    assert worst < 0.6  # the conditional mean is far nearer the truth than the shortest change
    # photos within their noise of m: nothing to correct
    quiet = m @ a.T + 0.5 * noise * rng.standard_normal((texels, 4))
    x, used = blend(m, m, quiet, ConstraintProjector.of(a, metric=sigma), noise=noise)
    assert used == np.inf and np.allclose(x, m, atol=1e-6)


def test_the_metric_step_is_kept_within_its_trust_region_and_the_plain_qp_does_the_rest():
    from tasks.constrained_blend import TRUST

    rng = np.random.default_rng(13)
    k, texels = 6, 400
    sigma = _covariance(rng, k)
    a = rng.standard_normal((2, k))
    m = rng.standard_normal((texels, k))
    b = m @ a.T + 0.1 * rng.standard_normal((texels, 2))
    b[:20] += 30.0  # a few texels the synthesis got badly wrong
    projector = ConstraintProjector.of(a, metric=sigma)
    x, damping = blend(m, m, b, projector)  # noise 0: the constraints are met exactly
    assert damping == 0.0 and np.abs(x @ a.T - b).max() < 1e-4
    full = projector.project(m, b)
    length = np.linalg.norm((full - m) @ projector.whiten.T, axis=1)
    limit = TRUST * np.median(length)
    inside = length <= limit
    assert inside.sum() >= texels // 2 and not inside[:20].any()
    assert np.allclose(x[inside], full[inside], atol=1e-5)  # short steps: the metric's own
    capped = m + (full - m) * (limit / length)[:, None]
    rest = ConstraintProjector.of(a).project(capped[~inside], b[~inside])
    assert np.allclose(x[~inside], rest, atol=1e-5)  # long ones: capped, then the plain QP
    assert not np.allclose(x[~inside], full[~inside], atol=1e-2)


def _smooth_field(rng, shape, k, sigma=2.5):
    field = ndimage.gaussian_filter(rng.standard_normal((*shape, k)), (sigma, sigma, 0),
                                    mode="wrap")
    return (field / field.std(axis=(0, 1))).astype(np.float32)


def test_texture_optimization_never_increases_its_energy_and_recovers_a_rearrangement():
    rng = np.random.default_rng(0)
    sample = _smooth_field(rng, (64, 64), 5)
    rows = rng.standard_normal((3, 5)).astype(np.float32)
    sample_guide = sample @ rows.T
    # the target is the sample rearranged: quadrants swapped and the whole rolled
    target = np.roll(np.concatenate([np.concatenate([sample[32:, 32:], sample[32:, :32]], 1),
                                     np.concatenate([sample[:32, 32:], sample[:32, :32]], 1)],
                                    0), (5, -7), axis=(0, 1))
    result = texture_optimization(sample, sample_guide, target @ rows.T, shape=(64, 64),
                                  params=TextureOptimizationParams(levels=2, iterations=6),
                                  guide_weight=3.0, seed=1)
    for energies in result.energy:
        assert all(b <= a * (1 + 1e-6) for a, b in itertools.pairwise(energies))
    error = np.sqrt(np.mean((result.coefficients - target) ** 2))
    assert error < 0.15  # of unit-variance channels; a random sample texel gives ~1.4
    shuffled = rng.permutation(target.reshape(-1, 5)).reshape(target.shape)
    assert np.sqrt(np.mean((shuffled - target) ** 2)) > 1.0


@pytest.mark.parametrize("lookups", [0, 5])
def test_the_pick_is_the_nearest_candidate_in_the_search_features(lookups, monkeypatch):
    import tasks.texture_optimization

    monkeypatch.setattr(tasks.texture_optimization, "PICK_EPS", 0.0)  # exact lookups
    rng = np.random.default_rng(11)
    params = TextureOptimizationParams(patch=4, pick=0.3, pick_lookups=lookups)
    sample = rng.standard_normal((20, 24, 6)).astype(np.float32)
    guide = rng.standard_normal((20, 24, 4)).astype(np.float32)
    source = SampleLevel(sample, guide, leading_components(sample, 0.9), 2.0, params, rng)
    x = rng.standard_normal((13, 11, 6)).astype(np.float32)
    target = rng.standard_normal((13, 11, 4)).astype(np.float32)
    qy, qx = (a.ravel() for a in np.meshgrid(np.arange(10), np.arange(8), indexing="ij"))
    match = rng.integers(0, len(source.ys) * source.width, len(qy))
    out = pick_vote(source, x, target, qy, qx, match, params)
    # brute force: every texel's candidates listed, distances in float64
    lead = source.rotation
    feat_s = np.concatenate([sample @ lead, 2.0 * guide], -1).reshape(-1, lead.shape[1] + 4)
    feat_x = np.concatenate([x @ lead, 2.0 * target], -1).reshape(-1, lead.shape[1] + 4)
    my, mx = source.origin(match)
    picked = np.empty((13 * 11, 6), np.float32)
    for t in range(13 * 11):
        ty, tx = divmod(t, 11)
        cands = [(my[i] + ty - qy[i]) * 24 + mx[i] + tx - qx[i] for i in range(len(qy))
                 if 0 <= ty - qy[i] < 4 and 0 <= tx - qx[i] < 4]
        g = ((feat_s[:, lead.shape[1]:] - feat_x[t, lead.shape[1]:]) ** 2).sum(1)
        cands += list(np.argsort(g, kind="stable")[:lookups])
        d = ((feat_s[cands].astype(np.float64) - feat_x[t]) ** 2).sum(1)
        picked[t] = sample.reshape(-1, 6)[cands[int(np.argmin(d))]]
    expected = 0.7 * x + 0.3 * picked.reshape(13, 11, 6)
    np.testing.assert_allclose(out, expected, rtol=0, atol=1e-6)


def test_the_pick_tells_apart_texels_the_guide_tells_apart_and_the_mean_blurs():
    # texels without neighbourhood structure, told apart only by an informative guide (8
    # values of 5 coefficients): a weighted mean of the overlapping matches blurs them
    rng = np.random.default_rng(3)
    sample = rng.standard_normal((48, 48, 5)).astype(np.float32)
    rows = rng.standard_normal((8, 5)).astype(np.float32)
    target = rng.permutation(sample.reshape(-1, 5)).reshape(sample.shape)
    errors = {}
    for pick in (0.0, 0.5, 1.0):
        result = texture_optimization(
            sample, sample @ rows.T, target @ rows.T, shape=(48, 48),
            params=TextureOptimizationParams(levels=1, patch=4, iterations=3, pick=pick),
            guide_weight=3.0, seed=2)
        errors[pick] = float(np.sqrt(np.mean((result.coefficients - target) ** 2)))
    assert errors[1.0] < 0.05  # every texel's own: the lookups find it
    assert errors[0.5] < 0.6 * errors[0.0]
    assert errors[0.0] > 0.3  # the mean of 16 texels fits the guide on average, no texel


def test_only_the_finest_level_picks_and_a_tie_keeps_the_first_candidate():
    rng = np.random.default_rng(4)
    sample = _smooth_field(rng, (40, 40), 5)
    rows = rng.standard_normal((6, 5)).astype(np.float32)
    target = np.roll(sample, (7, -5), axis=(0, 1))
    results = [texture_optimization(
        sample, sample @ rows.T, target @ rows.T, shape=(40, 40),
        params=TextureOptimizationParams(levels=2, patch=4, iterations=2, pick=pick),
        guide_weight=3.0, seed=1) for pick in (0.0, 0.5)]
    # the coarse level and the finest level's matches are the same: only the last vote moved
    assert results[0].energy == results[1].energy
    assert not np.array_equal(results[0].coefficients, results[1].coefficients)
    # a sample of one texel repeated: every candidate ties, and the first (a match) is kept
    params = TextureOptimizationParams(patch=2, pick=1.0, pick_lookups=3)
    flat = np.ones((4, 4, 2), np.float32)
    source = SampleLevel(flat, np.ones((4, 4, 1), np.float32), np.eye(2, dtype=np.float32),
                         1.0, params, rng)
    source.coefficients = rng.standard_normal((4, 4, 2)).astype(np.float32)  # tells them apart
    qy, qx = (a.ravel() for a in np.meshgrid(np.arange(2), np.arange(2), indexing="ij"))
    match = np.array([4, 0, 2, 6])  # origins (1, 1), (0, 0), (0, 2), (2, 0) in a 3-wide grid
    out = pick_vote(source, np.ones((3, 3, 2), np.float32), np.ones((3, 3, 1), np.float32),
                    qy, qx, match, params)
    my, mx = source.origin(match)
    # texel (0, 0) is covered by match 0 only, at offset (0, 0): sample texel (1, 1)
    np.testing.assert_array_equal(out[0, 0], source.coefficients[1, 1])
    # texel (1, 1): the first offer is offset (0, 0) of the grid origin (1, 1), match 3
    np.testing.assert_array_equal(out[1, 1], source.coefficients[my[3], mx[3]])


def test_statistics_imposed_on_itself_change_little_and_pull_noise_towards_the_sample():
    rng = np.random.default_rng(5)
    sample = _smooth_field(rng, (64, 64), 1, sigma=3.0)[..., 0] ** 2  # skewed, correlated
    stats = measure(sample, 3)
    same = impose(sample, stats, iterations=2)
    assert np.abs(same - sample).max() < 0.05 * np.ptp(sample)
    noise = rng.standard_normal((96, 80))
    after = impose(noise, stats, iterations=3)

    def moments(x):
        x = np.asarray(x, np.float64).ravel()
        c = x - x.mean()
        return np.array([x.mean(), x.std(), np.mean(c**3) / x.std() ** 3,
                         np.mean(c**4) / x.std() ** 4])

    target = moments(sample)
    assert np.all(np.abs(moments(after) - target) <= np.abs(moments(noise) - target) + 1e-9)
    assert np.allclose(moments(after), target, rtol=0.02, atol=0.02)
    ac = central_autocorrelation
    assert (np.linalg.norm(ac(after) / ac(after)[3, 3] - ac(sample) / ac(sample)[3, 3])
            < 0.5 * np.linalg.norm(ac(noise) / ac(noise)[3, 3] - ac(sample) / ac(sample)[3, 3]))


def test_imposed_statistics_keep_the_shape_and_pass_other_channels_through():
    rng = np.random.default_rng(6)
    sample, image = _smooth_field(rng, (48, 48), 3), _smooth_field(rng, (64, 80), 3)
    stats = sample_statistics(sample, image.shape[:2], params=StatisticsParams(iterations=1),
                              channels=2)
    out = impose_statistics(image, stats, iterations=1)
    assert out.shape == image.shape and out.dtype == np.float32
    assert np.array_equal(out[..., 2], image[..., 2]) and not np.allclose(out[..., 0],
                                                                          image[..., 0])


def test_refactor_keeps_the_product_and_makes_the_factors_canonical():
    rng = np.random.default_rng(7)
    u, _ = np.linalg.qr(rng.standard_normal((30, 6)))
    c = rng.standard_normal((500, 6)) * np.array([5, 3, 2, 1, 0.5, 0.0])  # one unused
    new_u, s, v, w = refactor(u, c)
    assert np.allclose(new_u @ np.diag(s) @ v.T, u @ c.T, atol=1e-10)
    assert np.allclose(new_u.T @ new_u, np.eye(6), atol=1e-10)
    assert np.allclose(v[:, :5].T @ v[:, :5], np.eye(5), atol=1e-10)
    assert np.all(np.diff(s) <= 0) and s[-1] < 1e-6
    assert np.allclose(c @ w, v * s, atol=1e-10)  # other coefficients map by W


def test_mean_colour_rows_are_exact_for_constant_log_radiance_over_lights():
    rng = np.random.default_rng(8)
    rows = np.repeat(rng.standard_normal((1, 3, 4)), 5, axis=0)  # every light the same
    lin, offset, spread = mean_colour_rows(rows, rng.standard_normal((20, 4)))
    assert np.allclose(lin, rows[0]) and np.allclose(offset, 0) and np.allclose(spread, 0)
    rows = rng.standard_normal((5, 3, 4))
    _, offset, spread = mean_colour_rows(rows, rng.standard_normal((20, 4)))
    assert np.all(offset > 0) and np.all(spread > 0)  # Jensen: log of mean >= mean of log


def test_locate_finds_a_crop_and_scores_a_stranger_low():
    rng = np.random.default_rng(9)
    image = _smooth_field(rng, (120, 100), 3)
    found = locate(image[37:69, 51:83], image)
    assert (found.y, found.x) == (37, 51) and found.score > 0.999
    other = locate(_smooth_field(rng, (32, 32), 3), image)
    assert other.score < 0.9


_SEARCH_IN_A_SESSION = """
import hashlib, sys
import dask, numpy as np
from pipeline.session import RuntimeOptions, Session

def search(n):
    from tasks.texture_optimization import _flat_index
    x = np.random.default_rng(0).standard_normal((n, 32)).astype(np.float32)
    distances, found = _flat_index(x).search(x[:4096], 5)
    return hashlib.sha1(distances.tobytes() + found.tobytes()).hexdigest()

with Session(RuntimeOptions(scheduler=sys.argv[1], workers=2, quiet=True)) as session:
    print(session.compute(dask.delayed(search)(8000))[0])
"""


@pytest.mark.slow  # 6 s: kept out of the default run (4 min), run by .ci/run
def test_faiss_searches_give_the_same_bits_on_every_local_scheduler():
    """faiss's distances change in their last bits with its (OpenMP) BLAS threads: the session
    gives tasks one, as worker processes have. Before, ``btf enlarge`` of a 256^2 sample
    differed between the threads and the processes scheduler.
    """
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    runs = {scheduler: subprocess.run([sys.executable, "-c", _SEARCH_IN_A_SESSION, scheduler],
                                      capture_output=True, text=True, check=True,
                                      env=env).stdout
            for scheduler in ("synchronous", "threads", "processes")}
    assert len(set(runs.values())) == 1, runs


@pytest.mark.parametrize("count", [25, 4096 * 2, 4096 * 3 + 11])
def test_the_coherence_table_searched_in_parts_is_the_one_search(count):
    """The parts (computed as parallel tasks by ``btf enlarge``) give one search's bits,
    duplicates included (a neighbourhood whose exact copy hides its own entry).
    """
    from tasks.texture_optimization import coherence, coherence_parts, coherence_rows

    x = np.random.default_rng(count).standard_normal((count, 32)).astype(np.float32)
    x[count // 2] = x[3]  # an exact duplicate
    whole = coherence_rows(x, 4, 0, count)
    assert len(coherence_parts(count)) == max(1, count // 4096)
    np.testing.assert_array_equal(coherence(x, 4), whole)
    assert whole.shape == (count, 4) and not (whole == np.arange(count)[:, None]).any()


def _nearest_fit_reference(sample, keys, wanted, count, ridge):
    """Each wanted texel's fit over its ``count`` nearest sample texels, by brute force."""
    out = []
    for b in wanted:
        near = np.argsort(((keys - b) ** 2).sum(axis=1), kind="stable")[:count]
        a, y = keys[near].astype(np.float64), sample[near].astype(np.float64)
        a_mean, y_mean = a.mean(axis=0), y.mean(axis=0)
        a, y = a - a_mean, y - y_mean
        gram = a.T @ a
        gram += ridge * np.trace(gram) / a.shape[1] * np.eye(a.shape[1])
        step = (b - a_mean) @ np.linalg.solve(gram, a.T @ y)
        spread = np.sqrt(np.mean(np.sum(y**2, axis=1)))
        out.append(y_mean + step * min(1.0, 2.0 * spread / np.linalg.norm(step)))
    return np.array(out)


@pytest.mark.parametrize("values", [1, 3, 12])
def test_local_regression_is_the_ridge_fit_of_the_nearest_sample_texels(values):
    from tasks.photo_regression import local_regression

    rng = np.random.default_rng(values)
    keys = rng.standard_normal((23, 19, values)).astype(np.float32)
    sample = (np.sin(keys @ rng.standard_normal((values, 5)))
              + 0.1 * rng.standard_normal((23, 19, 5))).astype(np.float32)
    wanted = rng.standard_normal((7, 11, values)).astype(np.float32)
    got, _ = local_regression(sample, keys, wanted, neighbours=40, ridge=0.03)
    count = max(40, 2 * values)
    expected = _nearest_fit_reference(sample.reshape(-1, 5), keys.reshape(-1, values),
                                      wanted.reshape(-1, values), count, 0.03)
    assert got.shape == (7, 11, 5) and got.dtype == np.float32
    np.testing.assert_allclose(got.reshape(-1, 5), expected, rtol=1e-4, atol=1e-4)


def test_local_regression_recovers_a_linear_law_bounds_its_steps_and_takes_a_constant():
    from tasks.photo_regression import local_regression

    rng = np.random.default_rng(5)
    keys = rng.standard_normal((30, 30, 6))
    law, offset = rng.standard_normal((6, 4)), rng.standard_normal(4)
    wanted = 0.5 * rng.standard_normal((9, 9, 6))  # among the sample's values: no step capped
    got, explained = local_regression(keys @ law + offset, keys, wanted, ridge=0.0)
    np.testing.assert_allclose(got, wanted @ law + offset, rtol=1e-3, atol=1e-3)
    assert explained.shape == (9, 9) and np.all(explained > 0.999)  # the law explains all
    # far outside the sample's values: a step of at most twice the neighbours' spread
    far, _ = local_regression(keys @ law + offset, keys, np.full((1, 1, 6), 50.0), ridge=0.0)
    spread = np.sqrt(np.sum(np.var(keys @ law, axis=(0, 1))))
    assert np.all(np.isfinite(far))
    assert np.linalg.norm(far - (keys @ law + offset).mean(axis=(0, 1))) < 4 * spread
    # every sample texel (64, all of them neighbours) with the same photo values: their mean,
    # not a NaN
    coefficients = keys[:8, :8] @ law
    same, explained = local_regression(coefficients, np.ones((8, 8, 6)), wanted)
    np.testing.assert_allclose(same, np.broadcast_to(coefficients.mean(axis=(0, 1)),
                                                     same.shape), rtol=1e-4, atol=1e-4)
    assert np.all(explained == 0)  # values that tell nothing explain nothing


def test_the_share_explained_is_the_adjusted_r2_of_the_fit():
    from tasks.photo_regression import local_regression

    rng = np.random.default_rng(9)
    keys = rng.standard_normal((40, 40, 4))
    signal = keys @ rng.standard_normal((4, 3))
    wanted = 0.5 * rng.standard_normal((5, 5, 4))
    # coefficients the values tell up to some noise, and noise alone
    noise = 0.1 * rng.standard_normal(signal.shape) * signal.std(axis=(0, 1))
    _, half = local_regression(signal + noise, keys, wanted, ridge=0.0)
    _, none = local_regression(noise, keys, wanted, ridge=0.0)
    assert 0.3 < float(np.median(half)) < 0.99, np.median(half)
    assert float(np.median(none)) < 0.1, np.median(none)
    # and the definition: 1 - (RSS / (n - G - 1)) / (TSS / (n - 1)) over the 64 nearest
    near = np.argsort(((keys.reshape(-1, 4) - wanted[0, 0]) ** 2).sum(axis=1))[:64]
    a, y = keys.reshape(-1, 4)[near], (signal + noise).reshape(-1, 3)[near]
    a, y = a - a.mean(axis=0), y - y.mean(axis=0)
    rss = np.sum((y - a @ np.linalg.lstsq(a, y, rcond=None)[0]) ** 2)
    assert half[0, 0] == pytest.approx(max(0.0, 1 - (rss / 59) / (np.sum(y**2) / 63)),
                                       abs=1e-4)


def test_regress_takes_texels_between_the_samples_that_the_photos_determine():
    # Texels of 5 values drawn from a smooth two-parameter family, seen through 3 photo values:
    # the target's texels are new draws, which no sample texel equals. Texture Optimization
    # can only copy (its error is the distance to the nearest sample texel); the regression
    # interpolates between them.
    from tasks.enlargement import EnlargementParams, enlarge

    rng = np.random.default_rng(11)
    mix = rng.standard_normal((2, 5))
    rows = rng.standard_normal((3, 5)).astype(np.float32)

    def texels(shape):
        z = rng.uniform(-1, 1, (*shape, 2))
        return np.tanh(1.5 * z @ mix).astype(np.float32)

    sample, target = texels((32, 32)), texels((40, 40))
    errors, residuals = {}, {}
    for share in (0.0, 1.0):
        params = EnlargementParams(
            texture=TextureOptimizationParams(levels=1, patch=4, iterations=2), statistics=None,
            regress=share, exact=True)
        result = enlarge(sample, sample @ rows.T, target @ rows.T, rows, params=params,
                         guide_weight=3.0, seed=1)
        errors[share] = float(np.sqrt(np.mean((result.coefficients - target) ** 2)))
        residuals[share] = result.residual
    assert errors[1.0] < 0.5 * errors[0.0], errors
    assert residuals[1.0] < 1e-4, residuals  # the QP after the move meets the photos again


def test_a_texel_moves_by_the_share_times_what_its_fit_explains(monkeypatch):
    import tasks.photo_regression
    from tasks.enlargement import EnlargementParams, regressed

    rng = np.random.default_rng(4)
    x = rng.standard_normal((6, 7, 5)).astype(np.float32)
    estimate = rng.standard_normal((6, 7, 5)).astype(np.float32)
    explained = rng.uniform(0, 1, (6, 7)).astype(np.float32)
    monkeypatch.setattr(tasks.photo_regression, "local_regression",
                        lambda *a, **k: (estimate, explained))
    rows = rng.standard_normal((2, 5))
    values = rng.standard_normal((6, 7, 2)).astype(np.float32)
    projector = ConstraintProjector.of(rows)
    got = regressed(x, x, values, values, projector, noise=0.0,
                    params=EnlargementParams(regress=0.5))
    moved = x + (0.5 * explained)[..., None] * (estimate - x)
    np.testing.assert_array_equal(got, blend(moved, moved, values, projector)[0])
    assert regressed(x, x, values, values, projector, noise=0.0,
                     params=EnlargementParams(regress=0.0)) is x


def test_the_value_range_is_the_samples_and_a_move_stops_at_its_edge():
    from tasks.photo_regression import ValueRange

    rng = np.random.default_rng(12)
    rows = rng.standard_normal((9, 4)).astype(np.float32)
    sample = rng.standard_normal((30, 20, 4)).astype(np.float32)
    bounds = ValueRange.of(sample, rows)
    values = sample.reshape(-1, 4) @ rows.T
    np.testing.assert_allclose(bounds.low, values.min(axis=0), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(bounds.high, values.max(axis=0), rtol=1e-5, atol=1e-5)
    # texels inside the range, moves of every length: x + t move stays within, and t is the
    # largest that does (1, or a row at its edge: a little further leaves the range)
    x = 0.3 * rng.standard_normal((500, 4)).astype(np.float32)
    move = (rng.standard_normal((500, 4)) * rng.uniform(0, 4, (500, 1))).astype(np.float32)
    t = bounds.share(x, move)
    assert t.shape == (500,) and np.all((t >= 0) & (t <= 1))
    moved = (x + t[:, None] * move) @ rows.T
    assert np.all(moved >= bounds.low - 1e-4) and np.all(moved <= bounds.high + 1e-4)
    further = (x + (t[:, None] + 1e-3) * move) @ rows.T
    outside = np.any((further < bounds.low) | (further > bounds.high), axis=1)
    assert np.all(outside[t < 1]) and 0.1 < np.mean(t < 1) < 0.9
    # a texel already outside in a row: no further out in it, but free to move back in
    square = ValueRange.of(np.array([[[-1, -1], [1, 1]]], np.float32), np.eye(2))
    outside = np.array([[2.0, 0.0]] * 3, np.float32)
    moves = np.array([[1.0, 0.0], [-1.0, 0.0], [-4.0, 0.0]], np.float32)
    np.testing.assert_allclose(square.share(outside, moves), [0.0, 1.0, 0.75])
    # shapes: (..., K) in, (...) out
    assert bounds.share(x.reshape(20, 25, 4), move.reshape(20, 25, 4)).shape == (20, 25)


def test_range_rows_are_all_rows_or_every_channel_of_evenly_spaced_directions():
    from tasks.photo_regression import range_rows

    basis = np.arange(300 * 3 * 2, dtype=np.float32).reshape(900, 2)
    assert range_rows(basis, 3, most=900) is basis
    picked = range_rows(basis, 3, most=90)
    assert picked.shape == (90, 2)
    directions = picked.reshape(30, 3, 2)[:, 0, 0] / 6  # each direction's first row
    assert directions[0] == 0 and directions[-1] == 299 and np.all(np.diff(directions) > 0)
    np.testing.assert_array_equal(picked.reshape(30, 3, 2)[:, :, 0] % 6, [[0, 2, 4]] * 30)


def test_the_bounded_move_keeps_every_texel_within_the_samples_values(monkeypatch):
    import tasks.photo_regression
    from tasks.enlargement import EnlargementParams, regressed
    from tasks.photo_regression import ValueRange

    rng = np.random.default_rng(13)
    sample = rng.standard_normal((16, 16, 5)).astype(np.float32)
    x = sample[:6, :7].copy()
    estimate = 6 * rng.standard_normal((6, 7, 5)).astype(np.float32)  # far outside
    explained = rng.uniform(0.5, 1, (6, 7)).astype(np.float32)
    monkeypatch.setattr(tasks.photo_regression, "local_regression",
                        lambda *a, **k: (estimate, explained))
    basis = rng.standard_normal((12, 5)).astype(np.float32)
    rows = basis[:2]
    values = x @ rows.T
    projector = ConstraintProjector.of(rows)
    bounds = ValueRange.of(sample, basis)
    params = EnlargementParams(regress=1.0)
    got = regressed(x, sample, sample @ rows.T, values, projector, noise=0.0, params=params,
                    bounds=bounds)
    move = explained[..., None] * (estimate - x)
    moved = x + bounds.share(x, move)[..., None] * move
    np.testing.assert_array_equal(got, blend(moved, moved, values, projector)[0])
    decoded = moved.reshape(-1, 5) @ basis.T
    assert np.all(decoded >= bounds.low - 1e-4) and np.all(decoded <= bounds.high + 1e-4)
    unbounded = regressed(x, sample, sample @ rows.T, values, projector, noise=0.0,
                          params=params)
    assert np.any(unbounded.reshape(-1, 5) @ basis.T < bounds.low - 0.1)  # it would leave


def test_neighbours_of_one_coefficient_explain_nothing_whatever_the_rounding():
    from tasks.photo_regression import local_regression

    rng = np.random.default_rng(6)
    keys = rng.standard_normal((16, 16, 3))
    for value in (0.0, 0.1, 1.0, 3.3, 1000.0):
        _, explained = local_regression(np.full((16, 16, 2), value), keys,
                                        rng.standard_normal((4, 4, 3)))
        assert np.all(explained == 0), value


def test_regress_must_be_a_share():
    from tasks.enlargement import EnlargementParams
    from tasks.errors import InvalidParameter

    for share in (-0.1, 1.5, float("nan")):
        with pytest.raises(InvalidParameter, match="regress"):
            EnlargementParams(regress=share)


def test_photo_mean_is_the_mean_of_the_sample_texels_nearest_in_photo_values():
    from tasks.enlargement import photo_mean

    rng = np.random.default_rng(8)
    sample, keys = rng.standard_normal((16, 16, 5)), rng.standard_normal((16, 16, 2))
    targets = rng.standard_normal((10, 12, 2))
    mean = photo_mean(sample, keys, targets)
    k = 256 // 64  # a 64th of a sample of fewer than 64^2 texels
    distance = np.linalg.norm(targets.reshape(-1, 1, 2) - keys.reshape(1, -1, 2), axis=-1)
    near = np.argsort(distance, axis=1)[:, :k]
    expected = sample.reshape(-1, 5)[near].mean(axis=1).reshape(10, 12, 5)
    np.testing.assert_allclose(mean, expected, rtol=1e-5, atol=1e-6)


def _shrink_case(hidden: str) -> tuple[np.ndarray, np.ndarray]:
    """A 32^2 sample whose first coefficient is its photo, and the rest ``hidden``: 'signs',
    independent of everything the photo shows; or 'slopes' of the photo, which its
    neighbourhoods tell and its value at a texel does not."""
    rng = np.random.default_rng(12)
    photo = ndimage.gaussian_filter(rng.standard_normal((32, 32)), 3.0, mode="wrap")
    photo /= photo.std()
    if hidden == "signs":
        rest = rng.choice([-1.0, 1.0], size=(32, 32, 4))
    else:
        rest = 4.0 * np.stack(np.gradient(photo), axis=-1)
    return np.concatenate([photo[..., None], rest], axis=-1).astype(np.float32), photo[..., None]


@pytest.mark.parametrize(("hidden", "chosen"), [("signs", lambda w: w >= 0.5),
                                                ("slopes", lambda w: w == 0.0)])
def test_choose_shrink_averages_what_the_photo_leaves_open_and_keeps_what_it_tells(hidden,
                                                                                   chosen):
    from tasks.enlargement import SHRINK_WEIGHTS, EnlargementParams, choose_shrink

    sample, values = _shrink_case(hidden)
    rows = np.eye(sample.shape[-1])[:1]
    params = EnlargementParams(texture=TextureOptimizationParams(levels=2, patch=4),
                               statistics=None)
    choice = choose_shrink(sample, values, rows, params=params, guide_weight=3.0, seed=0,
                           radiance=lambda c: c)
    assert set(choice.errors) == set(SHRINK_WEIGHTS) and choice.skipped is None
    best = min(SHRINK_WEIGHTS, key=choice.errors.get)
    assert choice.weight == (best if choice.errors[best] < 0.98 * choice.errors[0.0] else 0.0)
    assert chosen(choice.weight), choice.errors
