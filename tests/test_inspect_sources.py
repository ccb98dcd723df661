"""Looking at a measured source before ingesting it, and saying what ingest assumed (issue 53).

``btf inspect`` on a DFMF file, a UBO2003/ATRIUM zip, a folder of images and a UTIA BIG file
describes it from its headers and names, without ingesting it; on a store ingested from a
``.btf`` file the plain listing shows the colour model and the file's header. ``btf ingest``
names the colour reading it applied, ``btf export`` to ``.btf`` what the common readers do
with the colour model it writes. Every source is written here by the test, from the formats'
descriptions (docs/formats.md).
"""

from __future__ import annotations

import io
import json
import struct
import zipfile

import numpy as np
import pytest
import zarr
from dfmf_files import truncated_copy, write_dfmf

from helpers import no_partial_outputs
from pipeline.images import write_exr, write_png
from tasks.sampling import parse_sampling

H, W = 6, 10  # not square: a transposed size shows
VIEWS = [(0, 0), (30, 90)]  # (theta, phi) in degrees
LIGHTS = [(0, 0), (15, 60), (45, 300)]
GRID = [(light, view) for view in VIEWS for light in LIGHTS]  # view-major, as the names go
SRGB_LINE = ("colour: JPEG values decoded from sRGB to linear (--decode srgb; --decode "
             "gamma2.2 or none to change)")
XYZ_TAIL = ("converted to linear sRGB primaries (--xyz keep stores X,Y,Z; --xyz none reads "
            "the channels as named)")


def _picture(k: int) -> np.ndarray:
    y, x = np.mgrid[0:H, 0:W]
    return np.stack([20 * y + 10, 15 * x + 5, np.full((H, W), 30 + 40 * k)],
                    axis=-1).clip(0, 255).astype(np.uint8)


# --- the sources, written from the formats' descriptions ------------------------------------

def _jpeg(pixels: np.ndarray) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(pixels).save(buffer, "JPEG", quality=95)
    return buffer.getvalue()


def _rgbe(picture: np.ndarray) -> bytes:
    """A flat ATRIUM-style .hdr ('+X W -Y H', bottom row first) of float values."""
    top = picture.max(axis=-1)
    mantissa, exponent = np.frexp(top)
    rgb = np.floor(picture * (mantissa * 256.0 / top)[..., None])
    rgbe = np.concatenate([rgb, (exponent + 128)[..., None]], axis=-1).astype(np.uint8)
    return f"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n+X {W} -Y {H}\n".encode() + \
        rgbe[::-1].tobytes()


def _zip(path, suffix: str = "jpg", *, spoil_after_first: bool = False):
    """A UBO2003-style zip: a folder per view, index-prefixed member names, a readme."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as z:
        z.writestr("UBO2003/readme.txt", b"not an image")
        for k, ((tl, pl), (tv, pv)) in enumerate(GRID):
            name = (f"UBO2003/tv{tv:03d}_pv{pv:03d}/{k:05d} tl{tl:03d} pl{pl:03d} tv{tv:03d} "
                    f"pv{pv:03d}.{suffix}")
            data = (_jpeg(_picture(k)) if suffix == "jpg"
                    else _rgbe(_picture(k).astype(np.float32) / 16 + 0.25))
            z.writestr(name, b"not a JPEG at all" if spoil_after_first and k else data)
    return path


def _utia_folder(folder, suffix: str, write):
    """UTIA's three-digit names, a folder per view."""
    for k, ((tl, pl), (tv, pv)) in enumerate(GRID):
        sub = folder / f"tv{tv:03d}_pv{pv:03d}"
        sub.mkdir(parents=True, exist_ok=True)
        write(sub / f"tl{tl:03d}_pl{pl:03d}_tv{tv:03d}_pv{pv:03d}.{suffix}", k)
    return folder


