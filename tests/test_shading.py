"""Physics of the renderer against analytic references."""

from __future__ import annotations

import math

import numpy as np
import pytest

from helpers import facing
from tasks.heightfield import (
    Step,
    bilinear,
    bilinear_layers,
    dda_step,
    parallax_hits,
    shadow_tops,
    shifted,
    visibility,
)
from tasks.materials import Fields, Material
from tasks.sampling import direction_vectors, parse_sampling
from tasks.shading import ShadingModel, Surface, render_block, shade, shade_all


def _render(fields, halo, model, tv, pv, tl, pl):
    return render_block(fields, halo=halo, theta_view=np.atleast_1d(tv).astype(float),
                        phi_view=np.atleast_1d(pv).astype(float),
                        theta_light=np.atleast_1d(tl).astype(float),
                        phi_light=np.atleast_1d(pl).astype(float), model=model)


def _reference_radiance(albedo, alpha, f0, light, view, ambient):
    """Lambert + GGX (Walter et al. 2007) for a flat surface, written out independently."""
    n = np.array([0.0, 0.0, 1.0])
    h = (light + view) / np.linalg.norm(light + view)
    nl, nv, nh, vh = n @ light, n @ view, n @ h, view @ h
    a2 = alpha**2
    d = a2 / (math.pi * (nh**2 * (a2 - 1) + 1) ** 2)

    def g1(c):
        return 2 * c / (c + math.sqrt(a2 + (1 - a2) * c * c))

    f = f0 + (1 - f0) * (1 - vh) ** 5
    brdf = np.asarray(albedo) / math.pi + d * g1(nl) * g1(nv) * f / (4 * nl * nv)
    return math.pi * brdf * nl + ambient * np.asarray(albedo) * light[2]


@pytest.mark.parametrize(("tl", "pl", "tv", "pv"), [(0, 0, 0, 0), (30, 0, 30, 180),
                                                     (60, 45, 20, 200), (75, 300, 50, 90)])
def test_flat_surface_matches_the_analytic_brdf(tl, pl, tv, pv):
    albedo, alpha, f0 = np.array([0.6, 0.3, 0.1]), 0.2, 0.04
    model = ShadingModel(relief=2.0)
    halo = model.halo(tv, tl)
    size = 12 + 2 * halo
    fields = Fields.stack(np.full((size, size), 1.0), albedo, alpha, f0)
    out = _render(fields, halo, model, tv, pv, tl, pl)[0, 0]
    light, view = direction_vectors([tl], [pl])[0], direction_vectors([tv], [pv])[0]
    expected = _reference_radiance(albedo, alpha, f0, light, view, model.ambient)
    assert np.allclose(out, expected, rtol=2e-5, atol=1e-7)


def test_white_lambertian_facing_the_light_has_radiance_one():
    fields = Fields.stack(np.zeros((8, 8)), 1.0, 1.0, 1e-6)
    out = _render(fields, 0, ShadingModel(relief=1.0, ambient=0.0), 0, 0, 0, 0)
    assert np.allclose(out, 1.0, atol=1e-4)


def test_glossy_highlights_exceed_one():
    model = ShadingModel(relief=1.0)
    halo = model.halo(20, 20)
    fields = Fields.stack(np.zeros((8 + 2 * halo, 8 + 2 * halo)), 0.3, 0.05, 0.05)
    out = _render(fields, halo, model, 20, 0, 20, 180)
    assert out.min() > 2.0


@pytest.mark.parametrize(("theta", "phi"), [(60, 0), (75, 0), (70, 30), (65, 90), (80, 225)])
def test_cast_shadow_of_a_wall_has_the_analytic_length(theta, phi):
    # A ridge of height 5 along x = 100 (one texel wide) casts a shadow of horizontal length
    # 5 tan(theta) along the light's azimuth, away from the light.
    h = np.zeros((240, 240), np.float32)
    h[:, 120] = 5.0
    v = visibility(h, 60, 60, 120, 120, theta=theta, phi=phi, relief=5.0, penumbra=0.01,
                   max_length=200)
    length = 5.0 * math.tan(math.radians(theta))
    cx = math.cos(math.radians(phi))
    if abs(cx) < 1e-9:
        assert v.min() == 1.0  # light along the ridge: no shadow across it
        return
    row = v[60]
    x = np.arange(60, 180)
    # texels whose ray towards the light crosses the ridge below height 5
    distance = (120 - x) / cx  # horizontal distance along the light direction to the ridge
    shadowed = (distance > 0.5) & (distance < length - 0.5)
    lit = (distance < -0.5) | (distance > length + 1.5)
    assert np.all(row[shadowed] < 0.5)
    assert np.all(row[lit] > 0.5)


