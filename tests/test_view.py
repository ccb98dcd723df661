"""``btf view``: the relighting page, its blending rule, its errors, and the page in chromium.

The browser tests run Debian's chromium headless with WebGL2 on SwiftShader, driven by
playwright; they skip where there is no chromium (``.ci/run`` installs it and sets
BTF_REQUIRE_BROWSER, so there they fail instead).
"""

from __future__ import annotations

import base64

import numpy as np
import pytest
import zarr

from benchmarks.harness import BROWSER_FLAGS
from helpers import chromium, generate_store, no_partial_outputs
from tasks.svd import reconstruct_layers
from tasks.tonemap import to_uint8, tonemap
from tasks.transform import Transform
from tasks.viewer import SNAP, blend_weights, disk, pack_eigentextures, triangle_grid, triangulate

HEIGHT, WIDTH, RANK = 40, 56, 8  # not square: rows and columns cannot be swapped unseen
# Half-float eigentextures and float32 arithmetic on the GPU against float32 numpy: at most
# this many 8-bit display steps apart at a measured pair (measured: 1).
BOUND = 2


@pytest.fixture(scope="module")
def compressed(tmp_path_factory):
    from pipeline.cli import main

    root = tmp_path_factory.mktemp("view")
    m = generate_store(root / "m.zarr", "--material", "leather", "--size", "56",
                       "--sampling", "hemi:9", "--seed", "2", "--chunk", "16")
    assert main(["crop", str(m), str(root / "r.zarr"), "--region", f"0:{HEIGHT},0:{WIDTH}",
                 "-q"]) == 0
    assert main(["compress", str(root / "r.zarr"), str(root / "c.zarr"), "--rank", "12",
                 "-q"]) == 0
    return root / "c.zarr"


@pytest.fixture(scope="module")
def page(compressed):
    from pipeline.cli import main

    out = compressed.parent / "v.html"
    assert main(["view", str(compressed), str(out), "--rank", str(RANK), "-q"]) == 0
    return out


def _expected(group, view: int, light: int, scale: float, *, halves: bool = False):
    u, s, v = group["U"][..., :RANK], group["S"][:RANK], group["V"][..., :RANK]
    if halves:
        v = v.astype(np.float16).astype(np.float32)
    layer = reconstruct_layers(u[view, light][None], s, v,
                               transform=Transform.from_attrs(group.attrs["transform"]))[0]
    return to_uint8(tonemap(layer, scale=scale))


def test_blend_weights_pick_one_measured_pair_and_two_along_an_edge():
    rng = np.random.default_rng(7)
    theta, phi = rng.uniform(0, 80, 30), rng.uniform(0, 360, 30)
    points, tris = disk(theta, phi), triangulate(theta, phi, "light")
    for i in range(30):
        assert blend_weights(points, tris, points[i]) == [(i, 1.0)]
    for a, b in {(t[0], t[1]) for t in tris}:
        w = dict(blend_weights(points, tris, (points[a] + points[b]) / 2))
        assert set(w) == {a, b} and w[a] == pytest.approx(0.5) and w[b] == pytest.approx(0.5)
    for at in rng.uniform(-1, 1, (200, 2)):  # inside or outside the hull: a convex blend
        w = blend_weights(points, tris, at)
        assert all(x > 0 for _, x in w) and sum(x for _, x in w) == pytest.approx(1.0)
    assert blend_weights(disk([0.0], [0.0]), triangulate([0.0], [0.0], "view"), (0.3, 0.1)) \
        == [(0, 1.0)]


def test_directions_on_a_line_and_too_few_cannot_be_triangulated():
    with pytest.raises(ValueError, match="2 light direction"):
        triangulate(np.array([10.0, 20.0]), np.array([0.0, 0.0]), "light")
    with pytest.raises(ValueError, match="one line"):
        triangulate(np.array([10.0, 20.0, 30.0]), np.array([0.0, 0.0, 0.0]), "light")


