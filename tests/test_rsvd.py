"""The randomized SVD driver on its own: passes over an in-memory matrix, against numpy's SVD."""

from __future__ import annotations

import numpy as np
import pytest

from tasks.rsvd import randomized_svd, randomized_svd_rows
from tasks.svd import (
    BlockCheck,
    PassPart,
    TileSketch,
    co_project,
    co_range_test,
    combine_parts,
    frobenius2,
    power_step,
    project,
    row_product,
    tile_test_matrix,
)


def in_memory(a: np.ndarray, block_rows: int, tile_cols: int = 64):
    """A ``run_pass`` over the rows of ``a`` in blocks, counting its passes.

    The one-view sketch runs as the pipeline runs it: by tiles of ``tile_cols`` columns, each
    by row blocks, keeping each tile's co-range sketch for the ``sketch-vectors`` step.
    """
    a32 = a.astype(np.float32)
    blocks = [(r, a32[r : r + block_rows]) for r in range(0, a.shape[0], block_rows)]
    calls, kept = [], {}

    def run_pass(kind: str, **arrays) -> PassPart:
        calls.append(kind)
        parts, ok = [], BlockCheck()
        if kind == "sketch":
            for c0 in range(0, a.shape[1], tile_cols):
                tile = TileSketch(arrays["sketch"], arrays["seed"], (0, c0),
                                  a32[:, c0 : c0 + tile_cols].shape[1])
                for r, rows in blocks:
                    tile.add(r, rows[:, c0 : c0 + tile_cols])
                kept[c0] = tile.w
                f2 = frobenius2(a32[:, c0 : c0 + tile_cols])
                parts.append(PassPart(tile.sums(), {}, ok, f2))
            return combine_parts(*parts)
        if kind == "sketch-vectors":
            v = np.vstack([kept[c0].T.astype(np.float64) @ arrays["m"] for c0 in sorted(kept)])
            return PassPart({"v": v}, {}, ok, 0.0)
        for r, rows in blocks:
            f2 = float(np.sum(rows.astype(np.float64) ** 2))
            if kind == "power":
                parts.append(PassPart({"w": power_step(rows, arrays["x"])}, {}, ok, 0.0))
            else:
                parts.append(PassPart({}, {"z": [(r, project(rows, arrays["x"]))]}, ok, f2))
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


def _one_pass(a, rank, extra, *, block_rows=23, tile_cols=64, seed=2):
    run_pass, calls = in_memory(a, block_rows, tile_cols)
    f = randomized_svd(run_pass, rows=a.shape[0], texels=a.shape[1], rank=rank, extra=extra,
                       iterations=0, seed=seed, one_pass=True)
    return f, calls


def test_one_pass_reads_once_is_near_optimal_and_estimates_its_error():
    # a slowly decaying spectrum, where the sketch size matters
    a = _matrix(300, 900, lambda i: 1 / (1 + i / 4.0))
    rank = 10
    optimal = np.sqrt(np.sum(np.linalg.svd(a, compute_uv=False)[rank:] ** 2))
    ratios = {}
    for extra in (rank + 1, 5 * rank + 1):  # k = 2K + 1 (the former default), 6K + 1
        f, calls = _one_pass(a, rank, extra)
        assert calls == ["sketch", "sketch-vectors"]  # one pass; V from the kept sketches
        err = np.linalg.norm(a - (f.u * f.s) @ f.v.T)
        ratios[extra] = err / optimal
        assert f.error["log_relative_frobenius"] * np.linalg.norm(a) == pytest.approx(
            err, rel=0.35)
        assert np.allclose(f.u.T @ f.u, np.eye(rank), atol=1e-6)
        assert np.allclose(f.v.T @ f.v, np.eye(rank), atol=1e-6)
        assert f.widths == {"sketch_k": rank + extra, "sketch_s": 2 * (rank + extra) + 1,
                            "sketch_t": 10}
    assert ratios[5 * rank + 1] < 1.2 < 1.4 < ratios[rank + 1], ratios


def test_one_pass_with_sketches_as_large_as_the_rows_is_the_exact_svd():
    # k and s reach the 40 rows: Q = I and Psi = I, so the factors are the truncated SVD's
    a = _matrix(40, 700, lambda i: 5 * np.exp(-i / 5.0)) + 1.0
    f, _ = _one_pass(a, 8, 100)
    assert f.widths["sketch_k"] == f.widths["sketch_s"] == 40
    u, s, vt = np.linalg.svd(a.astype(np.float32).astype(np.float64), full_matrices=False)
    assert np.allclose(f.s, s[:8], rtol=1e-5)
    assert np.allclose(np.abs(np.sum(f.u * u[:, :8], axis=0)), 1, atol=1e-5)
    assert np.allclose(np.abs(np.sum(f.v * vt[:8].T, axis=0)), 1, atol=1e-5)


