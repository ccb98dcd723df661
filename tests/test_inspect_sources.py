"""Saying what ingest assumed (issue 53).

``btf ingest`` names the colour reading it applied, ``btf export`` to ``.btf`` what the
common readers do with the colour model it writes. Every source is written here by the test, from the formats'
descriptions (docs/formats.md).
"""

from __future__ import annotations

import io
import struct
import zipfile

import numpy as np
import pytest
import zarr
from dfmf_files import write_dfmf

from helpers import no_partial_outputs
from pipeline.images import write_exr, write_png

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