def _manifest_folder(folder, channels=("R", "G", "B")):
    """Float EXRs named layer{k}.exr, their directions in manifest.csv."""
    folder.mkdir()
    rows = ["file,theta_light,phi_light,theta_view,phi_view"]
    for k, ((tl, pl), (tv, pv)) in enumerate(GRID):
        write_exr(folder / f"layer{k}.exr", _picture(k) / 255.0, channels)
        rows.append(f"layer{k}.exr,{tl},{pl},{tv},{pv}")
    (folder / "manifest.csv").write_text("\n".join(rows) + "\n")
    return folder


def _chunk(cid: int, payload: bytes) -> bytes:
    pad = -len(payload) % 8
    return struct.pack("<QQ", cid, len(payload) + pad) + payload + b"\0" * pad


def _big(path, angles, *, height=H, width=W, colour_space: str | None = None):
    """A BIG file of float32 RGB images, directions (tl, pl, tv, pv) in radians (list 3)."""
    angles = np.asarray(angles, np.float64)
    data = np.arange(len(angles) * height * width * 3, dtype="<f4") / 1000.0
    chunks = [_chunk(1, struct.pack("<Q", len(angles))), _chunk(3, struct.pack("<Q", height)),
              _chunk(4, struct.pack("<Q", width)), _chunk(5, struct.pack("<Q", 3)),
              _chunk(7, struct.pack("<Q", 2)),
              _chunk(16, struct.pack("<Q", 3) + np.radians(angles).astype("<f8").tobytes()),
              _chunk(8, data.tobytes())]
    if colour_space:
        chunks.insert(4, _chunk(9, colour_space.encode()))
    path.write_bytes(b"BIG\0\0\0\0\0" + b"".join(chunks))
    return path


XML = "<?xml version=\"1.0\"?>\n<btf><material>carpet</material></btf>\n"


def _dfmf(path, *, model=11, views=None, lights=None, ks=(3, 2, 4), scalar_size=2,
          cosine=False, height=5, width=7):
    """A DFMF file (radian angles) with a descriptive header worth showing."""
    rng = np.random.default_rng(model)
    views = [(np.radians(t), np.radians(p)) for t, p in VIEWS] if views is None else views
    lights = [(np.radians(t), np.radians(p)) for t, p in LIGHTS] if lights is None else lights
    rows = len(views) * len(lights)
    u = [rng.normal(size=(rows, k)) * 0.1 for k in ks]
    sxv = [rng.normal(size=(height * width, k)) * 0.1 for k in ks]
    u[0][:, 0] = -1.0
    return write_dfmf(path, views=views, lights=lights, u=u, sxv=sxv, width=width,
                      height=height, color_model=model, scalar_size=scalar_size,
                      cosine=cosine, xml=XML, setup="Bonn dome 1", sensor="Canon EOS 1Ds",
                      light_source="camera flashes", ppmm=12.5, rgb_scale=(1.5, 1.0, 0.75))


def _ubo(name: str) -> list[tuple[float, float]]:
    s = parse_sampling(name)
    return list(zip(s.theta_light.tolist(), s.phi_light.tolist(), strict=True))


def _inspect(btf, path) -> tuple[dict, str]:
    r = btf("inspect", path, "--json")
    assert r.code == 0, r.err
    text = btf("inspect", path)
    assert text.code == 0, text.err
    return json.loads(r.out), text.out


# --- btf inspect on each kind of source ------------------------------------------------------

