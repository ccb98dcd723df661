"""The ``btf`` BSDF for Mitsuba 3 against btf's own reconstruction and the page's blend.

These need Mitsuba 3 and its llvm variant (LLVM 16 or later, see docs/mitsuba.md): slow
tests, skipped with the reason where either is missing, unless ``BTF_REQUIRE_MITSUBA=1``
(``.ci/run``, which installs both) makes that a failure.
"""

from __future__ import annotations

import numpy as np
import pytest

from helpers import generate_store, require_mitsuba_llvm
from pipeline import mitsuba_plugin
from pipeline.cli import main
from pipeline.stores import open_layers, open_store
from tasks.sampling import direction_vectors
from tasks.viewer import coefficients, locate, mesh

pytestmark = pytest.mark.slow
mi = dr = None  # mitsuba and drjit, once the module's fixture found them working


@pytest.fixture(scope="module", autouse=True)
def _mitsuba():
    """Import Mitsuba and check its llvm variant here, not at collection (no cost unless run)."""
    global mi, dr
    require_mitsuba_llvm()
    import drjit
    import mitsuba

    mi, dr = mitsuba, drjit


SIZE = 24


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    """Compressed stores: one top view (abtf) and a hemisphere of views, rank 6."""
    tmp = tmp_path_factory.mktemp("mitsuba")
    out = {}
    for name, sampling in (("abtf", "abtf:8,3"), ("hemi", "hemi:5")):
        src = generate_store(tmp / f"{name}.zarr", "--material", "leather", "--size", str(SIZE),
                             "--sampling", sampling, "--seed", "4")
        assert main(["compress", str(src), str(tmp / f"{name}_c.zarr"), "--rank", "6",
                     "-q"]) == 0
        out[name] = tmp / f"{name}_c.zarr"
    mitsuba_plugin.variant("llvm_ad_rgb")
    return out


_unit = direction_vectors  # (theta, phi) in degrees -> unit vectors


def _texel_centres(bsdf, h: int, w: int, wi, wo) -> np.ndarray:
    """``(h, w, 3)``: the BSDF at every texel centre of an ``h x w`` texture (row 0 at the
    top), seen from ``wi`` and lit from ``wo`` (local unit vectors)."""
    ys, xs = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    n = ys.size
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(*[np.full(n, c, np.float32) for c in wi])
    si.uv = mi.Point2f(((xs.ravel() + 0.5) / w).astype(np.float32),
                       (1 - (ys.ravel() + 0.5) / h).astype(np.float32))
    value = bsdf.eval(mi.BSDFContext(), si,
                      mi.Vector3f(*[np.full(n, c, np.float32) for c in wo]))
    return np.stack([np.asarray(value[c]) for c in range(3)], -1).reshape(h, w, 3)


def _plane_pixels(bsdf, light: np.ndarray, at: tuple[float, float] = (0.5, 0.5)) -> np.ndarray:
    """``(y, x, 3)``: a unit-irradiance directional light on the plane, seen from straight
    above by an orthographic camera, one ray through each texel at ``at`` (its centre by
    default; row 0 at the top)."""
    scene = mi.load_dict({"type": "scene", "plane": {"type": "rectangle", "bsdf": bsdf}})
    ys, xs = np.meshgrid(1 - (np.arange(SIZE) + at[0]) * 2 / SIZE,
                         -1 + (np.arange(SIZE) + at[1]) * 2 / SIZE, indexing="ij")
    n = ys.size
    ray = mi.Ray3f(mi.Point3f(xs.ravel(), ys.ravel(), np.full(n, 2.0)),
                   mi.Vector3f(np.zeros(n), np.zeros(n), -np.ones(n)))
    si = scene.ray_intersect(ray)
    assert bool(dr.all(si.is_valid()))
    to_light = mi.Vector3f(*[np.full(n, c, np.float32) for c in light])
    value = bsdf.eval(mi.BSDFContext(), si, si.to_local(to_light))
    return np.stack([np.asarray(value[c]) for c in range(3)], -1).reshape(SIZE, SIZE, 3)