def test_eigentextures_pack_as_half_float_layers_of_four():
    v = np.random.default_rng(1).normal(size=(3, 5, 6)).astype(np.float32)
    packed = pack_eigentextures(v)
    assert packed.shape == (2, 3, 5, 4) and packed.dtype == np.uint16
    back = packed.view(np.float16).astype(np.float32).transpose(1, 2, 0, 3).reshape(3, 5, 8)
    assert np.array_equal(back[..., :6], v.astype(np.float16).astype(np.float32))
    assert not back[..., 6:].any()


def test_bad_inputs_are_one_clear_error_and_nothing_is_written(compressed, btf, tmp_path):
    out = tmp_path / "v.html"
    assert btf("view", compressed, out, "--rank", "65").code == 2  # a usage error
    over = btf("view", compressed, out, "--rank", "13")
    assert over.code == 1 and "--rank 13 is larger than the store's rank 12" in over.err
    big = btf("view", compressed, out, "--budget", "0.01")
    assert big.code == 1 and "over --budget 0.01 MB" in big.err and "--level 1" in big.err
    other = tmp_path / "other.zarr"
    zarr.open_group(other, mode="w").attrs["btf_kind"] = "surface"
    kind = btf("view", other, out)
    assert kind.code == 1 and "this is a surface store" in kind.err
    one = tmp_path / "one.zarr"
    assert btf("crop", compressed.parent / "r.zarr", tmp_path / "one_r.zarr", "--light", "0",
               "-q").code == 0
    assert btf("compress", tmp_path / "one_r.zarr", one, "--rank", "4", "-q").code == 0
    single = btf("view", one, out)
    assert single.code == 1 and "1 light direction cannot be triangulated" in single.err
    line = tmp_path / "line.zarr"
    assert btf("crop", compressed.parent / "r.zarr", tmp_path / "line_r.zarr", "--light",
               "0,1", "-q").code == 0
    assert btf("compress", tmp_path / "line_r.zarr", line, "--rank", "4", "-q").code == 0
    two = btf("view", line, out)
    assert two.code == 1 and "2 light direction(s) cannot be triangulated" in two.err
    assert btf("view", compressed, out, "--exposure", "-1").code == 2
    assert no_partial_outputs(out) and not out.exists()
    out.write_text("kept")
    there = btf("view", compressed, out)
    assert there.code == 1 and "already exists; pass --overwrite" in there.err
    assert out.read_text() == "kept"


def _blobs(page) -> dict[str, str]:
    text = page.read_text()
    return {name: text.split(f'id="blob-{name}">')[1].split("</script>")[0] for name in ("V", "US")}


def test_a_radiance_store_is_compressed_on_the_way_as_btf_compress_would(compressed, btf,
                                                                         tmp_path):
    radiance = compressed.parent / "r.zarr"
    assert btf("compress", radiance, tmp_path / "c8.zarr", "--rank", "8", "-q").code == 0
    assert btf("view", tmp_path / "c8.zarr", tmp_path / "a.html", "-q").code == 0
    r = btf("view", radiance, tmp_path / "b.html", "--rank", "8")
    assert r.code == 0 and "compressing it at rank 8 first" in r.err, r.err
    assert _blobs(tmp_path / "a.html") == _blobs(tmp_path / "b.html")
    assert '"name": "r.zarr"' in (tmp_path / "b.html").read_text()
    big = btf("view", radiance, tmp_path / "c.html", "--budget", "0.01")
    assert big.code == 1 and "over --budget" in big.err and "compressing" not in big.err


def test_a_level_and_a_region_are_shown_and_said(compressed, btf, tmp_path):
    r = btf("view", compressed, tmp_path / "v.html", "--level", "1", "--region", "4:40,0:51")
    assert r.code == 0, r.err
    assert "18 x 25 texels" in r.err and "at level 1" in r.err
    html = (tmp_path / "v.html").read_text()
    assert '"width": 25, "height": 18' in html and "block means of 2^2" in html