@pytest.mark.parametrize("level", [0.5, 3.0, 5.5])
def test_parallax_of_a_flat_plane_is_the_analytic_offset(level):
    # Views are registered at half the relief: a plane at height `level` appears shifted by
    # (level - reference) tan(theta) towards the camera.
    relief, reference = 6.0, 3.0
    h = np.full((80, 80), level, np.float32)
    for theta, phi in ((30, 0), (60, 120), (75, 250)):
        oy, ox = parallax_hits(h, 30, 30, 20, 20, theta=theta, phi=phi, relief=relief,
                               reference=reference)
        shift = (level - reference) * math.tan(math.radians(theta))
        assert np.allclose(ox, shift * math.cos(math.radians(phi)), atol=1e-4)
        # rows run against the frame's +y
        assert np.allclose(oy, -shift * math.sin(math.radians(phi)), atol=1e-4)


def test_a_raised_square_appears_displaced_away_from_an_oblique_camera():
    # End to end through the renderer: a bright square raised to the top of the relief on a dark
    # floor, seen from 60 degrees. Its top is (relief - reference) above the registration plane,
    # so its image moves by (relief - reference) tan(theta) away from the camera; its far edge
    # shows that shift (the near edge is blurred by the visible wall).
    size, relief, theta = 48, 4.0, 60.0
    height = np.zeros((size, size), np.float32)
    height[16:32, 16:32] = relief
    albedo = np.full((size, size, 3), 0.05, np.float32)
    albedo[16:32, 16:32] = 0.9
    model = ShadingModel(relief=relief, ambient=0.0)
    halo = model.halo(theta, 0)
    pad = ((halo, halo), (halo, halo))
    fields = Fields.stack(np.pad(height, pad), np.pad(albedo, (*pad, (0, 0)), mode="edge"),
                          0.9, 0.02)
    shift = (relief - model.reference) * math.tan(math.radians(theta))
    # phi = 0: the camera is towards +x (higher columns), the square moves to lower columns;
    # phi = 90: it is towards +y, the top of the picture (row 0), the square moves down
    for phi, axis, sign in ((0.0, 1, 1), (90.0, 0, -1)):
        out = _render(fields, halo, model, theta, phi, 0, 0)[0, 0, ..., 0]
        bright = np.nonzero(out > 0.3)
        far_edge = bright[axis].min() if sign > 0 else bright[axis].max()
        expected = 16 - shift if sign > 0 else 31 + shift
        assert abs(far_edge - expected) <= 1.0, (phi, far_edge, expected)
        across = bright[1 - axis]
        assert across.min() == 16 and across.max() == 31  # no shift across the view plane


@pytest.mark.parametrize("name", ["wood", "leather", "tiles"])
def test_rendering_does_not_depend_on_the_tiling(name):
    m = Material(name, seed=5)
    s = parse_sampling("hemi:4")
    model = ShadingModel(relief=m.relief)
    halo = model.halo(s.theta_view.max(), s.theta_light.max())

    def tile(y0, x0, ny, nx):
        return _render(m.fields(y0 - halo, x0 - halo, ny + 2 * halo, nx + 2 * halo), halo,
                       model, s.theta_view, s.phi_view, s.theta_light, s.phi_light)

    whole = tile(0, 0, 40, 40)
    parts = np.concatenate([np.concatenate([tile(0, 0, 17, 25), tile(0, 25, 17, 15)], 3),
                            np.concatenate([tile(17, 0, 23, 25), tile(17, 25, 23, 15)], 3)], 2)
    assert np.array_equal(whole, parts)