def test_inspect_describes_a_dfmf_file_from_its_header(tmp_path, btf):
    ubo = [(np.radians(t), np.radians(p)) for t, p in _ubo("ubo2014")]
    path = _dfmf(tmp_path / "carpet.btf", views=ubo, lights=ubo)
    report, text = _inspect(btf, path)
    assert report["kind"] == "source" and "DFMF" in report["format"]
    assert report["file_bytes"] == path.stat().st_size
    assert (report["height"], report["width"], report["channels"]) == (5, 7, ["R", "G", "B"])
    s = report["sampling"]
    assert (s["name"], s["views"], s["lights"], s["layers"]) == ("ubo2014", 151, 151, 151**2)
    assert s["light"]["theta_max"] == pytest.approx(75, abs=1e-4)
    assert report["colour_model"]["number"] == 11
    assert report["colour_model"]["transform"] == "ylog-uv-over-y"
    d = report["dfmf"]
    assert d["components"] == [3, 2, 4] and d["scalar_type"] == "float16"
    assert d["cosine"] is False and d["measurement_setup"] == "Bonn dome 1"
    assert d["image_sensor"] == "Canon EOS 1Ds" and d["light_source"] == "camera flashes"
    assert d["ppmm"] == 12.5 and d["rgb_scale"] == [1.5, 1.0, 0.75]
    assert d["xml_characters"] == len(XML) and d["xml_first_line"] == '<?xml version="1.0"?>'
    assert d["channel_names"] == ["R", "G", "B"]
    g = report["ingest"]
    assert g["store"] == "compressed" and g["rank_at_most"] == 9 and g["refused"] is None
    assert g["factor_bytes"] == {"U": 151 * 151 * 3 * 9 * 4, "S": 9 * 4, "V": 5 * 7 * 9 * 4}
    assert g["radiance_bytes"] == 151 * 151 * 5 * 7 * 3 * 4
    assert report["colour"].startswith("DFMF colour model 11 (Y log, U/V over Y")
    for line in ("Bonn DFMF file (UBO2014 .btf)", "texels 5 x 7 (height x width), channels R,G,B",
                 "sampling: ubo2014: 151 view(s) x 151 light(s) = 22801 layers",
                 "colour model 11: Y log, U/V over Y; YUV to linear RGB (the store's "
                 "transform ylog-uv-over-y)\n  Y = exp(a0) - eps, U = a1 (Y + eps)",
                 "measurement setup 'Bonn dome 1', image sensor 'Canon EOS 1Ds', light source "
                 "'camera flashes'", "12.5 ppmm, RGB scale 1.5, 1, 0.75, channels R,G,B",
                 "components per channel 3+2+4 = 9 (float16), cosine flag not set",
                 f"XML: {len(XML)} characters, first line '<?xml version=\"1.0\"?>'",
                 "btf ingest makes a compressed store of rank 9 at most",
                 "colour: DFMF colour model 11"):
        assert line in text, (line, text)
    assert not (tmp_path / "carpet.zarr").exists()  # nothing was ingested


@pytest.mark.parametrize(("model", "channels", "cosine", "words", "rank"),
                         [(12, ("L0", "L1", "L2", "L3"), False, "log of each channel", 8),
                          (0, ("R", "G", "B"), True, "RGB, linear", 6),
                          (3, ("R", "G", "B"), False, "PCA, linear", 7)])  # + the mean's
def test_inspect_says_each_dfmf_model_and_the_file_s_channels(tmp_path, btf, model, channels,
                                                              cosine, words, rank):
    rng = np.random.default_rng(1)
    rows, texels = len(VIEWS) * len(LIGHTS), 4 * 3
    path = write_dfmf(tmp_path / "m.btf", views=[(0.0, 0.0), (0.5, 1.0)],
                      lights=[(0.0, 0.0), (0.3, 0.2), (0.8, 2.0)],
                      u=[rng.normal(size=(rows, 2)) for _ in channels],
                      sxv=[rng.normal(size=(texels, 2)) for _ in channels], width=4, height=3,
                      color_model=model, scalar_size=4, channel_names=channels, cosine=cosine,
                      color_mean=(0.1, 0.2, 0.3))
    report, text = _inspect(btf, path)
    assert report["channels"] == list(channels) and report["dfmf"]["scalar_type"] == "float32"
    assert report["colour_model"]["what"] == words and report["dfmf"]["cosine"] is cosine
    assert report["sampling"]["name"] is None
    g = report["ingest"]
    assert g["rank_at_most"] == rank and g["mean_component"] is (model == 3)
    assert g["factor_bytes"]["U"] == 6 * len(channels) * rank * 4
    assert f"cosine flag {'set' if cosine else 'not set'}" in text
    assert ("cos(theta_light)" in report["colour"]) is cosine
    assert ("and one for the colour mean" in text) is (model == 3)
    # what ingest makes is what inspect said
    assert btf("ingest", path, tmp_path / "m.zarr", "--quiet").code == 0
    assert zarr.open_group(tmp_path / "m.zarr").attrs["svd"]["rank"] == rank