@pytest.fixture(scope="module")
def browser():
    exe = chromium()
    sync_api = pytest.importorskip("playwright.sync_api")
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=exe, args=BROWSER_FLAGS)
        yield b
        b.close()


def _open(browser, page_path, fragment: str = ""):
    """The page in a new tab with every request outside the file refused; and its requests."""
    tab = browser.new_page()
    errors, requests = [], []
    tab.on("pageerror", lambda e: errors.append(str(e)))
    tab.on("request", lambda r: requests.append(r.url))
    tab.route("**/*", lambda route: route.continue_() if route.request.url.startswith(
        page_path.as_uri()) else route.abort())
    tab.goto(page_path.as_uri() + fragment)
    tab.wait_for_function("window.btfView !== undefined")
    assert not errors and "error" not in tab.evaluate("Object.keys(window.btfView)"), errors
    return tab, requests


# The canvas's RGBA bytes as base64: playwright's JSON of a 384^2 canvas as a list of numbers
# takes about 5 s, this 0.1 s.
_PIXELS_BASE64 = """() => {
  const p = window.btfView.pixels();
  let s = "";
  for (let i = 0; i < p.length; i += 0x8000) s += String.fromCharCode(...p.slice(i, i + 0x8000));
  return btoa(s);
}"""


def _pixels(tab) -> np.ndarray:
    """``window.btfView.pixels()``: RGBA bytes, bottom row first."""
    return np.frombuffer(base64.b64decode(tab.evaluate(_PIXELS_BASE64)), np.uint8)


def _canvas(tab) -> np.ndarray:
    flat = _pixels(tab)
    return flat.reshape(HEIGHT, WIDTH, 4)[::-1, :, :3]  # GL rows run bottom-up


def test_at_measured_pairs_the_canvas_is_btf_reconstruct_tone_mapped(browser, page,
                                                                     compressed):
    g = zarr.open_group(compressed, mode="r")
    tv, pv, tl, pl = (g[n][...] for n in ("theta_view", "phi_view", "theta_light", "phi_light"))
    tab, requests = _open(browser, page)
    assert {u for u in requests} == {page.as_uri()}  # nothing from the network
    scale = tab.evaluate("window.btfView.state.exposure")
    worst = 0
    for view, light in [(0, 0), (3, 7), (8, 2), (5, 5)]:
        tab.evaluate(f"window.btfView.set([{tl[light]}, {pl[light]}], [{tv[view]}, {pv[view]}])")
        got = _canvas(tab).astype(int)
        exact = _expected(g, view, light, scale).astype(int)
        worst = max(worst, int(np.abs(got - exact).max()))
        assert np.abs(got - _expected(g, view, light, scale, halves=True)).max() <= 1
        assert exact.std() > 5  # a texture, not a flat field
    assert worst <= BOUND, worst
    tab.close()


def test_between_two_measured_lights_the_canvas_lies_between_them(browser, page, compressed):
    g = zarr.open_group(compressed, mode="r")
    tl, pl = g["theta_light"][...], g["phi_light"][...]
    tris = triangulate(tl, pl, "light")
    points = disk(tl, pl)
    a, b = (int(i) for i in tris[0][:2])
    x, y = (points[a] + points[b]) / 2
    theta, phi = np.degrees(np.arcsin(np.hypot(x, y))), np.degrees(np.arctan2(y, x)) % 360
    view = int(np.argmin(g["theta_view"][...]))
    tv, pv = g["theta_view"][view], g["phi_view"][view]
    tab, _ = _open(browser, page)
    scale = tab.evaluate("window.btfView.state.exposure")
    tab.evaluate(f"window.btfView.set([{theta}, {phi}], [{tv}, {pv}])")
    mid = _canvas(tab).astype(int)
    one, two = (_expected(g, view, i, scale).astype(int) for i in (a, b))
    low, high = np.minimum(one, two), np.maximum(one, two)
    assert (mid >= low - BOUND).all() and (mid <= high + BOUND).all()
    assert (np.abs(mid - one) > BOUND).any() and (np.abs(mid - two) > BOUND).any()
    u, s_, v = g["U"][..., :RANK], g["S"][:RANK], g["V"][..., :RANK]
    half = reconstruct_layers(((u[view, a] + u[view, b]) / 2)[None], s_, v,
                              transform=Transform.from_attrs(g.attrs["transform"]))[0]
    assert np.abs(mid - to_uint8(tonemap(half, scale=scale))).max() <= BOUND  # 0.5 and 0.5
    # the page's blending rule is tasks.viewer's, point for point, inside and outside the hull
    rng = np.random.default_rng(3)
    for at in rng.uniform(-1, 1, (100, 2)):
        js = tab.evaluate(f"blendWeights(DATA.lightDisk, DATA.lightTriangles, [{at[0]}, {at[1]}])")
        py = blend_weights(points, tris, at)
        assert [i for i, _ in js] == [i for i, _ in py], at
        assert np.allclose([x for _, x in js], [x for _, x in py], atol=1e-9), at
    tab.close()


