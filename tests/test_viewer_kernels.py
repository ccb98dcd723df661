"""``tasks.viewer``: the blending mesh, the sphere's replica and the page's plan, in numpy.

The page (pipeline/templates/view.html) mirrors these; tests/test_view.py compares the two in
chromium.
"""

from __future__ import annotations

import numpy as np
import pytest

from tasks.sampling import parse_sampling
from tasks.viewer import (
    _barycentric,
    blend_weights,
    block_means,
    cell_triangles,
    disk,
    locate,
    mesh,
    page_bytes,
    plan_page,
    shown_rank,
    sphere_at,
    triangulate,
)

# a dome, the UBO2003 hemisphere, and lights on one side only (the hull misses the normal)
SAMPLINGS = {
    "dome151": (parse_sampling("dome151").theta_light, parse_sampling("dome151").phi_light),
    "ubo2003": (parse_sampling("ubo2003").theta_light, parse_sampling("ubo2003").phi_light),
    "one side": (np.array([20.0, 40.0, 60.0, 40.0, 60.0, 75.0, 75.0]),
                 np.array([0.0, 20.0, 40.0, -20.0, -40.0, 10.0, -10.0]) % 360),
}


def _dense(m, at, n) -> np.ndarray:
    labels, weights = locate(m, at)
    out = np.zeros((len(at), n))
    for i in range(3):
        np.add.at(out, (np.arange(len(at)), labels[:, i]), weights[:, i])
    return out


def test_blend_weights_pick_one_measured_pair_and_two_along_an_edge():
    rng = np.random.default_rng(7)
    theta, phi = rng.uniform(0, 80, 30), rng.uniform(0, 360, 30)
    m, points, tris = mesh(theta, phi, "light"), disk(theta, phi), triangulate(theta, phi, "l")
    for i in range(30):
        assert blend_weights(m, points[i]) == [(i, 1.0)]
    for a, b in {(t[0], t[1]) for t in tris}:
        w = dict(blend_weights(m, (points[a] + points[b]) / 2))
        assert set(w) == {a, b} and w[a] == pytest.approx(0.5) and w[b] == pytest.approx(0.5)
    for at in rng.uniform(-1, 1, (200, 2)):  # inside or outside the hull: a convex blend
        w = blend_weights(m, at)
        assert all(x > 0 for _, x in w) and sum(x for _, x in w) == pytest.approx(1.0)
    one = mesh([0.0], [0.0], "view")
    assert blend_weights(one, (0.3, 0.1)) == [(0, 1.0)]


@pytest.mark.parametrize("name", sorted(SAMPLINGS))
def test_the_blend_covers_the_disk_and_is_continuous_past_the_last_ring(name):
    """Every point of the unit disk lies in a triangle of the mesh (ghosts included), so the
    weights change by no more than their slope allows between neighbouring points, on circles
    inside the hull and beyond its last ring (where the nearest triangle's clipped weights
    jumped by up to 0.99 of the whole weight from one point to the next, and the grid's
    triangle by 0.19 inside it)."""
    theta, phi = SAMPLINGS[name]
    m = mesh(theta, phi, "light")
    rng = np.random.default_rng(1)
    r, a = np.sqrt(rng.uniform(0, 1, 5000)), rng.uniform(0, 2 * np.pi, 5000)
    at = np.stack([r * np.cos(a), r * np.sin(a)], -1)
    assert _barycentric(m.points, m.triangles, at).min(-1).max(1).min() > -1e-12
    inside = disk(theta, phi)
    for radius in (0.9, 0.975, 0.9999):
        t = np.linspace(0, 2 * np.pi, 8001)
        w = _dense(m, np.stack([radius * np.cos(t), radius * np.sin(t)], -1), len(inside))
        step = np.abs(np.diff(w, axis=0)).sum(1).max()
        assert step < 0.05, (name, radius, step)  # a step of 8e-4 on the disk
    # beyond the hull, on a ghost's ray: that hull vertex alone
    centre = np.zeros(2) if name != "one side" else None
    if centre is not None:
        outer = np.argmax(np.hypot(*inside.T))
        beyond = inside[outer] / np.linalg.norm(inside[outer]) * 0.999
        assert blend_weights(m, beyond) == [(int(outer), 1.0)]


@pytest.mark.parametrize("name", sorted(SAMPLINGS))
def test_every_cell_lists_the_triangle_that_holds_its_points(name):
    theta, phi = SAMPLINGS[name]
    m = mesh(theta, phi, "light")
    spans, items = cell_triangles(m, 128)
    rng = np.random.default_rng(2)
    r, a = np.sqrt(rng.uniform(0, 1, 5000)), rng.uniform(0, 2 * np.pi, 5000)
    at = np.stack([r * np.cos(a), r * np.sin(a)], -1)
    best = np.argmax(_barycentric(m.points, m.triangles, at).min(-1), axis=1)
    for p, t in zip(at, best, strict=True):
        for dx in (-1e-5, 0.0, 1e-5):  # a float32 lookup may round into the next cell
            x, y = np.clip(((p + dx) * 0.5 + 0.5) * 128, 0, 127).astype(int)
            first, count = spans[y, x]
            assert t in items[first:first + count]
    assert spans[..., 1].max() <= 32  # a short list a cell