def test_inspect_describes_a_ubo2003_zip_reading_only_its_first_image(tmp_path, btf):
    # every member but the first is not a JPEG: inspect decodes only the first one
    path = _zip(tmp_path / "wool.zip", spoil_after_first=True)
    report, text = _inspect(btf, path)
    assert report["format"] == "UBO2003/ATRIUM JPEG zip"
    assert report["file_bytes"] == path.stat().st_size
    assert report["images"]["count"] == 6 and report["images"]["kind"] == "JPEG"
    assert (report["height"], report["width"], report["channels"]) == (H, W, ["R", "G", "B"])
    s = report["sampling"]
    assert (s["name"], s["views"], s["lights"]) == (None, 2, 3)
    assert (s["view"]["theta_max"], s["light"]["phi_max"]) == (30, 300)
    assert report["ingest"] == {"store": "radiance", "shape": [2, 3, H, W, 3],
                                "dtype": "float16", "bytes": 2 * 3 * H * W * 3 * 2}  # 8-bit
    assert report["colour"] == SRGB_LINE.removeprefix("colour: ")
    assert SRGB_LINE in text and "6 images (JPEG)" in text
    assert f"radiance store of 2 views x 3 lights x {H} x {W} texels x 3 channels" in text
    assert btf("ingest", path, tmp_path / "s.zarr", "--quiet").code == 1  # ingest reads them


def test_inspect_describes_an_atrium_hdr_zip(tmp_path, btf):
    report, text = _inspect(btf, _zip(tmp_path / "atrium.zip", "hdr"))
    assert report["format"] == "ATRIUM HDR zip" and report["images"]["kind"] == "RGBE (.hdr)"
    assert (report["height"], report["width"]) == (H, W)
    assert report["attrs"]["hdr_rows"] == "bottom-up"
    assert "colour: Radiance RGBE values stored as they are (linear" in text


def test_inspect_describes_a_utia_png_folder(tmp_path, btf):
    folder = _utia_folder(tmp_path / "utia", "png", lambda p, k: write_png(p, _picture(k)))
    report, text = _inspect(btf, folder)
    files = sorted(folder.rglob("*.png"))
    assert report["format"] == "UTIA image folder" and report["images"]["kind"] == "PNG"
    assert report["file_bytes"] == sum(p.stat().st_size for p in files)
    assert report["images"]["directions_from"] == "the file names, a folder per view"
    assert (report["sampling"]["views"], report["sampling"]["lights"]) == (2, 3)
    assert report["ingest"]["shape"] == [2, 3, H, W, 3]
    assert ("colour: PNG values decoded from sRGB to linear (--decode srgb; --decode gamma2.2 "
            "or none to change)") in text


def test_inspect_describes_exr_folders_and_their_colour(tmp_path, btf):
    report, text = _inspect(btf, _manifest_folder(tmp_path / "linear"))
    assert report["format"] == "image folder" and report["images"]["kind"] == "EXR"
    assert report["images"]["directions_from"] == "manifest.csv"
    assert report["colour"] == "EXR values stored as they are (linear)"
    assert "colour: EXR values stored as they are (linear)" in text
    xyz, _ = _inspect(btf, _manifest_folder(tmp_path / "xyz", ("X", "Y", "Z")))
    assert xyz["colour"] == f"CIE XYZ (D65) {XYZ_TAIL}" and xyz["channels"] == ["R", "G", "B"]
    utia = _utia_folder(tmp_path / "utia", "exr",
                        lambda p, k: write_exr(p, _picture(k) / 255.0, ("R", "G", "B")))
    report, _ = _inspect(btf, utia)
    assert report["format"] == "UTIA image folder"
    assert "EXR channels R,G,B read as CIE XYZ (D65)" in report["colour"]
    assert report["colour"].endswith(XYZ_TAIL)