def test_the_url_sets_the_directions_and_dragging_the_light_changes_the_image(browser, page):
    tab, _ = _open(browser, page, "#light=40,90&view=10,0&exposure=1.5")
    state = tab.evaluate("window.btfView.state")
    assert state["light"] == [40, 90] and state["view"] == [10, 0] and state["exposure"] == 1.5
    before = _canvas(tab)
    box = tab.locator("#light").bounding_box()
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    tab.mouse.move(cx, cy)
    tab.mouse.down()
    tab.mouse.move(cx + 40, cy - 10, steps=5)
    tab.mouse.up()
    tab.wait_for_function("window.btfView.state.light[0] > 20 && window.btfView.state.light[0]"
                          " < 60 && window.btfView.state.light[1] < 30")
    tab.wait_for_timeout(100)  # the frame the drag asked for
    assert np.abs(_canvas(tab).astype(int) - before.astype(int)).max() > 10
    assert "light=" in tab.evaluate("location.hash")
    tab.close()


SPHERE, GRID, LIGHT_DISTANCE = 384, 128, 4  # as the page (pipeline/templates/view.html)


def _grid_blend(points, tris, grid, at):
    """The page's surface-mode blend: the grid cell's triangle, barycentric weights, or None
    where ``at`` is so close to a cell border that float32 may pick the other cell."""
    cell = (np.asarray(at) * 0.5 + 0.5) * GRID
    if np.any(np.abs(cell - np.round(cell)) < 1e-3):
        return None
    if len(tris) == 0:
        return [(0, 1.0)]
    x, y = np.clip(cell.astype(int), 0, GRID - 1)
    tri = tris[grid[y, x]]
    a, b, c = points[tri]
    wb, wc = np.linalg.solve(np.array([b - a, c - a]).T, np.asarray(at) - a)
    w = np.array([1 - wb - wc, wb, wc])
    w = np.where(w > SNAP, w, 0.0)
    return list(zip(tri.tolist(), (w / w.sum()).tolist(), strict=True))


