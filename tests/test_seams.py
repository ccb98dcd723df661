"""The border measures of tasks/seams.py against hand-built borders and a brute-force search."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.lib.stride_tricks import sliding_window_view

from tasks.seams import (
    Borders,
    PatchExemplar,
    border_figures,
    line_sides,
    seam_ratios,
    structure_ratios,
)


def stripes(h: int, w: int, period: int, shift: float = 0.0) -> np.ndarray:
    """Vertical stripes (lines ``period`` apart), three tone curves as channels."""
    x = np.arange(w)[None, :] - shift
    g = 0.5 + 0.5 * np.cos(2 * np.pi * x / period) ** 7 * np.ones((h, 1))
    return np.stack([g, np.sqrt(g), g * g], axis=-1).astype(np.float32)


def test_the_seam_ratio_is_the_mean_difference_across_a_line_over_the_rest():
    rng = np.random.default_rng(0)
    image = rng.random((20, 30, 2))
    ratios = seam_ratios(image, Borders((7,), (11,)))
    dy = np.abs(np.diff(image, axis=0)).mean(-1)  # dy[k]: rows k, k + 1
    dx = np.abs(np.diff(image, axis=1)).mean(-1)
    assert ratios == pytest.approx((dy[6].mean() / np.delete(dy, 6, axis=0).mean(),
                                    dx[:, 10].mean() / np.delete(dx, 10, axis=1).mean()))
    wrapped = seam_ratios(image, Borders.periodic())
    across = np.abs(image[0] - image[-1]).mean(-1).mean()
    assert wrapped[0] == pytest.approx(across / dy.mean())


def test_a_periodic_texture_cut_at_whole_periods_has_no_border():
    sample = stripes(64, 64, 16)
    exemplar = PatchExemplar(sample)
    tile = stripes(48, 48, 16, shift=-4)  # three whole periods: the wrap continues the lines
    figures = border_figures(exemplar, tile, Borders.periodic(), reach=8)
    assert figures.worst_structure == pytest.approx(1.0)  # both at the floor: copies
    assert figures.seam[1] < 0.1  # the wrap runs between two lines, where nothing changes
    off = border_figures(exemplar, stripes(48, 40, 16, shift=-4), Borders.periodic(), reach=8)
    # 2.5 periods: the wrap doubles a line; the pairs across it lie where nothing changes
    assert off.structure[1] > 1.3 > off.seam[1]


def test_a_crossfaded_break_stands_out_in_both_measures():
    """Lines shifted by half their spacing below row 40, crossfaded over 12 rows: the band
    holds doubled lines, and vertical differences where the stripes have none."""
    sample = stripes(96, 96, 24)
    exemplar = PatchExemplar(sample)
    top, bottom = stripes(80, 96, 24), stripes(80, 96, 24, shift=12)
    ramp = np.clip((np.arange(80) - 34) / 12, 0, 1)[:, None, None]
    broken = (1 - ramp) * top + ramp * bottom
    borders = Borders((40,), ())
    seam = seam_ratios(broken, borders)[0]
    structure = structure_ratios(exemplar, broken, borders, reach=12)[0]
    assert seam > 3 * 1.3 and structure > 3 * 1.3, (seam, structure)
    clean = structure_ratios(exemplar, top, borders, reach=12)[0]
    assert clean == pytest.approx(1.0)


def test_a_framed_tile_is_judged_on_its_own_side_of_its_borders():
    sample = stripes(96, 96, 24)
    exemplar = PatchExemplar(sample)
    frame = stripes(80, 80, 24)
    frame[:12] = stripes(12, 80, 24, shift=12)  # the neighbour above is out of phase
    tile = Borders.framed((56, 56), 12)
    framed = structure_ratios(exemplar, frame, tile, reach=8)
    whole = structure_ratios(exemplar, frame, Borders(tile.rows, tile.cols), reach=8)
    assert whole[0] > 1.3  # the line itself is broken ...
    assert framed[0] < whole[0]  # ... and the tile's own side sees only half a patch of it


def test_nearest_patch_distances_are_never_below_and_mostly_equal_a_brute_force_search():
    rng = np.random.default_rng(4)
    sample = rng.random((40, 36, 2)).astype(np.float32)
    sample = (sample + np.roll(sample, 1, 0) + np.roll(sample, 1, 1)) / 3  # some structure
    image = np.concatenate([sample[5:25, 3:30], rng.random((12, 27, 2)).astype(np.float32)])
    exemplar = PatchExemplar(sample, patch=8)
    got, _, _ = exemplar.distance_map(image, wrap=False, stride=1)
    patches = sliding_window_view(sample, (8, 8), axis=(0, 1)).reshape(-1, 2 * 64)
    queries = sliding_window_view(image, (8, 8), axis=(0, 1)).reshape(-1, 2 * 64)
    truth = np.sqrt(((queries[:, None] - patches[None]) ** 2).mean(-1).min(1))
    got = got.ravel()
    assert np.all(got >= truth - 1e-5)
    assert np.allclose(got[: 13 * 20], 0, atol=1e-5)  # copied patches lie at 0, found exactly
    # noise has no principal components: there the candidates are near misses, a few % off
    excess = got[-12 * 20 :] / truth[-12 * 20 :] - 1
    assert np.median(excess) < 0.05 and excess.max() < 0.4, (np.median(excess), excess.max())



@pytest.mark.parametrize("layout", [(0, 0, 0), (0, 1, 1, 0)])
def test_channels_held_alike_are_searched_once_at_the_same_distances(layout):
    """A grey sample's repeated channels are searched as one, scaled by sqrt(count): the
    re-ranking's distances are those over every channel, for query channels unlike each
    other too, and the PCA spans the same patches' space as over every channel."""
    from scipy.linalg import eigh

    from tasks.quilt_kernels import nearest_ssd
    from tasks.seams import channel_groups

    rng = np.random.default_rng(12)
    planes = rng.random((max(layout) + 1, 37, 33)).astype(np.float32)
    planes = (planes + np.roll(planes, 1, 1)) / 2
    sample = np.stack([planes[k] for k in layout], axis=-1)
    assert channel_groups(sample).tolist() == list(layout)
    exemplar = PatchExemplar(sample, patch=6, dims=5)
    assert exemplar._searched.shape[-1] == max(layout) + 1
    for queries in (rng.random((40, 6, 6, len(layout))).astype(np.float32),  # unlike
                    np.repeat(rng.random((40, 6, 6, 1)), len(layout), -1).astype(np.float32)):
        sy, sx = rng.integers(0, 32, (40, 7)), rng.integers(0, 28, (40, 7))
        np.testing.assert_allclose(exemplar._nearest_ssd(queries, sy, sx),
                                   nearest_ssd(sample, queries, sy, sx), rtol=2e-5, atol=1e-6)
    # the basis: the leading eigenvectors over every channel, up to sign and rounding
    flat = sliding_window_view(sample, (6, 6), axis=(0, 1))[::1, ::1].reshape(-1, 36 * len(
        layout)).astype(np.float64)
    flat -= flat.mean(axis=0)
    _, full = eigh(flat.T @ flat)
    full = full[:, ::-1][:, :5]
    np.testing.assert_allclose(np.abs(np.sum(full * exemplar.basis, axis=0)), 1, atol=1e-3)
    assert np.allclose(exemplar.basis.T @ exemplar.basis, np.eye(5), atol=1e-5)