def test_inspect_describes_a_big_file_and_names_its_sampling(tmp_path, btf):
    ubo = _ubo("ubo2003")
    angles = [(tl, pl, tv, pv) for tv, pv in ubo for tl, pl in ubo]  # 81 x 81 images of 1 x 2
    path = _big(tmp_path / "fabric.big", angles, height=1, width=2, colour_space="CIE XYZ")
    report, text = _inspect(btf, path)
    assert report["format"] == "UTIA BIG" and report["images"]["kind"] == "float, 3 plane(s)"
    assert report["file_bytes"] == path.stat().st_size
    assert report["images"]["count"] == 81 * 81
    s = report["sampling"]
    assert (s["name"], s["views"], s["lights"]) == ("ubo2003", 81, 81)
    assert report["ingest"]["shape"] == [81, 81, 1, 2, 3]
    assert report["ingest"]["bytes"] == 81 * 81 * 2 * 3 * 4
    assert report["colour"].startswith("CIE XYZ") and report["colour"].endswith(XYZ_TAIL)
    assert "sampling: ubo2003: 81 view(s) x 81 light(s) = 6561 layers" in text
    assert "radians" in report["images"]["directions_from"]
    # one view of the lights: the lights alone are named
    one = _big(tmp_path / "abtf.big", [(tl, pl, 0, 0) for tl, pl in ubo], height=1, width=2)
    report, text = _inspect(btf, one)
    assert report["sampling"]["name"] is None
    assert report["sampling"]["light"]["sampling"] == "ubo2003"
    assert "lights are ubo2003's directions" in text
    assert report["colour"] == "BIG values stored as they are (no colour space given)"


def _garbage(tmp_path):
    path = tmp_path / "notes.txt"
    path.write_text("hello")
    return path, "not a folder of images, a zip archive"


def _truncated_dfmf(tmp_path):
    good = _dfmf(tmp_path / "good.btf")
    return truncated_copy(good, tmp_path / "cut.btf", drop=3), "truncated"


def _bad_big(tmp_path):
    path = tmp_path / "x.big"
    path.write_bytes(b"BIGGER\0\0" + b"\0" * 16)
    return path, "not a BIG file"


def _bad_zip(tmp_path):
    path = tmp_path / "x.zip"
    path.write_bytes(b"PK\x03\x04 and nothing of a zip")
    return path, "not a readable zip archive"


def _missing(tmp_path):
    return tmp_path / "nothing.btf", "no such file"


def _missing_folder(tmp_path):
    return tmp_path / "utia_folder", "no such file, folder or store"


def _empty_folder(tmp_path):
    (tmp_path / "empty").mkdir()
    return tmp_path / "empty", "nor a measured source"


@pytest.mark.parametrize("damage", [_garbage, _truncated_dfmf, _bad_big, _bad_zip, _missing,
                                    _missing_folder, _empty_folder])
def test_inspect_of_bad_input_says_what_and_where_once(tmp_path, btf, damage):
    path, message = damage(tmp_path)
    for args in ((), ("--json",)):
        r = btf("inspect", path, *args)
        assert r.code == 1 and r.out == "", (r.code, r.out)
        assert message in r.err and str(path) in r.err, r.err
        assert len(r.err.strip().splitlines()) == 1, r.err


def test_inspect_of_a_source_refuses_scan_and_plot_and_writes_its_report(tmp_path, btf):
    path = _zip(tmp_path / "a.zip")
    r = btf("inspect", path, "--scan")
    assert r.code == 1 and "--scan reads a store" in r.err and "btf ingest" in r.err
    assert btf("inspect", path, "--plot", tmp_path / "p.png").code == 1
    assert not (tmp_path / "p.png").exists()
    assert btf("inspect", path, "--report", tmp_path / "r.json").code == 0
    assert json.loads((tmp_path / "r.json").read_text())["ingest"]["shape"] == [2, 3, H, W, 3]