def _sphere_pixel(g, px: int, py: int, light, repeat: float, scale: float):
    """What the sphere shows at pixel (px, py) (GL rows: from the bottom), or None if the
    pixel sits on a border a float32 computation may round either way."""
    q = (np.array([px, py]) + 0.5) / SPHERE * 2 - 1
    n = np.array([q[0], q[1], np.sqrt(max(1 - q @ q, 0.0))])
    t = np.array([n[2] + 1e-7, 0.0, -n[0]])
    t /= np.linalg.norm(t)
    bt = np.cross(n, t)
    th, ph = np.radians(light)
    lw = LIGHT_DISTANCE * np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph),
                                    np.cos(th)]) - n
    lw /= np.linalg.norm(lw)
    local_l = np.array([lw @ t, lw @ bt, lw @ n])
    if local_l[2] <= 0.01:
        return None
    tv, pv, tl, pl = (g[k][...] for k in ("theta_view", "phi_view", "theta_light", "phi_light"))
    weights = []
    for (theta, phi), at in (((tv, pv), np.array([t[2], bt[2]])), ((tl, pl), local_l[:2])):
        tris = triangulate(theta, phi, "direction")
        points = disk(theta, phi)
        weights.append(_grid_blend(points, tris, triangle_grid(points, tris, GRID), at))
    if None in weights:
        return None
    u = np.arctan2(n[0], n[2]) / (2 * np.pi) + 0.5
    h = np.arccos(np.clip(n[1], -1, 1)) / np.pi
    fx, fy = (u * repeat) % 1 * WIDTH, (h * repeat * 0.5) % 1 * HEIGHT
    if min(abs(fx - round(fx)), abs(fy - round(fy))) < 1e-2:
        return None
    v = g["V"][int(fy), int(fx), :RANK].astype(np.float16).astype(np.float32)
    us = g["U"][..., :RANK] * g["S"][:RANK]
    coef = sum(wv * wl * us[i, j].astype(np.float64) for i, wv in weights[0]
               for j, wl in weights[1])
    values = (coef @ v).astype(np.float32)
    radiance = Transform.from_attrs(g.attrs["transform"]).decode(values[None])[0]
    return to_uint8(tonemap(radiance, scale=scale))


