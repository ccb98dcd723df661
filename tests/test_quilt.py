"""Quilting (paper 003): seamless tile sets, prescriptions, and rendering them."""

from __future__ import annotations

import functools
import itertools
import re
import sys

import numpy as np
import pytest
import zarr
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from helpers import SLOW_PROCESSES, generate_store, quilt
from pipeline.graphs.prescriptions import PAIR, light_blocks
from pipeline.graphs.surface import lazy_layer
from pipeline.stores import open_store
from pipeline.stores.base import RADIANCE
from pipeline.stores.radiance import open_radiance
from tasks import prescription
from tasks.canvas import TERMS, Canvas
from tasks.corner_tiles import INTERIOR_ATTEMPTS, BorderCheck, SeamError, plan_tiles
from tasks.prescription import COMPILED_VALUES, check, compiled_pays, to_csr
from tasks.quilt_layout import overlap_for
from tasks.quilting import CandidateSearch, QuiltParams, boundary_cut
from tasks.seams import PatchExemplar
from tasks.svd import reconstruct_layers
from tasks.transform import Transform

PARAMS = ("--block", "16", "--overlap", "4", "--candidates", "4")
# the invariants of a plan hold for any plan: no planning again for the border bound
ANY_SEAM = {"max_seam": 1e9}


def _quilt(src, out, *args):
    return quilt(src, out, *PARAMS, *args)


def _exemplar(reference: np.ndarray, params: QuiltParams) -> PatchExemplar:
    """The border check's patches of ``reference`` for ``params``' block, as plan_tiles makes
    them: made once for several plans on one reference (their PCA basis and k-d tree are a
    good part of a small plan's time, and they do not depend on the plan)."""
    return PatchExemplar(np.asarray(reference, np.float32), patch=BorderCheck.patch(params))


@pytest.fixture(scope="module")
def noise() -> tuple[np.ndarray, PatchExemplar]:
    """A 50 x 54 noise reference and its border check's patches for blocks of 12."""
    reference = np.random.default_rng(5).random((50, 54, 3))
    return reference, _exemplar(reference, QuiltParams(12, 3, 3, 1, (18, 18)))


def neighbour_difference(img: np.ndarray, axis: int) -> float:
    """Mean absolute difference between neighbouring pixels along an axis."""
    return float(np.mean(np.abs(np.diff(img, axis=axis))))


def seam_difference(a: np.ndarray, b: np.ndarray, axis: int) -> float:
    """Mean absolute difference across the seam where ``b`` follows ``a`` along ``axis``."""
    last = np.take(a, -1, axis=axis)
    first = np.take(b, 0, axis=axis)
    return float(np.mean(np.abs(first - last)))


TOLERANCE = 1.6  # seams may be this much rougher than the sample's own neighbour differences


def _layer_images(sample, light):
    return open_radiance(sample)[RADIANCE].values[0, light]


def _naive_copy(img, block, size, seed=0):
    """A tile of random blocks of the sample, copied without overlap or cut."""
    rng = np.random.default_rng(seed)
    out = np.empty((size, size, img.shape[-1]), img.dtype)
    for y in range(0, size, block):
        for x in range(0, size, block):
            sy, sx = rng.integers(0, img.shape[0] - block, 2)
            out[y : y + block, x : x + block] = img[sy : sy + block, sx : sx + block]
    return out


@pytest.mark.parametrize("shape", [(37, 45), (40, 36), (8, 9)])
def test_the_fft_candidate_search_equals_the_masked_ssd_at_every_position(shape):
    """The transforms are circular, of the sample's size rounded up to a fast length (40 and
    36 are such lengths themselves): only positions past the last window may wrap."""
    rng = np.random.default_rng(4)
    h, w = shape
    sample = rng.random((h, w, 3))
    target = rng.random((8, 8, 3))
    mask = rng.random((8, 8)) > 0.4
    search = CandidateSearch(sample, 8)
    if shape != (37, 45):  # no padding at all: a wrong offset would wrap into valid errors
        assert search.shape == shape
    errors = search.errors(target, mask)
    brute = np.array([[np.sum(mask[..., None] * (sample[y : y + 8, x : x + 8] - target) ** 2)
                       for x in range(w - 7)] for y in range(h - 7)])
    assert errors.shape == brute.shape
    # float32 transforms: off by a few 1e-7 of the terms' size (here up to about 60)
    np.testing.assert_allclose(errors, brute, rtol=0, atol=1e-5 * brute.max())


@pytest.mark.parametrize("layout", [(0, 0, 0), (0, 1, 0, 0), (0, 1, 2, 1)])
def test_channels_held_alike_share_a_term_and_still_give_the_masked_ssd(layout):
    """A grey photo's reference repeats one channel: such channels share one transform,
    and the error image is still the masked SSD over every channel, for targets whose
    channels differ too (the group's target channels are summed, not assumed alike)."""
    rng = np.random.default_rng(7)
    h, w, b = 31, 26, 6
    planes = rng.random((max(layout) + 1, h, w)).astype(np.float32)
    sample = np.stack([planes[k] for k in layout], axis=-1)
    search = CandidateSearch(sample, b)
    assert search.group.tolist() == list(layout)
    assert len(search.spectra) == 2 + max(layout)
    for target in (rng.random((b, b, len(layout))),  # channels unlike the sample's
                   np.repeat(rng.random((b, b, 1)), len(layout), axis=-1)):  # or alike
        mask = rng.random((b, b)) > 0.3
        brute = np.array([[np.sum(mask[..., None] * (sample[y : y + b, x : x + b] - target)
                                  ** 2) for x in range(w - b + 1)] for y in range(h - b + 1)])
        np.testing.assert_allclose(search.errors(target, mask), brute, rtol=0,
                                   atol=1e-5 * brute.max())
    # the last channel changed by one step at one texel leaves its group
    near = sample.copy()
    near[3, 4, -1] = np.nextafter(near[3, 4, -1], np.float32(2))
    assert len(set(CandidateSearch(near, b).group.tolist())) == len(set(layout)) + (
        layout.count(layout[-1]) > 1)