def test_inspect_help_explains_sources(btf):
    r = btf("inspect", "--help")
    assert r.code == 0 and "FILE.btf" in r.out and "without ingesting" in r.out


def test_a_store_from_a_dfmf_file_lists_its_colour_model_and_the_file_s_header(tmp_path, btf):
    _dfmf(tmp_path / "m.btf")
    assert btf("ingest", tmp_path / "m.btf", tmp_path / "m.zarr", "--quiet").code == 0
    r = btf("inspect", tmp_path / "m.zarr")
    assert r.code == 0, r.err
    for line in ("transform: ylog-uv-over-y, eps 1e-05; DFMF colour model 11: Y = exp(a0) - eps, "
                 "U = a1 (Y + eps), V = a2 (Y + eps), YUV to RGB",
                 "source file header (DFMF metadata version 4): measurement setup 'Bonn dome 1', "
                 "image sensor 'Canon EOS 1Ds', light source 'camera flashes'",
                 "12.5 ppmm, RGB scale 1.5, 1, 0.75, channels R,G,B, colour model 11, "
                 "components per channel 3+2+4 = 9 (float16), cosine flag not set",
                 f"XML: {len(XML)} characters, first line '<?xml version=\"1.0\"?>'"):
        assert line in r.out, (line, r.out)


def test_a_compressed_store_lists_its_transform(btf, small_btf, tmp_path):
    assert btf("compress", small_btf, tmp_path / "c.zarr", "--rank", "3", "--quiet").code == 0
    r = btf("inspect", tmp_path / "c.zarr")
    assert "transform: log, eps 0.001: log(radiance + eps)" in r.out, r.out
    assert "header" not in r.out


# --- ingest says the colour reading it applied ------------------------------------------------

def _utia_rgb_exr(tmp_path):
    return _utia_folder(tmp_path / "u", "exr",
                        lambda p, k: write_exr(p, _picture(k) / 255.0, ("R", "G", "B")))


INGESTS = {
    "jpeg zip": (lambda t: _zip(t / "a.zip"), (), SRGB_LINE),
    "jpeg zip gamma": (lambda t: _zip(t / "a.zip"), ("--decode", "gamma2.2"),
                       "colour: JPEG values decoded as (v/max)^2.2 to linear (the Mitsuba BTF "
                       "plugin's curve) (--decode gamma2.2; --decode srgb or none to change)"),
    "hdr zip": (lambda t: _zip(t / "a.zip", "hdr"), (),
                "colour: Radiance RGBE values stored as they are (linear, the camera's RGB)"),
    "utia png": (lambda t: _utia_folder(t / "u", "png", lambda p, k: write_png(p, _picture(k))),
                 (), "colour: PNG values decoded from sRGB to linear (--decode srgb; --decode "
                     "gamma2.2 or none to change)"),
    "png folder": (lambda t: _manifest_png(t / "p"), (),
                   "colour: PNG values taken as linear, v/max, not decoded (--decode none; "
                   "--decode srgb or gamma2.2 to change)"),
    "xyz exr": (lambda t: _manifest_folder(t / "x", ("X", "Y", "Z")), (),
                f"colour: CIE XYZ (D65) {XYZ_TAIL}"),
    "xyz exr kept": (lambda t: _manifest_folder(t / "x", ("X", "Y", "Z")), ("--xyz", "keep"),
                     "colour: CIE XYZ (D65) stored as X,Y,Z (--xyz keep; --xyz srgb converts "
                     "them to linear sRGB primaries, --xyz none reads the channels as named)"),
    "utia rgb exr": (_utia_rgb_exr, (),
                     "colour: EXR channels R,G,B read as CIE XYZ (D65), as UTIA's database "
                     f"stores them, {XYZ_TAIL}"),
    "utia rgb exr as named": (_utia_rgb_exr, ("--xyz", "none"),
                              "colour: EXR values stored as they are (linear), channels as "
                              "named (--xyz none: no XYZ conversion"),
    "linear exr": (lambda t: _manifest_folder(t / "e"), (),
                   "colour: EXR values stored as they are (linear)\n"),
    "big": (lambda t: _big(t / "b.big", [(*a, *b) for b in VIEWS for a in LIGHTS],
                           colour_space="sRGB"), (),
            "colour: BIG values stored as they are (sRGB)"),
    "dfmf 11": (lambda t: _dfmf(t / "m.btf"), (),
                "colour: DFMF colour model 11 (Y log, U/V over Y; YUV to linear RGB, eps 1e-05) "
                "kept as the store's transform (ylog-uv-over-y)\n"),
    "dfmf 1": (lambda t: _dfmf(t / "m.btf", model=1), (),
               "colour: DFMF colour model 1 (YUV, linear) folded into U: the store holds "
               "linear RGB (transform linear)"),
}