def test_at_measured_pairs_the_plane_shows_the_reconstructed_layer(stores):
    path = stores["abtf"]
    bsdf = mitsuba_plugin.bsdf(path)
    layers = open_layers(path)["radiance"]  # btf reconstruct's values
    d = open_store(path).directions
    for light in (0, 5, 13, 23):
        got = _plane_pixels(bsdf, _unit(d.theta_light[light], d.phi_light[light]))
        want = layers[0, light].values
        assert np.allclose(got, want, rtol=1e-3, atol=1e-5 * want.max()), light


def test_between_measured_pairs_it_is_the_pages_blend(stores):
    path = stores["hemi"]
    bsdf = mitsuba_plugin.bsdf(path)
    store = open_store(path)
    d, g = store.directions, store.group
    us = g["U"][...] * g["S"][...]
    v = g["V"][...]
    views, lights = mesh(d.theta_view, d.phi_view, "view"), mesh(d.theta_light, d.phi_light,
                                                                  "light")
    rng = np.random.default_rng(7)
    n = 200
    wi = _unit(rng.uniform(0, 85, n), rng.uniform(0, 360, n))
    wo = _unit(rng.uniform(0, 85, n), rng.uniform(0, 360, n))
    ty, tx = rng.integers(0, SIZE, n), rng.integers(0, SIZE, n)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(*[wi[:, c].astype(np.float32) for c in range(3)])
    si.uv = mi.Point2f(((tx + 0.5) / SIZE).astype(np.float32),
                       (1 - (ty + 0.5) / SIZE).astype(np.float32))
    value = bsdf.eval(mi.BSDFContext(), si,
                      mi.Vector3f(*[wo[:, c].astype(np.float32) for c in range(3)]))
    got = np.stack([np.asarray(value[c]) for c in range(3)], -1)
    vl, vw = locate(views, wi[:, :2])
    ll, lw = locate(lights, wo[:, :2])
    transform = store.transform
    for i in range(n):
        c = coefficients(us, [(a, b) for a, b in zip(vl[i], vw[i], strict=True)],
                         [(a, b) for a, b in zip(ll[i], lw[i], strict=True)])
        want = transform.decode((c @ v[ty[i], tx[i]]).astype(np.float32))
        assert np.allclose(got[i], want, rtol=1e-3, atol=1e-6), (i, got[i], want)


def test_a_scene_file_names_the_plugin_and_renders_the_layer(stores, tmp_path):
    path = stores["abtf"]
    mitsuba_plugin.register()
    d = open_store(path).directions
    light = 9
    direction = -_unit(d.theta_light[light], d.phi_light[light])
    scene = tmp_path / "plane.xml"
    scene.write_text(f"""<scene version="3.0.0">
  <integrator type="direct"/>
  <sensor type="orthographic">
    <transform name="to_world"><lookat origin="0, 0, 2" target="0, 0, 0" up="0, 1, 0"/>
    </transform>
    <sampler type="independent"><integer name="sample_count" value="16"/></sampler>
    <film type="hdrfilm"><integer name="width" value="{SIZE}"/>
      <integer name="height" value="{SIZE}"/><rfilter type="box"/></film>
  </sensor>
  <emitter type="directional">
    <vector name="direction" x="{direction[0]}" y="{direction[1]}" z="{direction[2]}"/>
    <rgb name="irradiance" value="1"/>
  </emitter>
  <shape type="rectangle"><bsdf type="btf"><string name="store" value="{path}"/></bsdf>
  </shape>
</scene>""")
    image = np.asarray(mi.render(mi.load_file(str(scene)), spp=256))
    assert image.shape == (SIZE, SIZE, 3) and np.isfinite(image).all()
    # a pixel is the mean of the BSDF over its texel's footprint (bilinear between texel
    # centres, then the transform): 8 x 8 rays per texel, under the same unit irradiance
    bsdf = mitsuba_plugin.bsdf(path)
    offsets = (np.arange(8) + 0.5) / 8
    footprint = np.mean([_plane_pixels(bsdf, -direction, (a, b)) for a in offsets
                         for b in offsets], axis=0)
    assert np.allclose(image.mean(axis=(0, 1)), footprint.mean(axis=(0, 1)), rtol=0.01)
    assert np.median(np.abs(image - footprint) / footprint.max()) < 0.01
    # the picture is upright: its rows are the layer's rows, not reversed ones
    want = open_layers(path)["radiance"][0, light].values.mean(-1)
    lum = image.mean(-1)
    assert np.corrcoef(lum.ravel(), want.ravel())[0, 1] > np.corrcoef(
        lum.ravel(), want[::-1].ravel())[0, 1] + 0.1