def _errors_afresh(search: CandidateSearch, target: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The error image as the search computed it before it kept masks' spectra."""
    import scipy

    from tasks.quilt_kernels import clipped_errors, search_kernels

    kernels, norm = search_kernels(target, mask, search.group, len(search.spectra) - 1)
    rows = scipy.fft.rfft(kernels, n=search.shape[1], axis=-1)
    spectrum = scipy.fft.fft(rows, n=search.shape[0], axis=-2)
    spectrum *= search.spectra
    full = scipy.fft.irfft2(spectrum.sum(axis=0), search.shape)
    return clipped_errors(full, search.block - 1, *search.valid, norm)


def test_the_search_keeps_each_masks_spectrum_without_changing_a_bit():
    """The first term's spectrum is kept per mask: error images from a kept one and from a
    new one are those of all terms transformed together, bit for bit; beyond the kept number
    of masks the oldest go."""
    rng = np.random.default_rng(11)
    for shape, channels, b in (((41, 39), 3, 10), ((33, 50), 1, 7)):
        sample = rng.random((*shape, channels)).astype(np.float32)
        masks = []
        for n in range(CandidateSearch.MASKS_KEPT):  # L-shaped bands, as a fill's masks are
            mask = np.zeros((b, b), bool)
            mask[: n % 4], mask[:, : n // 4] = True, True
            masks.append(mask)
        search = CandidateSearch(sample, b)
        kept = None
        for _ in range(3):  # the first round computes each mask's term, then it is kept
            for mask in masks:
                target = rng.random((b, b, channels)).astype(np.float32)
                np.testing.assert_array_equal(search.errors(target, mask),
                                              _errors_afresh(search, target, mask))
            assert list(search._masks) == [(m.shape, m.dtype.str, m.tobytes()) for m in masks]
            kept = kept or dict(search._masks)
            assert all(search._masks[k] is v for k, v in kept.items())  # not computed again
        other = rng.random((b, b)) > 0.5  # one more: the oldest goes
        search.errors(rng.random((b, b, channels)).astype(np.float32), other)
        assert len(search._masks) == CandidateSearch.MASKS_KEPT
        assert next(iter(search._masks))[2] == masks[1].tobytes()


def test_the_boundary_cut_follows_the_cheapest_loop_around_the_kept_square():
    b = 12
    error = np.full((b, b), 10.0)
    error[2, 2:10] = error[9, 2:10] = error[2:10, 2] = error[2:10, 9] = 0.0  # a cheap ring
    keep = np.zeros((b, b), bool)
    keep[4:8, 4:8] = True
    region = boundary_cut(error, keep, outside_free=np.zeros((b + 2, b + 2), bool))
    expected = np.zeros((b, b), bool)
    expected[2:10, 2:10] = True
    np.testing.assert_array_equal(region, expected)


def test_the_cut_never_runs_along_a_window_edge_beside_filled_canvas():
    b = 12
    error = np.full((b, b), 10.0)
    error[0, :] = error[-1, :] = error[:, 0] = error[:, -1] = 0.0  # cheapest: the outermost ring
    keep = np.zeros((b, b), bool)
    keep[4:8, 4:8] = True
    region = boundary_cut(error, keep, outside_free=np.zeros((b + 2, b + 2), bool))
    assert region[4:8, 4:8].all()
    assert not (region[0].any() or region[-1].any() or region[:, 0].any()
                or region[:, -1].any())
    # next to free positions (empty or off the canvas) the edge may be taken, and is
    free = np.ones((b + 2, b + 2), bool)
    free[1:-1, 1:-1] = False
    assert boundary_cut(error, keep, outside_free=free).all()


@pytest.mark.parametrize("steps", [2, 3])
def test_a_tiles_border_bands_are_exactly_its_edge_strips(noise, steps):
    # The bands no interior patch reaches (B/2 - O wide) hold the edge strips as planned, in
    # every row and column: the corner quadrants re-blend the vertical strip's patches over
    # the horizontal strip only where the horizontal strip is the corner patch alone.
    block, overlap = 12, 3
    half, band, step = block // 2, block // 2 - overlap, block - overlap
    size = step * steps
    reference, exemplar = noise
    plan = plan_tiles(reference, QuiltParams(block, overlap, 3, 2, (size, size), **ANY_SEAM),
                      seed=2, exemplar=exemplar)
    for tile, (tl, tr, bl, br) in zip(plan.tiles, plan.corners, strict=True):
        pieces = [
            (np.s_[:band, :], plan.strips[("horizontal", tl, tr)], np.s_[half : half + band,
                                                                         half : half + size]),
            (np.s_[-band:, :], plan.strips[("horizontal", bl, br)], np.s_[half - band : half,
                                                                          half : half + size]),
            (np.s_[:, :band], plan.strips[("vertical", tl, bl)], np.s_[half : half + size,
                                                                       half : half + band]),
            (np.s_[:, -band:], plan.strips[("vertical", tr, br)], np.s_[half : half + size,
                                                                        half - band : half]),
        ]
        for where, strip, there in pieces:
            assert np.array_equal(tile.index[where], strip.index[there])
            assert np.array_equal(tile.weight[where], strip.weight[there])


@pytest.mark.parametrize("material", ["fabric", *(pytest.param(m, marks=pytest.mark.slow)
                                                  for m in ("stone", "tiles"))])
def test_a_quilted_texture_wraps_seamlessly_in_every_layer(tmp_path, btf, samples, material):
    # Pooled over seeds, layers and both wraps: one 48-pixel wrap line may run along an edge of
    # the sample itself (seen with stone, seed 0: adjacent sample pixels across a shadow edge).
    sample = samples[material]
    images = open_radiance(sample)[RADIANCE].values[0]
    refs = [(neighbour_difference(img, 0), neighbour_difference(img, 1)) for img in images]
    rough = []
    for seed in range(4):
        group = _quilt(sample, tmp_path / f"q{seed}.zarr", "--size", "48,48",
                       "--seed", str(seed))
        tiles = group[RADIANCE][0, 0]
        for t, (ref_v, ref_h) in zip(tiles, refs, strict=True):
            rough += [seam_difference(t, t, 0) / ref_v, seam_difference(t, t, 1) / ref_h]
    assert np.mean(rough) < TOLERANCE, rough
    # the tolerance is not loose: plain copies of random blocks fail it
    assert np.mean(_naive_seams(images, refs)) > TOLERANCE


def _naive_seams(images, refs) -> list[float]:
    """Seam roughness of plain copies of random 16-pixel blocks, per layer and seam."""
    naive = []
    for light, (img, (ref_v, ref_h)) in enumerate(zip(images, refs, strict=True)):
        copy = _naive_copy(img, 16, 48, seed=light)
        naive += [seam_difference(copy[:k], copy[k:], 0) / ref_v for k in (16, 32)]
        naive += [seam_difference(copy[:, :k], copy[:, k:], 1) / ref_h for k in (16, 32)]
    return naive


def test_corner_compatible_tiles_meet_seamlessly_in_every_2x2_arrangement(tmp_path, btf,
                                                                          samples):
    sample = samples["stone"]
    group = _quilt(sample, tmp_path / "q.zarr", "--corners", "2", "--size", "36,36")
    tiles = group[RADIANCE][:, 0]  # (tile, light, y, x, channel)
    corners = group["corners"][:]
    assert len(tiles) == 16 and sorted(map(tuple, corners)) == sorted(
        itertools.product(range(2), repeat=4))
    images = open_radiance(sample)[RADIANCE].values[0]
    refs = [(neighbour_difference(img, 0), neighbour_difference(img, 1)) for img in images]
    lookup = {tuple(c): i for i, c in enumerate(corners)}
    rough = []
    for v in itertools.product(range(2), repeat=9):  # the 9 vertices of a 2 x 2 arrangement
        g = np.array(v).reshape(3, 3)
        (a, b), (c, d) = [[tiles[lookup[(g[i, j], g[i, j + 1], g[i + 1, j], g[i + 1, j + 1])]]
                           for j in range(2)] for i in range(2)]
        for light, (ref_v, ref_h) in enumerate(refs):
            rough += [seam_difference(a[light], b[light], 1) / ref_h,
                      seam_difference(c[light], d[light], 1) / ref_h,
                      seam_difference(a[light], c[light], 0) / ref_v,
                      seam_difference(b[light], d[light], 0) / ref_v]
    assert np.mean(rough) < TOLERANCE
    assert np.mean(_naive_seams(images, refs)) > TOLERANCE
    # tiles whose edges have the same corner types share that edge's band exactly (the part of
    # the edge strip that no interior patch reaches: half a block minus the overlap)
    band = 16 // 2 - 4
    sides = {"left": ((0, 2), np.s_[:, :, :band]), "right": ((1, 3), np.s_[:, :, -band:]),
             "top": ((0, 1), np.s_[:, :band]), "bottom": ((2, 3), np.s_[:, -band:])}
    for (ends, where) in sides.values():
        for types in itertools.product(range(2), repeat=2):
            same = [t[where] for t, k in zip(tiles, corners, strict=True)
                    if tuple(k[list(ends)]) == types]
            assert len(same) == 4 and all(np.array_equal(same[0], t) for t in same[1:])


def _tile_mosaic(plan, types: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Prescription terms of the tiles laid on a grid of corner types (vertex types)."""
    lookup = {tuple(c): i for i, c in enumerate(plan.corners)}
    rows = [[plan.tiles[lookup[(types[i, j], types[i, j + 1], types[i + 1, j],
                                types[i + 1, j + 1])]]
             for j in range(types.shape[1] - 1)] for i in range(types.shape[0] - 1)]
    def join(name):
        return np.concatenate([np.concatenate([getattr(t, name) for t in row], axis=1)
                               for row in rows], axis=0)

    return join("index"), join("weight")


def _hard_seams(index, weight, sample_width, *, wrap):
    """4-neighbour output pairs, both one sample pixel, whose sources are not neighbours too."""
    top = np.argmax(weight, axis=-1)[..., None]
    single = np.take_along_axis(weight, top, -1)[..., 0] > 0.99
    sy, sx = np.divmod(np.take_along_axis(index, top, -1)[..., 0], sample_width)
    bad = total = 0
    for axis, step in ((0, (1, 0)), (1, (0, 1))):
        if wrap:
            here, there = np.s_[:, :], np.s_[:, :]
            nxt = [np.roll(a, -1, axis) for a in (sy, sx, single)]
        else:
            here = np.s_[:-1, :] if axis == 0 else np.s_[:, :-1]
            there = np.s_[1:, :] if axis == 0 else np.s_[:, 1:]
            nxt = [a[there] for a in (sy, sx, single)]
        both = single[here] & nxt[2]
        neighbours = (nxt[0] - sy[here] == step[0]) & (nxt[1] - sx[here] == step[1])
        bad += int(np.sum(both & ~neighbours))
        total += int(np.sum(both))
    return bad, total


@pytest.mark.parametrize("smooth", [False, True])
@pytest.mark.parametrize("block,overlap,steps", [(12, 3, 2), (16, 4, 3)])
def test_no_two_neighbouring_output_pixels_join_two_patches_without_a_blend(smooth, block,
                                                                          overlap, steps):
    # Every seam between two patches must be blended: an output pixel taken from one sample
    # pixel alone, next to another such pixel, must be the sample's neighbour in that direction
    # (across the wrap of a periodic tile and across the borders of corner-compatible tiles).
    rng = np.random.default_rng(3)
    reference = rng.random((60, 64, 3))
    if smooth:  # cheap errors everywhere: the cut is free to wander
        reference = ndimage.gaussian_filter(reference, (3, 3, 0))
    step = block - overlap
    single = QuiltParams(block, overlap, 4, 1, (step * steps,) * 2, **ANY_SEAM)
    exemplar = _exemplar(reference, single)  # the same structure patches for every plan
    for seed in range(3):
        one = plan_tiles(reference, single, seed=seed, exemplar=exemplar).tiles[0]
        bad, total = _hard_seams(one.index, one.weight, 64, wrap=True)
        assert total > 0 and bad == 0, (seed, bad, total)
        two = plan_tiles(reference, QuiltParams(block, overlap, 4, 2, (step * steps,) * 2,
                                                **ANY_SEAM), seed=seed, exemplar=exemplar)
        types = np.random.default_rng(seed).integers(0, 2, (4, 4))
        bad, total = _hard_seams(*_tile_mosaic(two, types), 64, wrap=False)
        assert total > 0 and bad == 0, (seed, bad, total)


def test_every_layer_is_the_prescription_applied_to_the_sample(tmp_path, btf, samples,
                                                              monkeypatch):
    # three layers at a time: the kernel's two-layer pass and its one-layer tail
    monkeypatch.setattr("pipeline.graphs.prescriptions.APPLY_BUDGET",
                        3 * 4 * 3 * (72 * 72 + 24 * 24))
    sample = samples["fabric"]
    group = _quilt(sample, tmp_path / "q.zarr", "--corners", "2", "--size", "24,24")
    layers = open_radiance(sample)[RADIANCE].values
    n = layers.shape[2] * layers.shape[3]
    for t in (0, 5, 15):
        matrix = to_csr(group["prescription_index"][t], group["prescription_weight"][t], n)
        for light in range(layers.shape[1]):
            expected = (matrix @ layers[0, light].reshape(n, -1)).reshape(24, 24, -1)
            assert np.array_equal(group[RADIANCE][t, 0, light], expected)


@given(views=st.integers(1, 3), lights=st.integers(1, 70), chunk=st.integers(1, 20),
       tasks=st.integers(1, 40))
@settings(max_examples=200, deadline=None)
def test_application_tasks_take_every_light_once_within_its_stored_block(views, lights, chunk,
                                                                         tasks):
    blocks = light_blocks(views, lights, chunk, tasks=tasks)
    for view in range(views):
        mine = sorted((l0, l1) for v, l0, l1 in blocks if v == view)
        assert [i for l0, l1 in mine for i in range(l0, l1)] == list(range(lights))
        # a part never spans two stored blocks (each is read whole), and only a stored
        # block's last part may be shorter than a pair
        assert all(l0 // chunk == (l1 - 1) // chunk for l0, l1 in mine)
        assert all(l1 - l0 >= PAIR or l1 == min(lights, (l0 // chunk + 1) * chunk)
                   for l0, l1 in mine)
    stored = views * -(-lights // chunk)
    if stored >= tasks:
        assert len(blocks) == stored  # enough tasks: the stored blocks, unsplit
    else:
        most = views * sum(-(-min(chunk, lights - l0) // PAIR) for l0 in range(0, lights, chunk))
        assert len(blocks) >= min(tasks, most) // 2  # halving overshoots by at most twice


def test_application_tasks_keep_only_the_lights_a_scene_needs():
    class Needs:
        def keeps(self, view, lights):
            return view == 1 and 21 in lights

    assert light_blocks(2, 48, 16, tasks=8, needs=Needs()) == [(1, 20, 22)]


def test_numba_is_loaded_for_prescriptions_only_where_the_work_pays_for_it(monkeypatch):
    monkeypatch.setattr("platform.machine", lambda: "x86_64")
    monkeypatch.delitem(sys.modules, "numba", raising=False)
    assert not compiled_pays(COMPILED_VALUES - 1) and compiled_pays(COMPILED_VALUES)
    monkeypatch.setattr("platform.machine", lambda: "aarch64")  # scipy's loop may fuse there
    assert compiled_pays(1)
    monkeypatch.setattr("platform.machine", lambda: "x86_64")
    monkeypatch.setitem(sys.modules, "numba", object())  # loaded already: nothing to pay
    assert compiled_pays(1)


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("channels", [1, 3, 4])
def test_apply_equals_scipys_sparse_product_bit_for_bit(channels, compiled):
    # numba's loop and scipy's own (chosen by the work, compiled_pays) give the same bits
    apply = functools.partial(prescription.apply, compiled=compiled)
    rng = np.random.default_rng(channels)
    sample, output = (9, 7), (8, 9)  # 72 output texels: more than the kernel prefetches ahead
    index = rng.integers(-1, 63, (72, TERMS))  # -1: unused terms
    index[5] = -1  # a row with no terms gives 0
    weight = np.where(index >= 0, rng.random(index.shape), 0).astype(np.float32)
    matrix = to_csr(index, weight, 63)
    layers = rng.standard_normal((3, 3, *sample, channels)).astype(np.float32)  # 9: odd
    out = np.full((3, 3, *output, channels), np.nan, np.float32)
    assert apply(matrix, layers, output=output, out=out) is out
    for v, light in itertools.product(range(3), range(3)):
        expected = matrix @ layers[v, light].reshape(63, channels)
        assert np.array_equal(out[v, light].reshape(72, channels), expected)
    assert np.array_equal(apply(matrix, layers[:1, :1], output=output), out[:1, :1])
    # the same matrix made without scipy, as the pipeline's tasks take it: the same bits
    assert np.array_equal(apply(prescription.rows(index, weight, 63), layers, output=output),
                          out)
    with pytest.raises(ValueError, match="cannot take"):
        apply(matrix, layers, output=(6, 6))
    with pytest.raises(ValueError, match="C-contiguous float32"):
        apply(matrix, layers, output=output, out=out[:, :, ::-1])
    memory = np.zeros(out.size, np.float32)  # layers and out in the same memory
    inside = memory[: layers.size].reshape(layers.shape)
    inside[...] = layers
    with pytest.raises(ValueError, match="must not overlap"):
        apply(matrix, inside, output=output, out=memory.reshape(out.shape))


def test_rows_are_the_padded_prescription_with_every_term_kept_in_order():
    rng = np.random.default_rng(7)
    index = rng.integers(-1, 5, (40, TERMS))  # 5 sample texels: many named twice in a row
    index[3] = -1
    weight = np.where(index >= 0, rng.random(index.shape), 0).astype(np.float32)
    matrix = prescription.rows(index, weight, 5)
    assert matrix.shape == (40, 5) and matrix.indptr.dtype == matrix.indices.dtype == np.int32
    assert matrix.data.dtype == np.float32
    dense = np.zeros((40, 5))
    for r, k in itertools.product(range(40), range(TERMS)):
        if index[r, k] >= 0:
            dense[r, index[r, k]] += weight[r, k]
    assert np.allclose(to_csr(index, weight, 5).toarray(), dense, rtol=1e-6, atol=0)
    for r in range(40):  # each row's used terms, in their stored order
        terms = slice(matrix.indptr[r], matrix.indptr[r + 1])
        assert np.array_equal(matrix.indices[terms], index[r][index[r] >= 0])
        assert np.array_equal(matrix.data[terms], weight[r][index[r] >= 0])
    assert np.diff(matrix.indptr)[3] == 0


@settings(max_examples=12, deadline=None)
@given(st.sampled_from([(8, 2), (12, 3), (16, 4)]), st.integers(1, 2), st.integers(0, 50),
       st.integers(2, 3))
def test_prescription_rows_sum_to_one_and_index_valid_sample_pixels(block_overlap, corners,
                                                                   seed, steps):
    block, overlap = block_overlap
    step = block - overlap
    rng = np.random.default_rng(seed)
    reference = rng.random((block + 2 + seed % 7, block + 5, 3)).astype(np.float32)
    plan = plan_tiles(reference, QuiltParams(block, overlap, 3, corners, (step * steps,) * 2,
                                             **ANY_SEAM), seed=seed)
    samples = reference.shape[0] * reference.shape[1]
    for tile in plan.tiles:
        assert check(tile.index.reshape(-1, TERMS), tile.weight.reshape(-1, TERMS),
                     samples) == []
        matrix = to_csr(tile.index.reshape(-1, TERMS), tile.weight.reshape(-1, TERMS), samples)
        assert np.allclose(matrix @ reference.reshape(samples, 3),
                           tile.value.reshape(-1, 3), atol=1e-4)


# processes (a fresh interpreter per worker, seconds each) in the slow set, as quilting on a
# cluster's worker processes (tests/test_s3.py, the cluster config: the bits of a synchronous
# run)
@pytest.mark.parametrize("scheduler", ["synchronous", SLOW_PROCESSES])
def test_the_same_seed_gives_the_same_tile_set_and_another_seed_another(tmp_path, btf,
                                                                       samples, scheduler):
    sample = samples["stone"]
    a = _quilt(sample, tmp_path / "a.zarr", "--seed", "4", "--size", "36,36")
    b = _quilt(sample, tmp_path / "b.zarr", "--seed", "4", "--size", "36,36",
               "--scheduler", scheduler)
    c = _quilt(sample, tmp_path / "c.zarr", "--seed", "5", "--size", "36,36")
    assert np.array_equal(a[RADIANCE][:], b[RADIANCE][:])
    assert np.array_equal(a["prescription_index"][:], b["prescription_index"][:])
    assert not np.array_equal(a[RADIANCE][:], c[RADIANCE][:])


def test_quilting_a_compressed_store_gives_a_compressed_tile_set(tmp_path, btf, samples):
    # rank 8: every tile below is within about 2% of the measured layer (rank 6: 5%)
    assert btf("compress", samples["stone"], tmp_path / "c.zarr", "--rank", "8",
               "--quiet").code == 0
    group = _quilt(tmp_path / "c.zarr", tmp_path / "q.zarr", "--size", "24,24",
                   "--corners", "2", "--workers", "3")
    assert group.attrs["btf_kind"] == "compressed-tileset"
    v = zarr.open_array(tmp_path / "c.zarr", path="V")
    assert v.chunks[0] < v.shape[0]  # several bands
    v = v[:]
    n = v.shape[0] * v.shape[1]
    # the store holds the prescriptions and the sample's eigentextures, not 16 tiles' worth
    assert group["V"].shape == v.shape and np.array_equal(group["V"][:], v)
    tileset = open_store(tmp_path / "q.zarr")
    tiles = tileset.tile_eigentextures(range(16))
    assert tiles.shape == (16, 24, 24, v.shape[-1])
    for t in range(16):
        matrix = to_csr(group["prescription_index"][t], group["prescription_weight"][t], n)
        assert np.allclose(tiles[t], (matrix @ v.reshape(n, -1)).reshape(24, 24, -1),
                           atol=1e-6)
    # Each tile, rebuilt, is the sample's layer as the compressed store rebuilds it, moved by
    # the prescription: exactly where a texel has one source, and between its sources where
    # patches blend (in the log domain: a weighted geometric mean). That layer is the measured
    # one up to the rank-8 compression error.
    eps = group.attrs["transform"]["eps"]
    rebuilt = reconstruct_layers(group["U"][0, 2], group["S"][:], v,
                                 transform=Transform("log", eps)).reshape(n, -1)
    layer = zarr.open_array(samples["stone"], path=RADIANCE)[0, 2]
    assert np.abs(rebuilt.reshape(layer.shape) - layer).mean() < 0.05 * layer.mean()
    for t in range(16):
        index, weight = group["prescription_index"][t], group["prescription_weight"][t]
        tile = reconstruct_layers(group["U"][0, 2], group["S"][:], tiles[t],
                                  transform=Transform("log", eps)).reshape(-1, 3)
        # the layer formed on the sample, then prescribed: the same radiance
        assert np.allclose(tileset.tile_layers([t], group["U"][0, 2][None])[0, :, :, 0]
                           .reshape(-1, 3), tile, rtol=1e-4, atol=1e-6), t
        single = (weight > 0).sum(axis=1) == 1
        # The tile's prescription P_t applied to the measured layer itself (not to its rank-8
        # rebuild) gives the tile up to the compression error: P_t @ layer where a texel has
        # one source, and P_t applied in the log domain (where compressed tile sets blend,
        # a geometric rather than arithmetic mean) for the whole tile.
        matrix = to_csr(index, weight, n)
        direct = matrix @ layer.reshape(n, -1)
        assert (np.abs(tile[single] - direct[single]).mean()
                < 0.05 * np.abs(direct[single]).mean()), t
        blended = np.exp(matrix @ np.log(layer.reshape(n, -1) + eps)) - eps
        assert np.abs(tile - blended).mean() < 0.05 * np.abs(blended).mean(), t
        first = index[np.arange(len(index)), np.argmax(weight, axis=1)]
        assert single.mean() > 0.25  # small tiles: much of them is blend bands
        assert np.allclose(tile[single], rebuilt[first[single]], rtol=1e-4, atol=1e-6), t
        sources = np.where((weight > 0)[..., None], rebuilt[np.maximum(index, 0)], np.nan)
        assert np.all(tile[~single] >= np.nanmin(sources[~single], axis=1) - 1e-5), t
        assert np.all(tile[~single] <= np.nanmax(sources[~single], axis=1) + 1e-5), t
    surface = lazy_layer(tmp_path / "q.zarr", view=0, light=2, size=(50, 60)).compute()
    assert surface.shape == (50, 60, 3) and np.isfinite(surface).all() and surface.min() >= 0


@pytest.mark.parametrize(("args", "message"), [
    (("--block", "15"), "--block: block must be an even number"),
    (("--overlap", "9"), "--overlap: overlap must be between"),
    (("--size", "50,48"), "--size: tile size (50, 48) must be a multiple of"),
    (("--weights", "1,1"), "--weights: expected three non-negative numbers"),
])
def test_bad_quilt_options_are_named(tmp_path, btf, samples, args, message):
    result = btf("quilt", samples["stone"], tmp_path / "q.zarr", *PARAMS, *args)
    assert result.code == 2 and message in result.err
    assert not (tmp_path / "q.zarr").exists()


def test_a_tile_set_too_large_to_plan_is_refused_before_planning(tmp_path, btf, samples):
    result = btf("quilt", samples["stone"], tmp_path / "q.zarr", *PARAMS, "--corners", "9",
                 "--size", "1200,1200")
    assert result.code == 1 and "6561 tiles of 1200 x 1200 texels needs about" in result.err
    assert "use fewer --corners or a smaller --size" in result.err
    assert not (tmp_path / "q.zarr").exists()


def test_the_block_size_follows_the_detected_period():
    from benchmarks.lattices import random_lattice_texture, stochastic_texture
    from tasks.quilt_layout import choose_block

    rng = np.random.default_rng(5)
    for _ in range(6):
        case = random_lattice_texture(rng, motif="blobs", noise=0.05, low=14, high=60)
        block, overlap, why = choose_block(case.image)
        period = max(np.hypot(*case.u), np.hypot(*case.v))
        assert block == pytest.approx(max(16, period), abs=2.5), (case.describe(), block, why)
        assert block % 2 == 0 and 2 <= overlap < block // 2 and "period" in why
    block, overlap, why = choose_block(stochastic_texture(rng, "fbm"))
    assert (block, overlap) == (32, 8) and "no clear lattice" in why


def test_a_sample_without_a_clear_lattice_is_searched_for_one_once(monkeypatch):
    """The quilt stage asks for the lattice, and choose_block again for its confidence: one
    detection per sample; a sample differing in one texel is detected afresh."""
    import tasks.periodicity
    import tasks.quilt_layout
    from benchmarks.lattices import stochastic_texture
    from tasks.quilt_layout import choose_block, sample_lattice

    tasks.quilt_layout._detected.cache_clear()
    calls = []
    detect = tasks.periodicity.detect_lattice
    monkeypatch.setattr(tasks.periodicity, "detect_lattice",
                        lambda gray: calls.append(gray.shape) or detect(gray))
    image = stochastic_texture(np.random.default_rng(8), "fbm")
    assert sample_lattice(image) is None
    block, _, why = choose_block(image, lattice=None)
    assert (block, len(calls)) == (32, 1) and "no clear lattice (confidence" in why
    changed = image.copy()
    changed[5, 7] += 1e-3
    assert sample_lattice(changed) is None and len(calls) == 2
    assert sample_lattice(image, 0.0) == detect(image) and len(calls) == 2  # kept, as found


@pytest.mark.parametrize("period", [39.8, 40.0, 38.3])
def test_a_given_tile_takes_the_even_block_nearest_the_period_whose_step_divides_it(period):
    # a period of 39.8 (reach 9) once searched odd blocks only (31-49) and fell back to the
    # default, though block 40 (step 30) divides a 60 or 90 texel tile
    from tasks.periodicity import Lattice
    from tasks.quilt_layout import choose_block

    lattice = Lattice((period, 0.0), (0.0, period), 1.0)
    for tile in ((60, 60), (90, 90), (60, 90)):
        block, overlap, why = choose_block(np.zeros((160, 160)), tile=tile, lattice=lattice)
        assert (block, overlap) == (40, 10), (tile, why)
    block, _, why = choose_block(np.zeros((160, 160)), tile=(56, 56), lattice=lattice)
    assert block % 2 == 0 and 56 % (block - overlap_for(block)) == 0, why


@pytest.fixture(scope="module")
def big_tiles(tmp_path_factory):
    """A 160 x 160 tiles sample whose lattice has a 40-texel period, for the tests that
    read it."""
    return generate_store(tmp_path_factory.mktemp("tiles") / "tiles.zarr", "--material",
                          "tiles", "--size", "160", "--scale", "40", "--sampling", "abtf:4,2",
                          "--chunk", "32")


def test_btf_quilt_without_a_block_takes_one_period_and_says_so(tmp_path, btf, big_tiles,
                                                                samples):
    result = btf("quilt", big_tiles, tmp_path / "q.zarr", "--candidates", "3")
    assert result.code == 0, result.err
    assert "block 40, overlap 10: one period of the detected lattice (" in result.err
    quilt = zarr.open_group(tmp_path / "q.zarr", mode="r").attrs["quilt"]
    assert (quilt["block"], quilt["overlap"]) == (40, 10)
    stone = samples["stone"]  # a sample without a lattice
    result = btf("quilt", stone, tmp_path / "s.zarr", "--candidates", "3")
    assert result.code == 0 and "block 32, overlap 8: no clear lattice" in result.err
    result = btf("quilt", stone, tmp_path / "bad.zarr", "--overlap", "20", "--quiet")
    assert result.code == 1 and "--overlap (with --block 32)" in result.err


def test_border_positions_match_a_direct_count():
    from tasks.quilting import border_positions

    rng = np.random.default_rng(3)
    sample = rng.random((23, 29, 2)) ** 3
    block = 8
    fit = border_positions(sample, block)
    dy = np.abs(np.diff(sample, axis=0)).mean(-1)
    dx = np.abs(np.diff(sample, axis=1)).mean(-1)
    for sy in range(23 - block + 1):
        for sx in range(29 - block + 1):
            row = dy[sy + block // 2 - 1, sx : sx + block].mean()
            col = dx[sy : sy + block, sx + block // 2 - 1].mean()
            assert fit["row"][sy, sx] == (row <= dy.mean())
            assert fit["col"][sy, sx] == (col <= dx.mean())
    assert np.array_equal(fit["both"], fit["row"] & fit["col"])
    assert 0 < fit["both"].mean() < 1


SEEDS = st.integers(0, 2**31 - 1)


def _worst_seed(texture: str, block: int | None, corners: int, seeds, refusals: int = 0
                ) -> dict:
    """The seams of ``seeds``; at most ``refusals`` of them refused, each with the message
    that says what stood out and what to try (tasks.corner_tiles.SeamError)."""
    from benchmarks.seams import texture_seams

    result = texture_seams(texture, block=block, seeds=seeds, corners=corners)
    assert len(result["failed"]) <= refusals, result["failed"]
    for _, message in result["failed"]:
        assert "its best border still stands out" in message and "try another seed" in message
    return result


BOUND_CASES = [
    ("brick", 48, 1),  # the bug report's setting
    ("brick", None, 1),
    ("brick", 48, 2),
    ("fabric", None, 1),  # a lattice with an 11.3-texel period: tiles of whole periods
]


def _check_bound(texture, block, corners, seed):
    """The bug report: one brick seed in six left a mortar line along the wrap, others a band
    where the rows of bricks break. Every border is measured on its own: seams across it and
    the structure along it (tasks/seams.py) at most 1.3x the tile's inside, measured on the
    texture (V = 1) or a mosaic of tiles (V = 2)."""
    r = _worst_seed(texture, block, corners, [seed], refusals=1 if corners > 1 else 0)
    if r["failed"]:
        return  # refused with the message (about 1 seed in 20 of brick's tile sets, see
        # BENCHMARKS.md): no output, so none out of bounds; the slow test bounds how often
    assert r["seam"]["worst"] <= 1.3 and r["structure"]["worst"] <= 1.3, r["seeds"]
    assert r["sharpness"]["worst"] >= 0.8, r["seeds"]


@pytest.mark.parametrize("texture,block,corners", [c for c in BOUND_CASES if c[2] == 1])
def test_a_seed_keeps_every_border_within_the_bound(texture, block, corners):
    """One seed per case, a date rather than a seed the planner was tuned on. Planning time
    varies by seed from seconds to a minute (issue 35), so the default set runs one seed of
    the single-corner cases (5 s each); tile sets (V = 2) and seeds the test did not pick are
    the slow set's, new seeds every run."""
    _check_bound(texture, block, corners, 20261126)


@pytest.mark.slow
@pytest.mark.parametrize("texture,block,corners", BOUND_CASES)
@settings(max_examples=1, deadline=None, derandomize=False)
@given(seed=SEEDS)
def test_every_seed_keeps_every_border_within_the_bound(texture, block, corners, seed):
    """Seeds the test did not pick, new ones every run (hypothesis)."""
    _check_bound(texture, block, corners, seed)


@pytest.mark.slow
@pytest.mark.parametrize("texture,corners,count", [
    # new seeds every run, a few per case (CI's runs add them up; `btf bench quilt
    # --seams-only` runs 20 of every one): brick is the bug report's texture
    ("brick", 1, 5),
    *[(t, 1, 3) for t in ("gravel", "grass", "moon", "lattice", "tiles")],
    ("brick", 2, 2),  # tile sets cost 3-60 s a seed
    *[(t, 2, 2) for t in ("gravel", "grass", "moon", "lattice", "tiles")],
])
def test_many_seeds_keep_every_border_within_the_bound(texture, corners, count):
    """Seeds the test did not pick (new ones every run): every output within the bound, and
    at most one refused tile set per run (brick: 1 seed in 20 in BENCHMARKS.md)."""
    seeds = np.random.default_rng().integers(0, 2**31 - 1, count).tolist()
    r = _worst_seed(texture, None, corners, seeds, refusals=1 if corners > 1 else 0)
    assert r["seam"]["worst"] <= 1.3 and r["structure"]["worst"] <= 1.3, r["seeds"]


def test_positions_in_phase_are_lattice_vectors_to_the_texel():
    # the generated tiles material repeats every 64 texels exactly: a corner patch one texel
    # off its phase (65 rows away: within the tile-size tolerance) broke every border between
    # corner types (V = 2, seed 1: structure 2.18 after 12 rounds)
    from tasks.periodicity import Lattice
    from tasks.quilt_layout import in_phase

    square = in_phase((193, 193), (87, 109), Lattice((64.0, 0.0), (0.0, 64.0), 1.0))
    ys, xs = np.nonzero(square)
    assert set(ys) == {23, 87, 151} and set(xs) == {45, 109, 173}
    oblique = Lattice((11.3, 2.1), (-3.2, 10.7), 1.0)  # a lattice off the texel grid
    found = np.argwhere(in_phase((120, 120), (60, 60), oblique)) - 60
    for point in (np.array([a, b]) @ np.array([oblique.u, oblique.v]) for a in range(-3, 4)
                  for b in range(-3, 4)):  # every lattice point has its nearest texel, only
        near = np.hypot(*(found - point).T)
        assert near.min() <= 0.5**0.5 and (near <= 1.0).sum() <= 4


def test_each_plan_of_an_interior_fills_its_quadrants_inwards_and_of_a_strip_from_its_other_end(
        noise):
    # every patch along a border is placed on its way in from a corner; the quadrants close
    # against each other inside the tile, and each plan starts with the next quadrant
    # (tasks.corner_tiles, "Where the joins fall")
    from tasks.corner_tiles import HORIZONTAL, VERTICAL, _TileSetPlanner, fill_order, strip_order

    # a strip from both of its corner patches inwards, closing in its middle; every second
    # plan starts with the other half
    assert strip_order(10, 0) == [1, 2, 3, 4, 5, 9, 8, 7, 6]
    assert strip_order(10, 1) == [9, 8, 7, 6, 1, 2, 3, 4, 5]
    assert strip_order(3, 0) == [1, 2] and strip_order(3, 1) == [2, 1]

    assert fill_order(5, 4, 0) == [(1, 1), (1, 2), (2, 1), (2, 2),  # top-left, by rows
                                   (1, 3), (2, 3),  # top-right, from the right
                                   (4, 1), (4, 2), (3, 1), (3, 2),  # bottom-left, from below
                                   (4, 3), (3, 3)]
    for generation in range(1, 5):
        order = fill_order(7, 6, generation)
        assert sorted(order) == sorted(fill_order(7, 6, 0))
        assert order[0] == [(1, 1), (1, 5), (6, 1), (6, 5)][generation % 4]
    reference, exemplar = noise
    plan = _TileSetPlanner(np.asarray(reference, np.float32), QuiltParams(12, 3, 3, 2, (27, 27)),
                           seed=1, exemplar=exemplar)
    plan.plan_all()
    windows = [[p.window for p in plan.fill(5).placements] for _ in range(5)]
    assert [w[0] for w in windows] == [(3, 3), (3, 12), (12, 3), (12, 12), (3, 3)]
    assert [w[-1] for w in windows] == [(12, 12), (3, 3), (3, 12), (12, 3), (12, 12)]
    assert all(sorted(w) == sorted(windows[0]) for w in windows)
    for key, ends in (((HORIZONTAL, 0, 1), [(0, 9), (0, 18)]),
                      ((VERTICAL, 1, 1), [(9, 0), (18, 0)])):
        first = [p.window for p in plan.strips[key].placements]
        plan.plan_strip(key)
        again = [p.window for p in plan.strips[key].placements]
        assert (first, again) == (ends, ends[::-1])


def test_a_strip_planned_again_keeps_the_best_of_its_candidates(noise):
    """Of the candidates, the strip kept is the one whose middle line stands out least, each
    candidate from a stream of its own (the next ones: none is planned twice); the tiles
    along it are planned again, the others kept."""
    from tasks.corner_tiles import VERTICAL, _TileSetPlanner

    reference, exemplar = noise
    plan = _TileSetPlanner(np.asarray(reference, np.float32), QuiltParams(12, 3, 3, 2, (27, 27)),
                           seed=5, exemplar=exemplar)
    plan.plan_all()
    for number in range(len(plan.types)):
        plan.tiles[number] = plan.plan_tile(number, 1)
    key = (VERTICAL, 0, 1)
    first = plan.generation[key]
    candidates = [plan._strip(key, g) for g in range(first, first + 3)]
    figures = [plan.strip_figure(key, c) for c in candidates]
    assert len(set(figures)) == 3 and np.argmin(figures) != 0  # not simply the first
    plan.plan_strips([key], candidates=3)
    kept = plan.strips[key]
    best = candidates[int(np.argmin(figures))]
    assert kept.placements == best.placements
    np.testing.assert_array_equal(kept.canvas.value, best.canvas.value)
    assert plan.generation[key] == first + 3
    along = {n for n, t in enumerate(plan.types) if key in plan.tile_strips(t)}
    assert set(plan.tiles) == set(range(len(plan.types))) - along


def test_a_strip_cut_from_the_sample_stands_out_in_neither_direction():
    """A strip's figure looks at its patches as they lie: strips cut from a striped sample
    (rows of one period, columns of another) along either direction show the sample's own
    patches (figure 0), while the same strips turned by 90 degrees do not."""
    from tasks.canvas import Canvas
    from tasks.corner_tiles import HORIZONTAL, VERTICAL, _Piece, _TileSetPlanner

    rng = np.random.default_rng(3)
    y, x = np.mgrid[0:60, 0:64]
    reference = np.stack([np.sin(y * 2 * np.pi / 5), np.sin(x * 2 * np.pi / 9),
                          0.1 * rng.random((60, 64))], axis=-1).astype(np.float32)
    params = QuiltParams(12, 3, 3, 2, (27, 27))
    plan = _TileSetPlanner(reference, params, seed=0)
    b, length = params.block, params.tile[0]

    def piece(value):
        canvas = Canvas.empty(*value.shape)
        canvas.value[...] = value
        return _Piece(canvas, [])

    across = reference[5 : 5 + b, 3 : 3 + length + b]
    down = reference[2 : 2 + length + b, 7 : 7 + b]
    assert plan.strip_figure((HORIZONTAL, 0, 1), piece(across)) < 1e-6
    assert plan.strip_figure((VERTICAL, 0, 1), piece(down)) < 1e-6
    turned = [plan.strip_figure((VERTICAL, 0, 1), piece(across.transpose(1, 0, 2))),
              plan.strip_figure((HORIZONTAL, 0, 1), piece(down.transpose(1, 0, 2)))]
    assert min(turned) > 0.05, turned


def test_the_cheapest_loop_costs_what_scipys_dijkstra_finds():
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    from tasks.quilt_kernels import cheapest_loop

    def scipy_best(cost, col, top):  # the sparse graph boundary_cut searched before
        n = len(cost)
        ids = np.arange(n * n).reshape(n, n)
        rows, cols, weights = [], [], []
        for dy, dx in ((0, 1), (1, 0)):
            w = 0.5 * (cost[: n - dy, : n - dx] + cost[dy:, dx:])
            ok = np.isfinite(w)
            if dx == 1:
                ok[:top, col] = False  # no step across the slit
            a, c = ids[: n - dy, : n - dx][ok], ids[dy:, dx:][ok]
            rows += [a, c]
            cols += [c, a]
            weights += [w[ok], w[ok]]
        graph = coo_matrix((np.concatenate(weights), (np.concatenate(rows),
                                                      np.concatenate(cols))), shape=(n * n,) * 2)
        best = np.inf
        for r in range(top):
            if np.isfinite(cost[r, col]) and np.isfinite(cost[r, col + 1]):
                dist = dijkstra(graph.tocsr(), indices=ids[r, col])
                best = min(best, dist[ids[r, col + 1]] + 0.5 * (cost[r, col] + cost[r, col + 1]))
        return best

    rng = np.random.default_rng(11)
    found = 0
    for case in range(60):
        n = int(rng.integers(5, 30))
        cost = rng.random((n, n)) ** 3 * 10
        cost[rng.random((n, n)) < (0.5 if case % 3 == 0 else 0.05)] = 0.0  # ties
        cost[rng.random((n, n)) < 0.1 * (case % 4)] = np.inf  # walls
        col, top = n // 2, int(rng.integers(0, n // 2))
        loop, ok = cheapest_loop(cost, col, top)
        expected = scipy_best(cost, col, top)
        assert ok == np.isfinite(expected)
        if ok:  # a loop's cost: each step half of each end, so each node's cost once
            found += 1
            assert float(cost[loop].sum()) == pytest.approx(expected, rel=1e-12, abs=1e-12)
            assert any(loop[r, col] and loop[r, col + 1] for r in range(top))
    assert found >= 30


def _numpy_place(canvas: Canvas, patch_index, patch_value, alpha, y0: int, x0: int) -> None:
    """Canvas.place as twenty numpy calls: the reference the compiled blend must match."""
    rows, cols = canvas.window(y0, x0, *alpha.shape)
    py, px = rows - y0, cols - x0
    a = alpha[np.ix_(py, px)].astype(np.float32)
    sel = np.ix_(rows, cols)
    if np.any(~canvas.filled[sel] & (a < 1.0)):
        raise ValueError("a patch must cover empty canvas pixels with weight 1")
    keep = a > 0
    idx = canvas.index[sel]
    wt = canvas.weight[sel] * (1.0 - a)[..., None]
    wt[wt < 1e-4] = 0.0
    idx[wt == 0] = -1
    slot = np.argmin(np.where(idx >= 0, wt, -1.0), axis=-1)
    ys, xs = np.nonzero(keep)
    idx[ys, xs, slot[ys, xs]] = patch_index[np.ix_(py, px)][ys, xs]
    wt[ys, xs, slot[ys, xs]] = a[ys, xs]
    total = wt.sum(axis=-1, keepdims=True, dtype=np.float64)
    canvas.index[sel] = idx
    canvas.weight[sel] = np.where(total > 0, wt / np.where(total > 0, total, 1.0), 0.0)
    value = canvas.value[sel]
    canvas.value[sel] = np.where(keep[..., None], a[..., None] * patch_value[np.ix_(py, px)]
                                 + (1 - a)[..., None] * value, value)
    canvas.filled[sel] |= keep


@pytest.mark.parametrize("case", ["random", "ties", "masked", "few allowed", "nan"])
def test_the_candidates_k_best_are_the_smallest_errors_ties_to_the_lower_position(case):
    from tasks.quilt_kernels import smallest

    rng = np.random.default_rng(len(case))
    err = rng.random((37, 53)).astype(np.float32)
    if case == "ties":  # a periodic sample: many exactly equal errors, the best among them
        err = np.round(err * 4).astype(np.float32)
    allowed = rng.random(err.shape) < (0.002 if case == "few allowed" else 0.3)
    if case == "nan":
        err[rng.random(err.shape) < 0.5] = np.nan
    use = case in ("masked", "few allowed")
    positions = np.flatnonzero(allowed if use else np.ones(err.shape, bool))
    positions = positions[~np.isnan(err.ravel()[positions])]
    for k in (1, 5, 17):
        k = min(k, positions.size)
        expected = positions[np.lexsort((positions, err.ravel()[positions]))][:k]
        got = smallest(err, allowed if use else np.ones((1, 1), bool), use, k)
        assert got.tolist() == expected.tolist(), k


def test_the_compiled_blend_gives_the_bits_of_numpys():
    rng = np.random.default_rng(8)
    for _ in range(60):
        h, w, b = (int(n) for n in rng.integers([8, 8, 3], [50, 50, 20]))
        ours, theirs = Canvas.empty(h, w, 3), Canvas.empty(h, w, 3)
        for _ in range(10):  # patches overlapping each other and the canvas' edges
            y0, x0 = int(rng.integers(-b, h)), int(rng.integers(-b, w))
            alpha = (rng.random((b, b)) ** 2).astype(np.float32)
            alpha[rng.random((b, b)) < 0.2] = 0.0
            alpha[rng.random((b, b)) < 0.02] = 5e-5  # a weight dropped once blended
            rows, cols = ours.window(y0, x0, b, b)
            empty = np.ones((b, b), bool)
            empty[np.ix_(rows - y0, cols - x0)] = ~ours.filled[np.ix_(rows, cols)]
            alpha[empty] = 1.0
            index = rng.integers(0, 10**6, (b, b)).astype(np.int32)
            value = rng.random((b, b, 3)).astype(np.float32)
            ours.place(index, value, alpha, y0, x0)
            _numpy_place(theirs, index, value, alpha, y0, x0)
        for name in ("index", "weight", "value", "filled"):
            np.testing.assert_array_equal(getattr(ours, name), getattr(theirs, name), name)
        total = ours.weight.sum(axis=-1, dtype=np.float64)  # rows sum to 1 where filled, else 0
        assert np.allclose(total[ours.filled], 1.0, atol=1e-5)
        assert np.all(total[~ours.filled] == 0)
    with pytest.raises(ValueError, match="empty canvas pixels with weight 1"):
        Canvas.empty(4, 4, 3).place(np.zeros((2, 2), np.int32), np.zeros((2, 2, 3), np.float32),
                                    np.full((2, 2), 0.5, np.float32), 1, 1)


@pytest.mark.parametrize(("corners", "side", "bound", "seed", "lines", "whole", "ahead"), [
    # 3 rounds: strips planned again (the best of four), then the whole set again
    (2, 18, 1.1, 2, 3, True, False),
    (1, 27, 0.98, 8, 2, False, True),  # one tile: its plans made ahead, 8 in 2 rounds
    (2, 18, 1.05, 6, 3, False, True),  # rounds with one tile beyond the bound: ahead too
])
def test_the_tile_set_is_the_same_for_any_number_of_planning_threads(
        noise, monkeypatch, corners, side, bound, seed, lines, whole, ahead):
    from tasks import corner_tiles

    reference, exemplar = noise
    params = QuiltParams(12, 3, 3, corners, (side, side), max_seam=bound, attempts=4)
    said, spared = [], []
    plan_tile = corner_tiles._TileSetPlanner.plan_tile

    def spying(planner, number, attempts, spare=None, ahead=0, best=None):
        spared.append(spare is not None)
        return plan_tile(planner, number, attempts, spare, ahead, best)

    monkeypatch.setattr(corner_tiles._TileSetPlanner, "plan_tile", spying)
    plans = []
    for threads in (1, 3):
        spared.clear()
        plans.append(plan_tiles(reference, params, seed=seed, exemplar=exemplar,
                                threads=threads, progress=said.append))
    assert len(said) == 2 * lines
    assert any("the whole set planned again" in line for line in said) == whole
    assert any(spared) == ahead  # on 3 threads: plans made ahead beside a tile alone
    one, other = plans
    assert one.placements == other.placements
    assert one.checks == other.checks  # the same figures and counts of plans
    for a, b in zip(one.tiles, other.tiles, strict=True):
        for name in ("index", "weight", "value"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_planning_says_how_its_rounds_go_and_a_passing_plan_is_silent(noise):
    reference, exemplar = noise
    lines = []
    strict = QuiltParams(12, 3, 3, 2, (18, 18), max_seam=1e-3, attempts=2)
    with pytest.raises(SeamError):
        plan_tiles(reference, strict, seed=2, exemplar=exemplar, progress=lines.append)
    assert len(lines) == 2, lines
    assert lines[0].startswith("block 12, 16 tile(s) of 18 x 18: round 1 of at most 2: ")
    # every tile planned once in the first round; the strips that two or more tiles fail at
    # planned again at once, before more plans of those tiles' interiors
    assert re.search(r"; \d+ strip\(s\) along which two or more tiles fail planned again "
                     r"\(16 interior plan\(s\) so far\)$", lines[0]), lines
    # the last round: tiles along no shared strip planned up to INTERIOR_ATTEMPTS times
    assert lines[1].endswith(f"({16 + 16 * INTERIOR_ATTEMPTS} interior plan(s) so far)"), lines
    assert "round 2 of at most 2: 0 of 16 tile(s) within the bound (" in lines[1], lines
    # each round names its worst tile, border and figure (beyond the bound)
    for line in lines:
        found = re.search(r"within the bound \(worst: tile (\d{4}), (row|col) \d+ "
                          r"\((seam|structure) (\d+\.\d+)\)\)", line)
        assert found and float(found[4]) > 1e-3, line
    lines.clear()
    plan_tiles(reference, QuiltParams(12, 3, 3, 2, (18, 18), **ANY_SEAM), seed=2,
               exemplar=exemplar, progress=lines.append)
    assert lines == []


def test_the_border_check_refuses_a_tile_that_breaks_the_pattern():
    from benchmarks.seams import reference_of

    reference = reference_of("tiles")  # strictly periodic, 64 texels
    params = QuiltParams(64, 16, 5, 1, (192, 192))
    exemplar = _exemplar(reference, params)  # the planner's check and this one: one made
    plan = plan_tiles(reference, params, seed=3, exemplar=exemplar)
    check = BorderCheck(reference, params, exemplar)
    assert check.figures(plan.tiles[0], *[None] * 4).worst <= 1.3
    broken = plan.tiles[0]
    broken.value[:, 96:] = np.roll(broken.value[:, 96:], 20, axis=0)  # half shifted by 20 rows
    assert check.figures(broken, *[None] * 4).worst_structure > 1.3


def test_the_default_tile_holds_whole_periods_and_a_given_one_that_does_not_is_named(
        tmp_path, btf, big_tiles):
    from benchmarks.seams import reference_of
    from tasks.quilt_layout import default_tile, sample_lattice, tile_mismatch

    lattice = sample_lattice(reference_of("fabric"))  # a centred lattice, 16 texels along axes
    tile = default_tile((256, 256), 12, lattice)
    assert max(tile_mismatch(tile, lattice)) <= 1.0 and all(n % 12 == 0 for n in tile), tile
    assert max(tile_mismatch((252, 252), lattice)) > 1.0  # the previous default: 15.75 periods
    result = btf("quilt", big_tiles, tmp_path / "q.zarr", "--block", "40", "--overlap", "10",
                 "--size", "150,150", "--max-seam", "10")
    assert result.code == 0, result.err
    assert "out of phase with the sample's lattice" in result.err
    assert "sizes that close: 120,120" in result.err


def test_a_plan_that_cannot_pass_stops_with_the_tile_and_its_figure(tmp_path, btf, samples):
    out = tmp_path / "q.zarr"
    # the smallest tile (two steps): it fails every round as a whole sample's tile does, in a
    # sixth of the time
    result = btf("quilt", samples["stone"], out, *PARAMS, "--max-seam", "0.3", "--size",
                 "24,24")
    assert result.code == 1
    assert "tile 0000: after" in result.err and "stands out" in result.err
    assert "bound 0.3" in result.err and not out.exists()


def test_the_automatic_block_fits_a_given_tile_size():
    from benchmarks.lattices import random_lattice_texture
    from tasks.quilt_layout import choose_block

    case = random_lattice_texture(np.random.default_rng(2), motif="blobs", noise=0.0,
                                  gradient=0.0, low=39, high=41)
    block, overlap, why = choose_block(case.image)
    assert block == 40 and overlap == 10
    block, overlap, why = choose_block(case.image, tile=(144, 144))  # step 30 does not divide
    assert 144 % (block - overlap) == 0 and abs(block - 40) <= 10, (block, overlap, why)
    assert "divides the tile 144 x 144" in why
    block, overlap, why = choose_block(case.image, tile=(97, 97))  # nothing near divides 97
    assert (block, overlap) == (32, 8) and "the default" in why


def test_the_quilt_bench_takes_its_application_rate_from_the_run_that_plans_once():
    from benchmarks.quilt import rates

    result = {"sampling": "abtf:6,4", "machine": {"cpus": 2},
              "planning": [{"size": 512, "tile": [504, 504], "plan_seconds": 4.0}],
              "quilt_cli": {"seconds": 38.5, "one_plan_seconds": 9.0}}
    values = 504 * 504 * 24 * 3  # tile texels x layers x channels
    got = rates(result)
    assert got["quilt_values_per_core_second"] == pytest.approx(values / (9.0 - 4.0 - 1.0) / 2)
    assert got["quilt_plan_seconds_per_texel_pair"] == pytest.approx(4.0 / (504**2 * 512**2))
    del result["quilt_cli"]["one_plan_seconds"]  # a run that planned until the check passed
    assert "quilt_values_per_core_second" not in rates(result)


def test_the_quilt_bench_times_the_product_against_scipys_and_a_copy():
    import argparse
    import types

    from benchmarks.quilt import _application

    rng = np.random.default_rng(0)
    index = rng.integers(-1, 64, (8, 8, TERMS)).astype(np.int32)
    weight = np.where(index >= 0, rng.random(index.shape), 0).astype(np.float32)
    plan = types.SimpleNamespace(tiles=[types.SimpleNamespace(index=index, weight=weight)])
    result = _application(plan, rng.random((2, 8, 8, 3)).astype(np.float32),
                          argparse.Namespace(repeat=1))
    assert result["nnz_per_row"] == pytest.approx((index >= 0).sum() / 64)
    assert all(r["apply_gbps"] > 0 and r["scipy_gbps"] > 0 for r in result["threads"].values())


def test_the_photo_plans_bench_draws_crops_and_seeds_and_repeats_a_draw():
    from benchmarks.photoplans import SIZE, draws, photo, photo_reference

    first, again, other = draws(7, ["brick", "grass"], 3), draws(7, ["brick", "grass"], 3), \
        draws(8, ["brick", "grass"], 3)
    assert first == again and first != other
    for case in first:
        h, w = photo(case["photo"]).shape
        y, x = case["crop"]
        assert 0 <= y <= h - SIZE and 0 <= x <= w - SIZE
    g = photo("gravel")[:SIZE, :SIZE]
    reference = photo_reference(g)
    assert reference.shape == (SIZE, SIZE, 3) and np.isfinite(reference).all()
    # the reference follows the photo (the diffuse map dominates the default weights)
    assert np.corrcoef(reference.mean(axis=-1).ravel(), g.ravel())[0, 1] > 0.7


@pytest.mark.slow
def test_tile_sets_planned_on_photos_keep_the_bound_for_a_random_draw():
    """`btf quilt --corners 2`'s defaults on 256^2 photo crops (16 tiles of 240^2), one crop
    and seed per photo drawn anew every run: every output within the bound 1.3 on its 4 x 4
    mosaic, as sharp as the bench holds (BENCHMARKS.md, "Quilt plans on photos")."""
    from benchmarks.photoplans import draws, measure

    # and a draw whose mosaic stood at 1.307 while its thinned checks passed (THIN_MARGIN)
    known = {"photo": "brick", "crop": [154, 172], "seed": 2056478575}
    for case in [*draws(None, ["brick", "gravel", "grass"], 1), known]:
        r = measure(case, threads=2)
        if r["failed"]:  # refused with its message: nothing out of bounds is written
            assert "try another seed" in r["failed"], r
            continue
        assert r["seam"] <= 1.3 and r["structure"] <= 1.3, r
        assert r["sharpness"] >= 0.75, r