def _manifest_png(folder):
    folder.mkdir()
    rows = ["file,theta_light,phi_light,theta_view,phi_view"]
    for k, ((tl, pl), (tv, pv)) in enumerate(GRID):
        write_png(folder / f"layer{k}.png", _picture(k))
        rows.append(f"layer{k}.png,{tl},{pl},{tv},{pv}")
    (folder / "manifest.csv").write_text("\n".join(rows) + "\n")
    return folder


@pytest.mark.parametrize("case", sorted(INGESTS))
def test_ingest_names_the_colour_reading_it_applied(tmp_path, btf, case):
    write, args, line = INGESTS[case]
    src = write(tmp_path)
    r = btf("ingest", src, tmp_path / "s.zarr", *args)
    assert r.code == 0, r.err
    assert f"ingest: {line}" in r.err, r.err
    assert r.err.count("ingest: colour: ") == 1
    quiet = btf("ingest", src, tmp_path / "q.zarr", "--quiet", *args)
    assert quiet.code == 0 and "colour" not in quiet.err


def test_ingest_s_colour_line_comes_only_once_the_output_is_begun(tmp_path, btf):
    src = _zip(tmp_path / "a.zip")
    r = btf("ingest", src, tmp_path / "s.zarr")
    assert r.code == 0 and r.err.index("ingest: 2 x 3 layers") < r.err.index(SRGB_LINE)
    refused = btf("ingest", src, tmp_path / "s.zarr")  # exists: nothing is ingested
    assert refused.code == 1 and "colour:" not in refused.err


# --- export says what the readers make of the colour model it writes --------------------------

@pytest.mark.parametrize(("model", "says"), [
    (12, ["colour model 12 (log of each channel): btflib decodes it; btf.hh, btf-extractor "
          "and the Mitsuba BTF plugin decode only models 0 and 11 and return this model's "
          "channel sums a without the exp: radiance is exp(a) - 1e-05 per channel",
          "export the layers as EXR"]),
    (11, ["colour model 11 (Y log, U/V over Y; YUV to linear RGB): btflib, btf.hh and "
          "btf-extractor (the Mitsuba BTF plugin's reader) decode it, but btf-extractor clamps "
          "RGB to [0, 1]"]),
    (0, ["colour model 0 (RGB, linear): btflib, btf.hh and btf-extractor (the Mitsuba BTF "
         "plugin's reader) all return the values as they are"]),
])
def test_export_to_dfmf_says_what_the_common_readers_return(tmp_path, btf, model, says):
    _dfmf(tmp_path / "m.btf", model=model, ks=(2, 2, 2), scalar_size=4)
    assert btf("ingest", tmp_path / "m.btf", tmp_path / "m.zarr", "--quiet").code == 0
    r = btf("export", tmp_path / "m.zarr", tmp_path / "out.btf")
    assert r.code == 0, r.err
    assert zarr.open_group(tmp_path / "m.zarr").attrs["transform"]["dfmf_colour_model"] == model
    for text in says:
        assert text in r.err, (text, r.err)
    assert r.err.count("export: readers: ") == 1
    quiet = btf("export", tmp_path / "m.zarr", tmp_path / "q.btf", "--quiet")
    assert quiet.code == 0 and quiet.err == ""
    assert no_partial_outputs(tmp_path / "never.btf")