def test_sampling_matches_its_pdf_and_its_weights_are_eval_over_pdf(stores):
    from mitsuba.chi2 import BSDFAdapter, ChiSquareTest, SphericalDomain

    path = stores["hemi"]
    mitsuba_plugin.register()
    sample_func, pdf_func = BSDFAdapter("btf", f'<string name="store" value="{path}"/>')
    chi2 = ChiSquareTest(domain=SphericalDomain(), sample_func=sample_func, pdf_func=pdf_func,
                         sample_dim=3)
    assert chi2.run(), chi2.messages
    # the weight sample() returns is eval / pdf of the direction it drew
    bsdf = mitsuba_plugin.bsdf(path)
    n = 4096
    rng = np.random.default_rng(3)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    wi = _unit(rng.uniform(0, 80, n), rng.uniform(0, 360, n))
    si.wi = mi.Vector3f(*[wi[:, c].astype(np.float32) for c in range(3)])
    si.uv = mi.Point2f(*[rng.random(n).astype(np.float32) for _ in range(2)])
    ctx = mi.BSDFContext()
    bs, weight = bsdf.sample(ctx, si, mi.Float(rng.random(n).astype(np.float32)),
                             mi.Point2f(*[rng.random(n).astype(np.float32) for _ in range(2)]))
    value, pdf = bsdf.eval_pdf(ctx, si, bs.wo)
    expected = np.stack([np.asarray(value[c]) for c in range(3)], -1) / np.asarray(pdf)[:, None]
    got = np.stack([np.asarray(weight[c]) for c in range(3)], -1)
    assert np.allclose(got, expected, rtol=1e-5, atol=1e-7)
    assert np.allclose(np.asarray(bs.pdf), np.asarray(pdf), rtol=1e-6)


def test_btf_mitsuba_renders_the_plane_and_the_scalar_variant_agrees(stores, tmp_path):
    from pipeline.images import read_image

    path = stores["abtf"]
    d = open_store(path).directions
    light = 6
    theta, phi = float(d.theta_light[light]), float(d.phi_light[light])
    out = tmp_path / "plane.exr"
    assert main(["mitsuba", str(path), str(out), "--light", f"{theta},{phi}", "--spp", "256",
                 "--variant", "llvm_ad_rgb", "-q"]) == 0
    image, channels = read_image(out)
    assert channels == ("R", "G", "B") and image.shape == (SIZE, SIZE, 3)
    bsdf = mitsuba_plugin.bsdf(path)
    offsets = (np.arange(8) + 0.5) / 8
    footprint = np.mean([_plane_pixels(bsdf, _unit(theta, phi), (a, b)) for a in offsets
                         for b in offsets], axis=0)
    assert np.allclose(image.mean(axis=(0, 1)), footprint.mean(axis=(0, 1)), rtol=0.01)
    # scalar_rgb evaluates the same Dr.Jit code one sample at a time: the same values
    centre = _plane_pixels(bsdf, _unit(theta, phi))
    mitsuba_plugin.variant("scalar_rgb")
    try:
        scalar = mitsuba_plugin.bsdf(path)
        for y, x in ((0, 0), (5, 17), (23, 23)):
            si = dr.zeros(mi.SurfaceInteraction3f)
            si.wi = mi.Vector3f(0, 0, 1)
            si.uv = mi.Point2f((x + 0.5) / SIZE, 1 - (y + 0.5) / SIZE)
            value = scalar.eval(mi.BSDFContext(), si, mi.Vector3f(*_unit(theta, phi)))
            assert np.allclose([value[0], value[1], value[2]], centre[y, x], rtol=1e-5,
                               atol=1e-7)
    finally:
        mitsuba_plugin.variant("llvm_ad_rgb")