def test_one_pass_with_an_exact_co_range_alone_and_its_error_sketch():
    a = _matrix(40, 700, lambda i: 1 / (1 + i / 3.0))
    f, _ = _one_pass(a, 6, 19)  # k = 25 < 40 rows; s = min(51, 40) = 40 rows: Psi = I
    assert (f.widths["sketch_k"], f.widths["sketch_s"]) == (25, 40)
    optimal = np.sqrt(np.sum(np.linalg.svd(a, compute_uv=False)[6:] ** 2))
    a64 = a.astype(np.float32).astype(np.float64)
    assert np.linalg.norm(a64 - (f.u * f.s) @ f.v.T) < 1.2 * optimal
    assert np.allclose(f.v.T @ f.v, np.eye(6), atol=1e-6)
    # the estimate's V^T Phi (from W Phi) is that of the V written, with the tiles' own Phi
    phi = np.vstack([tile_test_matrix(2, 2, (0, c0), min(64, 700 - c0), 10)
                     for c0 in range(0, 700, 64)]).astype(np.float64)
    direct = np.linalg.norm(a64 @ phi - (f.u * f.s) @ (f.v.T @ phi)) / np.sqrt(10)
    assert f.error["log_relative_frobenius"] * np.linalg.norm(a64) == pytest.approx(direct,
                                                                                   rel=1e-6)


def test_one_pass_factors_do_not_depend_on_the_row_blocks():
    a = _matrix(300, 400, lambda i: 1 / (1 + i / 4.0))
    one, _ = _one_pass(a, 6, 31, block_rows=300)
    other, _ = _one_pass(a, 6, 31, block_rows=37)
    assert np.allclose(one.s, other.s, rtol=1e-5)
    assert np.allclose(np.abs(np.sum(one.v * other.v, axis=0)), 1, atol=1e-4)


def test_the_co_range_test_matrix_is_the_same_whoever_makes_which_rows():
    whole = co_range_test(5, 30, 0, 3000).toarray()
    assert np.array_equal(whole[:, 1000:1500], co_range_test(5, 30, 1000, 1500).toarray())
    assert np.array_equal(whole[:, 1023:1025], co_range_test(5, 30, 1023, 1025).toarray())
    assert not np.array_equal(whole, co_range_test(6, 30, 0, 3000).toarray())
    # a sparse sign map: 8 entries +-1 in distinct rows of every column
    assert np.array_equal(np.count_nonzero(whole, axis=0), np.full(3000, 8))
    assert set(np.unique(whole)) == {-1.0, 0.0, 1.0}
    assert np.count_nonzero(co_range_test(5, 3, 0, 10).toarray(), axis=0).tolist() == [3] * 10


@pytest.mark.parametrize("rows,texels,width", [
    (1, 1, 3),  # a single value; fewer columns than entries per row (3 of 8)
    (37, 1000, 193),  # rows and texels off the loops' group and run lengths
    (64, 640, 9),  # whole groups and runs; barely more columns than entries
])
def test_the_compiled_sign_products_are_the_sparse_products(rows, texels, width):
    from tasks.sketch_kernel import add_sign_columns, add_sign_rows
    from tasks.svd import sign_map

    rng = np.random.default_rng(rows)
    a = (rng.standard_normal((rows, 2 * texels)) * np.logspace(-3, 3, 2 * texels)
         ).astype(np.float32)[:, ::2]  # a strided view, values over six decades
    omega = sign_map(7, 1, (0, 0), texels, width)
    dense = np.zeros((texels, width))
    np.put_along_axis(dense, omega[0], omega[1], axis=1)
    start = rng.standard_normal((rows, width)).astype(np.float32)
    y = start.copy()
    add_sign_columns(a, *omega, y)
    exact = start + a.astype(np.float64) @ dense
    # each sum within float rounding of the sizes of its own terms (not of the largest sum)
    assert np.all(np.abs(y - exact) <= 1e-6 * (np.abs(start) + np.abs(a) @ np.abs(dense)))
    psi = sign_map(8, 3, (0,), rows, width)  # Psi^T: a row per matrix row
    dense_psi = np.zeros((rows, width))
    np.put_along_axis(dense_psi, psi[0], psi[1], axis=1)
    w = np.zeros((width, texels), np.float32)
    add_sign_rows(a, *psi, w)
    exact = dense_psi.T @ a.astype(np.float64)
    assert np.all(np.abs(w - exact) <= 1e-5 * (np.abs(dense_psi.T) @ np.abs(a)))
    again = np.zeros_like(w)
    add_sign_rows(np.ascontiguousarray(a), *psi, again)
    assert np.array_equal(w, again)  # fixed order: a copy of the input gives the same bits


def test_the_compiled_sign_products_refuse_what_does_not_fit():
    from tasks.sketch_kernel import add_sign_columns, add_sign_rows
    from tasks.svd import sign_map

    a = np.ones((4, 10), np.float32)
    cols, signs = sign_map(1, 1, (0,), 10, 12)
    with pytest.raises(ValueError, match="outside its 11 columns"):
        add_sign_columns(a, cols, signs, np.zeros((4, 11), np.float32))
    with pytest.raises(ValueError, match="a sign map of 4 rows"):
        add_sign_rows(a, cols, signs, np.zeros((12, 10), np.float32))
    with pytest.raises(TypeError, match="y must be a C-contiguous float32 matrix"):
        add_sign_columns(a, cols, signs, np.zeros((4, 12)))


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