def test_a_judged_part_needs_an_inside():
    exemplar = PatchExemplar(stripes(32, 32, 8))
    with pytest.raises(ValueError, match="nothing to compare"):
        structure_ratios(exemplar, stripes(20, 20, 8), Borders((10,), (10,)), reach=12)


@pytest.mark.slow
def test_the_search_benchmark_finds_no_patch_nearer_than_the_exact_search():
    from benchmarks.seams import SEARCHES, search_accuracy, search_report

    result = search_accuracy("gravel", checks=2, seeds=range(1))
    rows = result["rows"]
    assert [r["search"] for r in rows] == list(SEARCHES)
    for r in rows:
        assert r["checks"] == 2
        # every search returns the distance of a real patch: never below the exact nearest
        assert r["excess_mean"] >= 0 and r["excess_p99"] >= 0, r
        assert 0 <= r["worst_error_mean"] <= r["worst_error_max"] < 0.3, r
    assert len(search_report([result])) == 2 + len(SEARCHES)


def test_a_sparse_inside_is_the_inside_measured_on_every_other_patch_and_sides_in_full():
    """``sparse_inside=2`` (a tile's check): the inside's mean over the grid's even rows and
    columns only, every patch beside a line still measured, fewer patches searched; an inside
    too small to thin is measured whole."""
    rng = np.random.default_rng(8)
    sample = rng.random((64, 64, 2)).astype(np.float32)
    sample = (sample + np.roll(sample, 1, 0) + np.roll(sample, 1, 1)) / 3
    image = np.tile(sample, (4, 4, 1))[:250, :244]
    image[:, 120:] = np.roll(image[:, 120:], 5, axis=0)  # a break along column 120
    image += 0.05 * rng.random(image.shape).astype(np.float32)
    exemplar = PatchExemplar(sample)
    borders, reach = Borders.framed((210, 204), 20), 8.0
    searched = []
    distances = exemplar.distances
    exemplar.distances = lambda q: searched.append(len(q)) or distances(q)

    d, cy, cx = exemplar.distance_map(image, wrap=False, within=borders.within(image.shape[:2]))
    full = sum(searched)
    near_y = np.any([np.abs(cy - line) <= reach for line in borders.rows], axis=0)
    near_x = np.any([np.abs(cx - line) <= reach for line in borders.cols], axis=0)
    inside = ~near_y[:, None] & ~near_x[None, :]
    thinned = np.zeros_like(inside)
    thinned[::2, ::2] = True
    assert np.count_nonzero(inside & thinned) >= 400  # enough to thin
    scale = d[inside & thinned].mean()
    expected = [max(max(side.mean(), exemplar.floor) for side in
                    line_sides(d, cy, cx, kind, line, image.shape[:2], wrap=False, reach=reach))
                / scale for kind, line in borders.lines()]
    searched.clear()
    got = structure_ratios(exemplar, image, borders, reach=reach, sparse_inside=2)
    assert got == pytest.approx(expected, rel=1e-6)
    assert sum(searched) < 0.45 * full  # 1,796 of 4,899 here: the sides and a quarter
    whole = structure_ratios(exemplar, image, borders, reach=reach)
    assert whole != got and whole == pytest.approx(got, rel=0.05)

    small = Borders.framed((60, 60), 20)  # an inside of a few dozen patches
    assert (structure_ratios(exemplar, image[:100, :100], small, reach=reach, sparse_inside=2)
            == structure_ratios(exemplar, image[:100, :100], small, reach=reach))