def test_the_sphere_gives_every_pixel_its_own_light_view_and_texel(browser, page, compressed):
    g = zarr.open_group(compressed, mode="r")
    tab, _ = _open(browser, page, "#light=45,135&view=0,0&mode=1&repeat=3")
    state = tab.evaluate("window.btfView.state")
    assert state["mode"] == "sphere" and state["repeat"] == 3
    shown = _pixels(tab).reshape(
        SPHERE, SPHERE, 4)[..., :3].astype(int)  # GL rows: bottom first
    rng = np.random.default_rng(5)
    checked, worst = 0, 0
    while checked < 60:
        px, py = rng.integers(0, SPHERE, 2)
        if ((np.array([px, py]) + 0.5) / SPHERE * 2 - 1) @ (
                (np.array([px, py]) + 0.5) / SPHERE * 2 - 1) >= 0.98:
            continue
        want = _sphere_pixel(g, int(px), int(py), (45, 135), 3, state["exposure"])
        if want is None:
            continue
        worst = max(worst, int(np.abs(shown[py, px] - want).max()))
        checked += 1
    assert worst <= BOUND, worst
    lit, dark = shown[SPHERE * 3 // 4, SPHERE // 4], shown[SPHERE // 4, SPHERE * 3 // 4]
    assert lit.sum() > 60 and dark.sum() == 0  # facing the light (upper left) / turned away
    assert (shown[0, 0] == [29, 31, 33]).all()  # outside the sphere: the background
    tab.close()


def test_a_tile_set_is_laid_as_btf_render_lays_it_and_wraps_round_the_sphere(browser,
                                                                             compressed, btf):
    from pipeline.cli import main
    from pipeline.stores.tileset import stored_seed, tile_eigentextures
    from tasks.placement import cell_tiles, gather

    q, page = compressed.parent / "q.zarr", compressed.parent / "q.html"
    assert main(["quilt", str(compressed), str(q), "--corners", "2", "--seed", "1", "-q"]) == 0
    assert main(["view", str(q), str(page), "--rank", str(RANK), "-q"]) == 0
    big = btf("view", q, compressed.parent / "big.html", "--budget", "0.01")
    assert big.code == 1 and "lower --rank, or raise --budget" in big.err  # not --level
    g = zarr.open_group(q, mode="r")
    tiles = tile_eigentextures(g, range(g["corners"].shape[0]), RANK)
    ty, tx = tiles.shape[1:3]
    cells = max(1, min(4, 512 // max(ty, tx)))
    seed = stored_seed(g)
    tab, _ = _open(browser, page)
    ids = cell_tiles(0, 0, cells, cells, seed=seed, corners=2)
    assert tab.evaluate("window.btfView.swatchMap") == ids.ravel().tolist()
    assert len(set(ids.ravel().tolist())) > 1  # several variations laid
    tv, pv, tl, pl = (g[n][...] for n in ("theta_view", "phi_view", "theta_light", "phi_light"))
    tab.evaluate(f"window.btfView.set([{tl[7]}, {pl[7]}], [{tv[3]}, {pv[3]}])")
    shown = _pixels(tab).reshape(
        cells * ty, cells * tx, 4)[::-1, :, :3].astype(int)
    mosaic = gather(tiles.astype(np.float16).astype(np.float32), 0, 0, cells * ty, cells * tx,
                    seed=seed, corners=2)
    layer = reconstruct_layers(g["U"][3, 7, :, :RANK][None], g["S"][:RANK], mosaic,
                               transform=Transform.from_attrs(g.attrs["transform"]))[0]
    scale = tab.evaluate("window.btfView.state.exposure")
    assert np.abs(shown - to_uint8(tonemap(layer, scale=scale))).max() <= 1
    tab.evaluate("window.btfView.set(null, null, null, 'sphere')")
    ball = _pixels(tab).reshape(
        SPHERE, SPHERE, 4)[..., :3]
    assert ball[SPHERE // 2, SPHERE // 2].sum() > 0
    tab.close()


def test_a_roller_tile_set_is_laid_on_its_lattice_as_btf_render_lays_it(browser, tmp_path):
    from pipeline.cli import main
    from pipeline.stores.tileset import stored_seed, tile_eigentextures
    from tasks.placement import lattice_gather

    t = generate_store(tmp_path / "t.zarr", "--material", "tiles", "--size", "96", "--scale",
                       "24", "--sampling", "hemi:9", "--seed", "1")
    for args in (["compress", t, tmp_path / "c.zarr", "--rank", "8"],
                 ["roller", tmp_path / "c.zarr", tmp_path / "r.zarr", "--tiles", "2",
                  "--seed", "2"],
                 ["view", tmp_path / "r.zarr", tmp_path / "r.html"]):
        assert main([str(a) for a in args] + ["-q"]) == 0, args
    g = zarr.open_group(tmp_path / "r.zarr", mode="r")
    spec = g.attrs["lattice"]
    tab, _ = _open(browser, tmp_path / "r.html")
    w, h = (tab.evaluate(f"DATA.{k}") for k in ("width", "height"))
    tv, pv, tl, pl = (g[n][...] for n in ("theta_view", "phi_view", "theta_light", "phi_light"))
    tab.evaluate(f"window.btfView.set([{tl[5]}, {pl[5]}], [{tv[2]}, {pv[2]}])")
    shown = _pixels(tab).reshape(
        h, w, 4)[::-1, :, :3].astype(int)
    rep = g["representative"][...] if "representative" in g.array_keys() else None
    tiles = tile_eigentextures(g, range(g["corners"].shape[0]))
    mosaic = lattice_gather(tiles.astype(np.float16).astype(np.float32), 0, 0, h, w,
                            hnf=tuple(spec["hnf"]), basis=(tuple(spec["U"]), tuple(spec["V"])),
                            representative=rep, seed=stored_seed(g))
    layer = reconstruct_layers(g["U"][2, 5][None], g["S"][...], mosaic,
                               transform=Transform.from_attrs(g.attrs["transform"]))[0]
    scale = tab.evaluate("window.btfView.state.exposure")
    assert np.abs(shown - to_uint8(tonemap(layer, scale=scale))).max() <= 1
    hh, ww, shear = spec["hnf"]
    assert h % (hh * ww // np.gcd(shear, ww)) == 0 and w % ww == 0  # whole periods both ways
    tab.close()


BONN_VIEWS = [(0.0, 0.0), (0.3, 1.2), (0.6, -2.0)]  # radians, as Bonn's files store them
BONN_LIGHTS = [(0.0, 0.0), (0.5, 0.4), (0.9, 3.0), (1.1, -1.5)]


def _bonn_factors(rng, model: int, texels: int):
    """Per-channel U and S x V of clearly coloured texels: a log luminance about -1 and, for
    the YUV models, chroma large enough that a wrong YUV matrix shows (model 10 keeps its
    chroma as log magnitudes above log eps)."""
    rows = len(BONN_VIEWS) * len(BONN_LIGHTS)
    chroma = {9: 0.15, 10: 10.0, 11: 0.4}.get(model)
    u, sxv = [], []
    for c in range(3):
        uc, vc = rng.normal(size=(rows, 2)) * 0.1, rng.normal(size=(texels, 2)) * 0.5
        vc[:, 0] = 1.0
        if chroma is None or c == 0:
            uc[:, 0] += -1.0 if model == 12 or (c == 0 and chroma) else 0.5
        else:
            uc[:, 0] += chroma * (1 if c == 1 else -1)
        u.append(uc)
        sxv.append(vc)
    return u, sxv


@pytest.mark.parametrize("model", [3, 9, 10, 11, 12])
def test_a_bonn_file_shows_what_bonns_reader_decodes(browser, tmp_path, model):
    """Data the viewer was not made on: a DFMF file of each kind of colour model, ingested
    (the YUV models are decoded by the shader), against the decoding of Bonn's own reader."""
    from dfmf_files import reference_decode, write_dfmf

    from pipeline.cli import main

    w, h = 13, 9
    u, sxv = _bonn_factors(np.random.default_rng(model), model, w * h)
    kw = {"color_matrix": np.array([[0.9, 0.1, 0.05], [0.2, 0.7, -0.1], [0.0, 0.3, 1.1]]),
          "color_mean": (0.2, 0.3, 0.25)} if model == 3 else {}
    write_dfmf(tmp_path / "f.btf", views=BONN_VIEWS, lights=BONN_LIGHTS, u=u, sxv=sxv,
               width=w, height=h, color_model=model, scalar_size=4, **kw)
    for args in (["ingest", tmp_path / "f.btf", tmp_path / "f.zarr"],
                 ["view", tmp_path / "f.zarr", tmp_path / "f.html"]):
        assert main([str(a) for a in args] + ["-q"]) == 0, args
    bonn = np.maximum(reference_decode(u, sxv, color_model=model, width=w, height=h,
                                       lights=BONN_LIGHTS, **kw), 0)
    tab, _ = _open(browser, tmp_path / "f.html")
    scale = tab.evaluate("window.btfView.state.exposure")
    g = zarr.open_group(tmp_path / "f.zarr", mode="r")
    tv, pv, tl, pl = (g[n][...] for n in ("theta_view", "phi_view", "theta_light", "phi_light"))
    for view, light in [(0, 0), (1, 2), (2, 3)]:
        tab.evaluate(f"window.btfView.set([{tl[light]}, {pl[light]}], [{tv[view]}, {pv[view]}])")
        shown = _pixels(tab).reshape(
            h, w, 4)[::-1, :, :3].astype(int)
        want = to_uint8(tonemap(bonn[view, light].astype(np.float32), scale=scale)).astype(int)
        assert np.abs(shown - want).max() <= BOUND, (model, view, light)
        assert np.ptp(want, axis=-1).mean() > 10  # coloured: the channels differ
    tab.close()


@pytest.mark.slow
def test_btf_bench_view_reports_its_table(tmp_path):
    import json

    from helpers import btf_process

    chromium()
    pytest.importorskip("playwright.sync_api")
    out = tmp_path / "view.json"  # a process of its own: playwright's sync API does not nest
    r = btf_process("bench", "view", "--size", "64", "--repeat", "1", "--frames", "4",
                    "--json", out)
    assert r.returncode == 0, r.stderr
    assert "| page MB |" in r.stdout
    figures = json.loads(out.read_text())
    assert len(figures["frame_ms"]) == 4 and all(ms > 0 for ms in figures["frame_ms"])
    assert figures["first_frame_ms"][0] > 0 and figures["page_mb"] < 1
    assert figures["numpy_layer_ms"] > 0