def test_the_sphere_map_is_conformal_with_no_pole_on_the_visible_hemisphere():
    """The page's texture map (stereographic from the back pole): at every point of the
    visible hemisphere, where the poles of a longitude/latitude map were too, a texel is a
    square on the sphere (the texture's derivatives along the surface are orthogonal and of
    one length); longitude/latitude pinches it to nothing towards its poles."""
    rng = np.random.default_rng(4)
    r, a = np.sqrt(rng.uniform(0, 0.995**2, 2000)), rng.uniform(0, 2 * np.pi, 2000)
    q = np.stack([r * np.cos(a), r * np.sin(a)], -1)
    q[:200] = np.stack([rng.uniform(-0.1, 0.1, 200), rng.choice([-0.99, 0.99], 200)], -1)
    h = 1e-6

    def lift(p):  # screen -> sphere point, texture coordinates
        n = np.concatenate([p, np.sqrt(1 - (p**2).sum(-1, keepdims=True))], -1)
        return n, sphere_at(p, (0.0, 0.0)).texture

    n0, s0 = lift(q)
    worst, lonlat = 1.0, 1.0
    for i in range(len(q)):
        jac_n, jac_s, jac_l = [], [], []
        for d in (np.array([h, 0.0]), np.array([0.0, h])):
            n1, s1 = lift(q[i:i + 1] + d)
            jac_n.append(n1[0] - n0[i])
            jac_s.append(s1[0] - s0[i])
            lon = lambda n: np.arctan2(n[0], n[2])  # noqa: E731
            jac_l.append([lon(n1[0]) - lon(n0[i]), np.arccos(n1[0][1]) - np.arccos(n0[i][1])])
        # texture change per unit of surface along an orthonormal basis of the tangent plane
        basis, _ = np.linalg.qr(np.array(jac_n).T)
        to_surface = np.linalg.pinv(basis.T @ np.array(jac_n).T)
        for jac, keep in ((jac_s, "ours"), (jac_l, "lonlat")):
            sv = np.linalg.svd(np.array(jac).T @ to_surface, compute_uv=False)
            if keep == "ours":
                worst = max(worst, sv[0] / sv[1])
            else:
                lonlat = max(lonlat, sv[0] / sv[1])
    assert worst < 1.001, worst
    assert lonlat > 5  # what a longitude/latitude map does near its poles
    centre = sphere_at(np.zeros((1, 2)), (50.0, 90.0))
    assert np.allclose(centre.texture, 0.5)  # the middle of the texture at the centre
    assert centre.light[0, 1] > 0.7 and abs(centre.light[0, 0]) < 1e-9  # lit from +y: the top


def test_the_default_rank_keeps_the_energy_within_the_shader_limit():
    s = np.array([100.0, 10.0, 3.0, 1.0, 0.3, 0.1])
    total = float((s**2).sum()) / 0.99999  # the store itself left out 0.001%
    assert shown_rank(s, total, most=64) == 4  # 100^2 + 10^2 + 3^2 + 1 >= 99.99%
    assert shown_rank(s, total, most=3) == 3
    assert shown_rank(s, total, most=64, share=0.9999999) == 6  # out of reach: all stored


def test_a_page_plan_takes_a_coarser_level_before_fewer_than_the_least_components():
    size = lambda level: ((512 >> level) ** 2, 0)  # noqa: E731
    rows, fixed = 151 * 151 * 3, 100_000
    budget = 25 << 20
    level, k = plan_page(size, rows=rows, fixed=fixed, budget=budget, wanted=64, least=8)
    assert page_bytes(size(level)[0], k, rows, fixed) <= budget
    assert page_bytes(size(level)[0], k + 1, rows, fixed) > budget or k == 64
    assert level == 0 and k >= 8
    assert plan_page(size, rows=rows, fixed=fixed, budget=20 << 20, wanted=64, least=64) is None
    level, k = plan_page(lambda lv: ((2048 >> lv) ** 2, 0), rows=rows, fixed=fixed,
                         budget=budget, wanted=40, least=8)
    assert level >= 1 and k >= 8
    assert plan_page(size, rows=rows, fixed=fixed, budget=budget, wanted=8, least=8,
                     levels=[0]) == (0, 8)


def test_block_means_keep_the_partial_blocks_at_the_ends():
    a = np.arange(5 * 7 * 2, dtype=np.float32).reshape(5, 7, 2)
    m = block_means(a, 2)
    assert m.shape == (3, 4, 2)
    assert np.allclose(m[0, 0], a[:2, :2].mean((0, 1)))
    assert np.allclose(m[2, 3], a[4:, 6:].mean((0, 1)))
    assert np.allclose(m[1, 3], a[2:4, 6:].mean((0, 1)))
