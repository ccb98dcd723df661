"""``btf view``: the relighting page, its blending rule, its errors, and the page in chromium.

The browser tests run Debian's chromium headless with WebGL2 on SwiftShader, driven by
playwright; they skip where there is no chromium (``.ci/run`` installs it and sets
BTF_REQUIRE_BROWSER, so there they fail instead).
"""

from __future__ import annotations

import numpy as np
import pytest
import zarr

from helpers import BROWSER_FLAGS, chromium, generate_store, no_partial_outputs
from tasks.svd import reconstruct_layers
from tasks.tonemap import to_uint8, tonemap
from tasks.transform import Transform
from tasks.viewer import blend_weights, disk, pack_eigentextures, triangulate

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
    assert no_partial_outputs(out) and not out.exists()


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


def _canvas(tab) -> np.ndarray:
    flat = np.array(tab.evaluate("window.btfView.pixels()"), np.uint8)
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


@pytest.mark.slow
def test_btf_bench_view_reports_its_table(tmp_path):
    chromium()
    pytest.importorskip("playwright.sync_api")
    from benchmarks.cli import main as bench

    out = tmp_path / "view.json"
    assert bench(["view", "--size", "64", "--repeat", "1", "--frames", "4", "--json",
                  str(out)]) == 0
    import json

    r = json.loads(out.read_text())
    assert len(r["frame_ms"]) == 4 and all(ms > 0 for ms in r["frame_ms"])
    assert 0 < r["first_frame_ms"][0] and r["page_mb"] < 1 and r["numpy_layer_ms"] > 0
