"""The randomized SVD driver on its own: passes over an in-memory matrix, against numpy's SVD."""

from __future__ import annotations

import numpy as np
import pytest

from tasks.rsvd import randomized_svd, randomized_svd_rows
from tasks.svd import (
    BlockCheck,
    PassPart,
    co_project,
    combine_parts,
    power_step,
    project,
    row_product,
    sketch_rows,
)


def in_memory(a: np.ndarray, block_rows: int):
    """A ``run_pass`` over the rows of ``a`` in blocks, counting its passes."""
    a32 = a.astype(np.float32)
    blocks = [(r, a32[r : r + block_rows]) for r in range(0, a.shape[0], block_rows)]
    calls = []

    def run_pass(kind: str, **arrays) -> PassPart:
        calls.append(kind)
        parts, ok = [], BlockCheck()
        for r, rows in blocks:
            f2 = float(np.sum(rows.astype(np.float64) ** 2))
            if kind == "power":
                parts.append(PassPart({"w": power_step(rows, arrays["x"])}, {}, ok, 0.0))
            elif kind == "project":
                parts.append(PassPart({}, {"z": [(r, project(rows, arrays["x"]))]}, ok, f2))
            else:
                psi = arrays["psi"][:, r : r + rows.shape[0]]
                y, z, w = sketch_rows(rows, arrays["omega"], arrays["phi"], psi)
                parts.append(PassPart({"w": w}, {"y": [(r, y)], "z": [(r, z)]}, ok, f2))
        return combine_parts(*parts)

    return run_pass, calls


def _matrix(m, n, decay, seed=0):
    rng = np.random.default_rng(seed)
    u, _ = np.linalg.qr(rng.standard_normal((m, min(m, n))))
    v, _ = np.linalg.qr(rng.standard_normal((n, min(m, n))))
    return (u * decay(np.arange(min(m, n)))) @ v.T


@pytest.mark.parametrize("shape", [(90, 400), (400, 90)])
@pytest.mark.parametrize("iterations", [1, 2])
def test_multi_pass_factors_are_near_optimal_and_use_the_planned_passes(shape, iterations):
    a = _matrix(*shape, lambda i: 10 * np.exp(-i / 6.0))
    run_pass, calls = in_memory(a, 17)
    rank = 8
    f = randomized_svd(run_pass, rows=shape[0], texels=shape[1], rank=rank, extra=6,
                       iterations=iterations, seed=3)
    assert calls == ["power"] * iterations + ["project"]
    exact = np.linalg.svd(a, compute_uv=False)
    optimal = np.sqrt(np.sum(exact[rank:] ** 2))
    err = np.linalg.norm(a - (f.u * f.s) @ f.v.T)
    assert err <= 1.02 * optimal
    assert np.allclose(f.u.T @ f.u, np.eye(rank), atol=1e-6)
    assert np.allclose(f.v.T @ f.v, np.eye(rank), atol=1e-6)
    # the error from the identity is the measured one (the data is float32: rel. ~1e-7)
    assert f.error["log_relative_frobenius"] == pytest.approx(err / np.linalg.norm(a),
                                                              rel=2e-2)


def test_power_iterations_are_needed_on_a_slow_spectrum():
    a = _matrix(120, 300, lambda i: 1 / np.sqrt(1 + i))
    exact = np.linalg.svd(a, compute_uv=False)
    optimal = np.sqrt(np.sum(exact[10:] ** 2))
    errors = []
    for q in (0, 2):
        run_pass, _ = in_memory(a, 40)
        f = randomized_svd(run_pass, rows=120, texels=300, rank=10, extra=4, iterations=q,
                           seed=1)
        errors.append(np.linalg.norm(a - (f.u * f.s) @ f.v.T) / optimal)
    assert errors[1] < 1.02 < errors[0]  # the tolerance above would catch a driver without them