def test_shadows_kept_for_other_views_give_the_same_bits(monkeypatch):
    """The shadows a block's lights cast are kept for the blocks of other views (one view a
    block, in any order, wider and narrower margins): every layer is what rendering it with
    nothing kept gives, and the cache stays within its limit."""
    from tasks import shading

    m = Material("stone", seed=3)
    s = parse_sampling("dome151")
    model = ShadingModel(relief=m.relief)
    halo = model.halo(s.theta_view.max(), s.theta_light.max())
    fields = m.fields(-halo, -halo, 24 + 2 * halo, 20 + 2 * halo)
    views = np.random.default_rng(4).permutation(len(s.theta_view))[:40]
    lights = slice(60, 72)

    def blocks(cache):
        monkeypatch.setattr(shading, "SHADOWS", cache)
        return [_render(fields, halo, model, s.theta_view[v], s.phi_view[v],
                        s.theta_light[lights], s.phi_light[lights]) for v in views]

    kept = shading.ShadowCache()
    with_cache = blocks(kept)
    assert len(kept.entries) == 12 and 0 < kept.size <= kept.limit
    small = shading.ShadowCache(limit=kept.size // 2)  # some lights' shadows dropped
    again = blocks(small)
    assert 0 < small.size <= small.limit
    none = shading.ShadowCache(limit=0)
    fresh = blocks(none)
    # each light's shadows computed once per wider margin, not once per view
    assert kept.computed < small.computed < none.computed == 12 * len(views)
    for a, b, c in zip(with_cache, again, fresh, strict=True):
        assert np.array_equal(a.view(np.uint32), c.view(np.uint32))
        assert np.array_equal(b.view(np.uint32), c.view(np.uint32))


def test_a_view_kept_for_its_other_lights_gives_the_same_bits(monkeypatch):
    """What a view sees of a strip is kept for the view's other blocks of lights (blocks of
    views and of lights in a shuffled order, two materials in one cache): every layer is what
    rendering it with nothing kept gives, and the cache stays within its limit."""
    from tasks import shading

    s = parse_sampling("dome151")
    cases = []
    for name, seed in (("stone", 3), ("leather", 1)):
        m = Material(name, seed=seed)
        model = ShadingModel(relief=m.relief)
        halo = model.halo(s.theta_view.max(), s.theta_light.max())
        cases.append((m.fields(-halo, -halo, 24 + 2 * halo, 20 + 2 * halo), halo, model))
    views = np.random.default_rng(5).permutation(len(s.theta_view))[:6]
    views[0] = int(np.argmin(s.theta_view))  # the top view, which is not kept
    lights = [slice(a, a + 8) for a in (0, 40, 80, 120)]
    order = [(c, v, lt) for c in range(2) for v in views for lt in range(4)]
    order = [order[i] for i in np.random.default_rng(6).permutation(len(order))]

    def blocks(cache, keyed=False):
        monkeypatch.setattr(shading, "VIEWS", cache)
        out = []
        for c, v, lt in order:
            fields, halo, model = cases[c]
            # keyed: the caller says what the fields are (a stage), so they are not hashed
            out.append(render_block(fields, halo=halo, theta_view=s.theta_view[v:v + 1],
                                    phi_view=s.phi_view[v:v + 1],
                                    theta_light=s.theta_light[lights[lt]],
                                    phi_light=s.phi_light[lights[lt]], model=model,
                                    key=("case", c) if keyed else None))
        return out

    kept = shading.ViewCache()
    with_cache = blocks(kept)
    oblique = 2 * (len(views) - 1)
    assert len(kept.entries) == kept.computed == oblique and 0 < kept.size <= kept.limit
    small = shading.ViewCache(limit=kept.size // 3)  # some views dropped and made again
    again = blocks(small)
    assert 0 < small.size <= small.limit and oblique < small.computed < 4 * oblique
    by_key = shading.ViewCache()
    keyed = blocks(by_key, keyed=True)
    assert by_key.computed == oblique
    none = shading.ViewCache(limit=0)  # VIEWS.limit 0: nothing hashed, nothing kept
    fresh = blocks(none)
    assert none.computed == 0 and not none.entries
    for a, b, k, c in zip(with_cache, again, keyed, fresh, strict=True):
        for x in (a, b, k):
            assert np.array_equal(x.view(np.uint32), c.view(np.uint32))


def test_cast_shadows_darken_low_elevations():
    m = Material("leather", seed=1)
    with_shadows, without = ShadingModel(relief=m.relief), ShadingModel(relief=m.relief,
                                                                        shadows=False)
    halo = with_shadows.halo(0, 80)
    f = m.fields(-halo, -halo, 64 + 2 * halo, 64 + 2 * halo)
    thetas = np.array([10.0, 45.0, 70.0, 80.0])
    lit = _render(f, halo, with_shadows, 0, 0, thetas, np.zeros(4)).mean(axis=(2, 3, 4))[0]
    unlit = _render(f, halo, without, 0, 0, thetas, np.zeros(4)).mean(axis=(2, 3, 4))[0]
    ratio = lit / unlit
    assert ratio[0] > 0.99  # light from near the normal: no cast shadows
    assert ratio[-1] < 0.8  # grazing light: large shadowed areas
    assert np.all(np.diff(ratio) < 0)  # the lower the light, the darker


def test_highlight_is_at_the_mirror_direction():
    m = Material("tiles", seed=0, scale=32)
    model = ShadingModel(relief=m.relief)
    phis = np.arange(0, 360, 30.0)
    halo = model.halo(45, 45)
    f = m.fields(-halo, -halo, 32 + 2 * halo, 32 + 2 * halo)
    out = _render(f, halo, model, 45, 0, np.full(12, 45.0), phis)[0]
    assert phis[np.argmax(out.mean(axis=(1, 2, 3)))] == 180


def test_highlights_move_with_the_light_azimuth():
    # Top view, light 20 degrees from the normal: the brightest texels are those whose normal
    # bisects light and view, i.e. leans about 10 degrees towards the light's azimuth.
    m = Material("leather", seed=2)
    model = ShadingModel(relief=m.relief, shadows=False)
    f = m.fields(-2, -2, 68, 68)
    tops = {}
    for phi in (0.0, 90.0, 180.0, 270.0):
        layer = _render(f, 2, model, 0, 0, 20, phi)[0, 0].sum(axis=-1)
        top = layer > np.percentile(layer, 98)
        rise = facing(f.height, phi)[2:-2, 2:-2]  # slope facing the light
        assert abs(rise.mean()) < 0.05
        assert rise[top].mean() > 0.1
        assert np.mean(rise[top] > 0) > 0.9
        tops[phi] = top
    assert np.mean(tops[0.0] & tops[180.0]) < 0.2 * np.mean(tops[0.0])
    assert np.mean(tops[90.0] & tops[270.0]) < 0.2 * np.mean(tops[90.0])


def test_the_halo_is_enough_for_the_most_grazing_light_and_view():
    # abtf:24,8 has lights 5.6 degrees above the horizon; dome151 views reach 75 degrees.
    m = Material("leather", seed=3)
    model = ShadingModel(relief=m.relief)
    halo = model.halo(75.0, 84.375)
    kw = dict(tv=[0.0, 75.0], pv=[0.0, 200.0], tl=[84.375, 84.375], pl=[0.0, 135.0])
    exact = _render(m.fields(-halo, -halo, 24 + 2 * halo, 24 + 2 * halo), halo, model, **kw)
    wide = halo + 25
    wider = _render(m.fields(-wide, -wide, 24 + 2 * wide, 24 + 2 * wide), wide, model, **kw)
    assert np.array_equal(exact, wider)


def test_a_window_without_enough_halo_is_refused():
    h = np.zeros((20, 20), np.float32)
    with pytest.raises(ValueError, match="texels around"):
        visibility(h, 2, 2, 16, 16, theta=80, phi=0, relief=4.0, penumbra=0.3, max_length=50)


def _numpy_shadow_tops(h, r0, c0, ny, nx, step, steps, rise):
    """The cast-shadow march as whole-array numpy operations (the compiled loop's reference)."""
    top = np.full((ny, nx), -np.inf, np.float32)
    for t in range(1, steps + 1):
        ray = np.float32(t * step.length * rise)
        np.maximum(top, shifted(h, r0, c0, ny, nx, t * step.dy, t * step.dx) - ray, out=top)
    return top


@pytest.mark.parametrize("phi", [0.0, 45.0, 90.0, 180.0, 270.0, 17.3, 133.7, 301.9])
def test_the_compiled_shadow_march_gives_numpy_s_bits(phi):
    """Every branch of the loop (no, one or two fractional offsets) on rough random heights."""
    rng = np.random.default_rng(int(phi * 10))
    h = (rng.random((90, 97)) ** 3 * 12).astype(np.float32)
    h[40:44, 50:52] = 30.0  # a spike far above the rest
    # A DDA step moves a whole texel along one axis; the loop also takes two fractions.
    for step in (dda_step(phi), Step(0.37 + phi / 1000, -0.61, 0.9)):
        for theta in (5.0, 50.0, 84.0):
            rise = math.cos(math.radians(theta)) / math.sin(math.radians(theta))
            got = shadow_tops(h, 22, 23, 41, 47, step, 20, rise)
            want = _numpy_shadow_tops(h, 22, 23, 41, 47, step, 20, rise)
            assert got.dtype == np.float32
            np.testing.assert_array_equal(got, want)


def test_the_compiled_shading_gives_numpy_s_bits_for_every_light():
    """``shade_all`` against ``shade`` light by light, on random surfaces with extreme values:
    roughness near 0 and 1, normals at grazing angles, lights below the horizon.
    """
    rng = np.random.default_rng(7)
    ny, nx = 23, 31
    normal = rng.normal(size=(3, ny, nx)).astype(np.float32)
    normal[2] = np.abs(normal[2]) * np.where(rng.random((ny, nx)) < 0.2, 1e-3, 1.0)
    normal /= np.sqrt((normal * normal).sum(0))
    alpha = rng.choice(np.array([1e-3, 0.05, 0.3, 1.0], np.float32), (ny, nx))
    f0 = rng.random((ny, nx), dtype=np.float32)
    albedo = rng.random((ny, nx, 3), dtype=np.float32) * 2
    theta = np.array([0.0, 10, 45, 80, 89.9, 95, 120])
    phi = np.array([0.0, 33, 90, 181, 270, 359, 12])
    lights = direction_vectors(theta, phi)
    vis = rng.random((len(lights), ny, nx), dtype=np.float32)
    vis[:, :4] = 0.0
    for view in direction_vectors(np.array([0.0, 60.0, 85.0]), np.array([0.0, 200.0, 47.0])):
        surface = Surface.seen_from(tuple(normal), albedo, alpha, f0, view)
        got = shade_all(surface, vis, lights, ambient=0.04,
                        out=np.empty((len(lights), ny, nx, 3), np.float32))
        for il, light in enumerate(lights):
            np.testing.assert_array_equal(got[il], shade(surface, vis[il], light, ambient=0.04))


def test_the_compiled_resampling_gives_numpy_s_bits_for_every_layer():
    """``bilinear_layers`` against ``bilinear`` layer by layer: offsets of both signs, whole
    texels, and channels-last fields (albedo) as they are resampled.
    """
    rng = np.random.default_rng(11)
    a = (rng.random((5, 40, 44)) * 3 - 1).astype(np.float32)
    oy = (rng.random((20, 23)) * 12 - 6).astype(np.float32)
    ox = (rng.random((20, 23)) * 12 - 6).astype(np.float32)
    oy[::3] = np.round(oy[::3])
    ox[:, ::4] = 0.0
    got = bilinear_layers(a, 9, 10, oy, ox)
    for k in range(len(a)):
        np.testing.assert_array_equal(got[k], bilinear(a[k], 9, 10, oy, ox))
    albedo = np.moveaxis(a[:3], 0, -1)
    np.testing.assert_array_equal(np.moveaxis(bilinear_layers(a[:3], 9, 10, oy, ox), 0, -1),
                                  bilinear(albedo, 9, 10, oy, ox))