@pytest.mark.parametrize("maker", ["quilt", "roller"])
def test_a_tile_set_on_a_plane_is_btf_renders_surface(tmp_path, maker):
    from pipeline.images import read_image

    if maker == "quilt":
        src = generate_store(tmp_path / "s.zarr", "--material", "leather", "--size", "48",
                             "--sampling", "abtf:6,2", "--seed", "2")
        args = ["quilt", "--corners", "2"]
    else:  # the roller on an exactly periodic material
        src = generate_store(tmp_path / "s.zarr", "--material", "tiles", "--size", "96",
                             "--scale", "16", "--sampling", "abtf:6,2", "--seed", "3")
        args = ["roller", "--tiles", "2"]
    assert main(["compress", str(src), str(tmp_path / "c.zarr"), "--rank", "5", "-q"]) == 0
    tiles = tmp_path / "t.zarr"
    assert main([args[0], str(tmp_path / "c.zarr"), str(tiles), *args[1:], "-q"]) == 0
    h, w, light = 70, 90, 7
    assert main(["render", str(tiles), str(tmp_path / "r.exr"), "--light", str(light),
                 "--size", f"{h},{w}", "--origin", "5,-11", "-q"]) == 0
    want, _ = read_image(tmp_path / "r.exr")
    bsdf = mitsuba_plugin.bsdf(tiles, size=(h, w), origin=(5, -11))
    d = open_store(tiles).directions
    got = _texel_centres(bsdf, h, w, (0, 0, 1), _unit(d.theta_light[light], d.phi_light[light]))
    assert np.allclose(got, want, rtol=1e-3, atol=1e-6 * want.max())


@pytest.mark.parametrize(("model", "cosine"), [(11, False), (10, False), (9, True), (12, False)])
def test_a_dfmf_store_shows_its_layers_through_its_colour_model(tmp_path, model, cosine):
    from dfmf_files import write_dfmf

    views = [(0.0, 0.0), (0.3, 1.2), (0.6, -2.0)]  # radians, as Bonn's files
    lights = [(0.0, 0.0), (0.5, 0.4), (0.9, 3.0), (1.1, -1.5)]
    rng = np.random.default_rng(model)
    ks, width, height = (3, 2, 2), 20, 12
    rows = len(views) * len(lights)
    u = [rng.normal(size=(rows, k)) * 0.1 for k in ks]
    sxv = [rng.normal(size=(width * height, k)) * 0.3 for k in ks]
    for c in range(3):
        log_like = c == 0 or model == 12
        u[c][:, 0], sxv[c][:, 0] = (-1.0 if log_like else 0.02), 1.0
    write_dfmf(tmp_path / "s.btf", views=views, lights=lights, u=u, sxv=sxv,
               color_model=model, scalar_size=2, width=width, height=height, cosine=cosine)
    assert main(["ingest", str(tmp_path / "s.btf"), str(tmp_path / "s.zarr"), "-q"]) == 0
    store = open_store(tmp_path / "s.zarr")
    d = store.directions
    layers = open_layers(tmp_path / "s.zarr")["radiance"].values  # btf reconstruct's
    bsdf = mitsuba_plugin.bsdf(tmp_path / "s.zarr")
    for v in range(d.views):
        for li in range(d.lights):
            got = _texel_centres(bsdf, height, width, _unit(d.theta_view[v], d.phi_view[v]),
                                 _unit(d.theta_light[li], d.phi_light[li]))
            want = layers[v, li]
            assert np.allclose(got, want, rtol=1e-3, atol=1e-5 * want.max()), (v, li)


def test_a_level_of_detail_is_the_pages_block_means(stores):
    from tasks.viewer import block_means

    path = stores["abtf"]
    store = open_store(path)
    g, d = store.group, store.directions
    bsdf = mitsuba_plugin.bsdf(path, level=1)
    side, light = SIZE // 2, 11
    got = _texel_centres(bsdf, side, side, (0, 0, 1),
                         _unit(d.theta_light[light], d.phi_light[light]))
    us = g["U"][0, light] * g["S"][...]  # (channel, k)
    want = store.transform.decode(block_means(g["V"][...], 2) @ us.T)
    assert np.allclose(got, want, rtol=1e-3, atol=1e-6)