def test_one_pass_reads_once_and_estimates_its_error():
    a = _matrix(100, 350, lambda i: 30 * np.exp(-i / 8.0))
    run_pass, calls = in_memory(a, 23)
    f = randomized_svd(run_pass, rows=100, texels=350, rank=10, extra=11, iterations=0,
                       seed=2, one_pass=True)
    assert calls == ["sketch"]
    err = np.linalg.norm(a - (f.u * f.s) @ f.v.T)
    optimal = np.sqrt(np.sum(np.linalg.svd(a, compute_uv=False)[10:] ** 2))
    assert err < 3 * optimal
    assert f.error["log_relative_frobenius"] * np.linalg.norm(a) == pytest.approx(err, rel=0.35)


def test_the_same_seed_gives_the_same_factors_whatever_the_blocks():
    a = _matrix(60, 200, lambda i: np.exp(-i / 4.0))
    results = []
    for rows in (60, 7):
        run_pass, _ = in_memory(a, rows)
        results.append(randomized_svd(run_pass, rows=60, texels=200, rank=5, extra=5,
                                      iterations=2, seed=9))
    # other blocks sum in another order: equal to rounding, and the same subspace
    assert np.allclose(results[0].s, results[1].s, rtol=1e-5)
    assert np.allclose(np.abs(results[0].v.T @ results[1].v), np.eye(5), atol=1e-4)


def by_tiles(a: np.ndarray, tile: int):
    """A row-side ``run_pass`` over the columns of ``a`` in tiles, counting its passes."""
    a32 = a.astype(np.float32)
    calls = []

    def run_pass(kind: str, **arrays) -> PassPart:
        calls.append(kind)
        parts = []
        for t in range(0, a.shape[1], tile):
            at = a32[:, t : t + tile]
            exact = kind != "row-power"
            z = co_project(at, arrays["q"], exact=exact)
            if kind == "row-vectors":
                v = np.zeros((a.shape[1], arrays["m"].shape[1]))
                v[t : t + tile] = z @ arrays["m"]
                parts.append(PassPart({"v": v}, {}, BlockCheck(), 0.0))
                continue
            sums = {"y": row_product(at, z, exact=exact)} | ({"g": z.T @ z} if exact else {})
            parts.append(PassPart(sums, {}, BlockCheck(),
                                  float(np.sum(at.astype(np.float64) ** 2))))
        return combine_parts(*parts)

    return run_pass, calls


@pytest.mark.parametrize("shape", [(90, 400), (60, 1000)])
@pytest.mark.parametrize("iterations", [1, 2])
def test_the_row_side_is_near_optimal_orthonormal_and_uses_its_passes(shape, iterations):
    a = _matrix(*shape, lambda i: 10 * np.exp(-i / 6.0))
    run_pass, calls = by_tiles(a, 37)
    rank = 8
    f = randomized_svd_rows(run_pass, rows=shape[0], texels=shape[1], rank=rank, extra=6,
                            iterations=iterations, seed=3)
    assert calls == ["row-power"] * iterations + ["row-gram", "row-vectors"]
    exact = np.linalg.svd(a, compute_uv=False)
    err = np.linalg.norm(a - (f.u * f.s) @ f.v.T)
    assert err <= 1.02 * np.sqrt(np.sum(exact[rank:] ** 2))
    assert np.allclose(f.s, exact[:rank], rtol=5e-3)  # Ritz values: from below
    assert np.allclose(f.u.T @ f.u, np.eye(rank), atol=1e-6)
    assert np.allclose(f.v.T @ f.v, np.eye(rank), atol=1e-6)
    assert f.error["log_relative_frobenius"] == pytest.approx(err / np.linalg.norm(a),
                                                              rel=2e-2)


def test_the_row_side_needs_its_power_iterations_on_a_slow_spectrum():
    a = _matrix(60, 1000, lambda i: 1 / np.sqrt(1 + i))
    optimal = np.sqrt(np.sum(np.linalg.svd(a, compute_uv=False)[10:] ** 2))
    errors = []
    for q in (0, 2):
        run_pass, _ = by_tiles(a, 64)
        f = randomized_svd_rows(run_pass, rows=60, texels=1000, rank=10, extra=4,
                                iterations=q, seed=1)
        errors.append(np.linalg.norm(a - (f.u * f.s) @ f.v.T) / optimal)
    assert errors[1] < 1.02 < errors[0]
