"""The reference image that guides quilting (paper 003, section 2.2): ``btf reference``."""

from __future__ import annotations

import numpy as np

from helpers import generate_store
from pipeline.stores.radiance import open_radiance


def test_reference_maps_follow_the_ground_truth(tmp_path, btf):
    path = generate_store(tmp_path / "leather.zarr", "--material", "leather", "--size", "96",
                          "--sampling", "abtf:12,6", "--seed", "1")
    from pipeline.graphs.reference import compute_reference
    from pipeline.session import RuntimeOptions, Session

    with Session(RuntimeOptions(quiet=True)) as session:
        maps, view = compute_reference(path, weights=(1, 0.5, 0.5), view=None, session=session)
    truth = open_radiance(path)
    height = truth["height"].values
    albedo = truth["albedo"].values

    def corr(a, b):
        return np.corrcoef(a.ravel(), b.ravel())[0, 1]

    assert view == 0
    assert corr(maps.height, height) > 0.7
    assert corr(maps.diffuse.mean(-1), albedo.mean(-1)) > 0.8
    grow, gx = np.gradient(height)  # the frame's +y is towards row 0: n_y goes with +dh/drow
    assert corr(maps.normal[..., 0], -gx) > 0.6 and corr(maps.normal[..., 1], grow) > 0.6
    assert maps.reference.min() >= 0 and maps.reference.max() <= 1
    result = btf("reference", path, tmp_path / "ref.exr", "--weights", "1,1,0", "--quiet")
    assert result.code == 0
    import OpenEXR

    with OpenEXR.File(str(tmp_path / "ref.exr"), separate_channels=True) as f:
        planes = {name: np.array(c.pixels) for name, c in f.channels().items()}
    assert set(planes) == {"diffuse.R", "diffuse.G", "diffuse.B", "height.Y", "reflectance.Y",
                           "normal.X", "normal.Y", "normal.Z", "reference.R", "reference.G",
                           "reference.B"}
    assert planes["height.Y"].shape == (96, 96)
    # weights 1,1,0: the reference is the mean of the diffuse and height maps
    assert np.allclose(planes["reference.G"], 0.5 * (planes["diffuse.G"] + planes["height.Y"]),
                       atol=1e-6)


def test_light_sums_of_blocks_combine_to_the_sums_over_all_lights():
    from tasks.reference import combine_light_sums, light_sums
    from tasks.sampling import direction_vectors, parse_sampling

    s = parse_sampling("abtf:6,3")
    lights = direction_vectors(s.theta_light, s.phi_light)
    layers = np.random.default_rng(2).gamma(0.5, 1.0, (len(lights), 9, 11, 3)).astype(np.float32)
    whole = light_sums(layers, lights)
    for cuts in ([5, 9], [1, 2, 17]):
        parts = np.stack([light_sums(layers[a:b], lights[a:b])
                          for a, b in zip([0, *cuts], [*cuts, len(lights)], strict=True)])
        # equal up to the float32 rounding of the luminance each block is weighted by
        assert np.allclose(combine_light_sums(parts), whole, rtol=1e-6, atol=1e-6)
        # associative: combining partial combinations gives the same
        twice = combine_light_sums(np.stack([combine_light_sums(parts[:2]),
                                             combine_light_sums(parts[2:])]))
        assert np.allclose(twice, whole, rtol=1e-6, atol=1e-6)


def test_a_view_s_light_sums_read_block_by_block_equal_the_whole_view_s(tmp_path, small_tasks):
    """Several blocks of lights, rows and columns (odd sizes at the edges), each read in its
    own task: the combined sums are those of the whole view at once."""
    import dask

    from pipeline.graphs.reductions import light_sums
    from pipeline.stores.base import Directions
    from tasks.reference import light_sums as whole_sums
    from tasks.sampling import direction_vectors

    path = generate_store(tmp_path / "g.zarr", "--material", "stone", "--size", "37",
                          "--sampling", "hemi:5", "--chunk", "8", "--dir-chunk", "2")
    ds = open_radiance(path)
    d = Directions.of(ds)
    lights = direction_vectors(d.theta_light, d.phi_light)
    assert d.theta_view.size > 1
    for view in (0, d.theta_view.size - 1):
        sums, blocks = light_sums(path, view, lights)
        assert blocks[0] > 1 and blocks[1] > 1 and blocks[2] > 1, blocks
        (got,) = dask.compute(sums, scheduler="threads")
        want = whole_sums(ds["radiance"].values[view], lights)
        assert got.shape == want.shape == (37, 37, want.shape[-1])
        assert np.allclose(got, want, rtol=1e-6, atol=1e-6)
