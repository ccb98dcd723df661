"""btf report: the page's parts, its figures against exact references, and a real browser."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest

from tasks.evaluation import abrdf_error, lookup_baseline, tiling_baseline
from tasks.report_html import Picture, Section, Table, render
from tasks.transform import Transform


def _png(rgb) -> bytes:
    import io

    from matplotlib.image import imsave

    buffer = io.BytesIO()
    imsave(buffer, np.asarray(rgb, float), format="png")
    return buffer.getvalue()


def test_the_page_embeds_its_pictures_escapes_text_and_needs_no_network():
    pixels = np.zeros((4, 4, 3))
    pixels[0, 0] = 1
    page = render("t <b>", "intro & more", [Section(
        "s", ("<script>alert(1)</script>",), (Table(("a", "b"), (("1.5 s", "x<y"),)),),
        (Picture("one", _png(pixels)),), ("btf generate 'a b'",))])
    assert "<script>" not in page and "&lt;script&gt;" in page and "x&lt;y" in page
    assert page.count('src="data:image/png;base64,') == 1
    assert "http" not in page.replace("http-equiv", "")
    assert '<td class="n">1.5 s</td>' in page and "btf generate &#x27;a b&#x27;" in page


def test_baselines_on_cases_with_a_known_answer():
    rng = np.random.default_rng(1)
    sample = rng.random((6, 5, 3))
    tiled = tiling_baseline(sample, (14, 13), (4, 3))
    assert np.array_equal(tiled[4:10, 3:8], sample)  # the sample where it was measured
    assert np.array_equal(tiled[10:14, 8:13], sample[:4, :5])  # and repeated beyond
    assert np.array_equal(tiling_baseline(sample, (3, 13), (4, 3), start=(5, 0)), tiled[5:8])
    # a target that rearranges the sample's texels: the lookup finds every one of them
    keys = rng.random((6, 5, 2))
    order = rng.permutation(30)
    target = keys.reshape(30, 2)[order].reshape(5, 6, 2)
    looked = lookup_baseline(sample, keys, target)
    assert np.array_equal(looked, sample.reshape(30, 3)[order].reshape(5, 6, 3))


def test_eq_11_is_the_mean_of_each_texel_s_rms_radiance_error():
    rng = np.random.default_rng(2)
    u, coef = rng.normal(size=(12, 3)) * 0.3, rng.normal(size=(5, 4, 3)) * 0.3
    eps = 1e-3
    exact = np.exp(coef @ u.T) - eps  # (5, 4, rows)
    truth = exact + rng.normal(size=exact.shape) * 0.01
    mask = rng.random((5, 4)) < 0.6
    expected = np.sqrt(((exact - truth) ** 2).mean(-1))[mask].mean()
    assert abrdf_error(u, coef, Transform("log", eps), truth, mask) == pytest.approx(
        expected, rel=1e-6)


@pytest.mark.slow
def test_the_demo_report_renders_in_a_real_browser_with_every_picture_loaded(btf, tmp_path,
                                                                            monkeypatch):
    from helpers import chromium as find_chromium
    from helpers import small_demo

    chromium = find_chromium()

    monkeypatch.chdir(tmp_path)
    # the whole demo, its tile set rendered by Mitsuba on a sphere included, where Mitsuba is
    # installed (.ci/run installs it and LLVM 19: there the llvm variant renders it)
    import importlib.util
    import os

    mitsuba = (os.environ.get("BTF_REQUIRE_MITSUBA") == "1"
               or importlib.util.find_spec("mitsuba") is not None)
    assert btf("run", small_demo(tmp_path, mitsuba=mitsuba), "--quiet").code == 0
    page = tmp_path / "out" / "demo" / "report.html"
    if mitsuba:
        text = page.read_text()
        assert "Rendered by Mitsuba 3 through btf" in text
        assert "sphere of out/demo/tiles.zarr" in text
        if os.environ.get("BTF_REQUIRE_MITSUBA") == "1":
            assert "(llvm_ad_rgb)" in text
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             f"--user-data-dir={tmp_path / 'profile'}"]
    # the DOM after layout: every picture decoded (naturalWidth > 0) and the page not blank
    probe = tmp_path / "probe.html"
    probe.write_text(page.read_text().replace("</body>", """<script>
window.addEventListener('load', () => {
  const imgs = [...document.images];
  const loaded = imgs.filter(i => i.complete && i.naturalWidth > 0).length;
  document.title = `images ${imgs.length} loaded ${loaded} height ${document.body.scrollHeight}`;
});
</script></body>"""))
    dom = subprocess.run([chromium, *flags, "--virtual-time-budget=5000", "--dump-dom",
                          probe.as_uri()], capture_output=True, text=True, timeout=120)
    import re

    found = re.search(r"<title>images (\d+) loaded (\d+) height (\d+)</title>", dom.stdout)
    assert found, dom.stderr[-2000:]
    count, loaded, height = map(int, found.groups())
    assert count >= 20 and loaded == count and height > 2000
    shot = tmp_path / "shot.png"
    subprocess.run([chromium, *flags, "--window-size=1024,1400", f"--screenshot={shot}",
                    page.as_uri()], capture_output=True, timeout=120)
    from matplotlib.image import imread

    pixels = imread(shot)[..., :3]
    assert pixels.std() > 0.05  # text, tables and pictures: not a blank page


def test_a_png_carries_text_that_the_report_reads_back(tmp_path):
    import imagecodecs

    from pipeline.images import png_text, write_png

    pixels = np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3)
    write_png(tmp_path / "x.png", pixels, text={"btf": "Mitsuba 3 (llvm_ad_rgb), 16 spp"})
    data = (tmp_path / "x.png").read_bytes()
    assert png_text(data) == {"btf": "Mitsuba 3 (llvm_ad_rgb), 16 spp"}
    assert np.array_equal(imagecodecs.png_decode(data), pixels)  # still a valid PNG
    write_png(tmp_path / "y.png", pixels)
    assert png_text((tmp_path / "y.png").read_bytes()) == {}
    assert png_text(b"not a png") == {}
