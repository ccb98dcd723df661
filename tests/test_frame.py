"""One frame everywhere: a material of known geometry, written in every format by this test.

The frame (docs/formats.md, "The frame"): right-handed, z the surface normal towards the viewer,
x along increasing columns, y towards the top of the picture (row 0 is the top row), phi from
+x towards +y. A field of bumps is shaded here (Lambert, numpy) under lights from the four
sides, each format's files are written from those layers by this test (not by btf's exporter),
and after ``btf ingest`` the slopes that face a light are the bright ones in every store: lit
from phi = 90 the slopes facing the top of the picture, lit from phi = 270 those facing its
bottom. A mirrored reader (rows reversed, or a DFMF file read in its own row order) makes
every layer's correlation with the slopes change sign.
"""

from __future__ import annotations

import io
import struct
import zipfile

import numpy as np
import pytest
import zarr
from dfmf_files import write_dfmf

from helpers import facing, side_lights_brighten_the_slopes_facing_them

H, W = 24, 40  # not square: a transposed reader changes the shape
LIGHTS = [(0, 0), (50, 0), (50, 90), (50, 180), (50, 270)]  # (theta, phi), degrees
VIEW = (0, 0)
SIDES = [1, 2, 3, 4]  # the lights from the four sides


def heights() -> np.ndarray:
    """Smooth bumps at fixed random places (pixels of height)."""
    rng = np.random.default_rng(53)
    rows, cols = np.mgrid[0:H, 0:W].astype(np.float64)
    h = np.zeros((H, W))
    for y, x in rng.uniform((0, 0), (H, W), (14, 2)):
        h += 2.5 * np.exp(-((rows - y) ** 2 + (cols - x) ** 2) / (2 * 2.5**2))
    return h


def shade(h: np.ndarray, theta: float, phi: float) -> np.ndarray:
    """Lambertian radiance ``(y, x, 3)`` of height field ``h`` lit from ``(theta, phi)``."""
    grow, gx = np.gradient(h)
    n = np.stack([-gx, grow, np.ones_like(gx)], axis=-1)  # dh/dy = -dh/drow
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    t, p = np.radians(theta), np.radians(phi)
    light = np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])
    return 0.02 + np.array([0.8, 0.6, 0.4]) * np.maximum(n @ light, 0.0)[..., None]


def layers() -> np.ndarray:
    """Radiance ``(lights, H, W, 3)`` of the bumps, in [0.02, 0.82], shaded in the frame."""
    return np.stack([shade(heights(), *light) for light in LIGHTS]).astype(np.float32)


def assert_upright(images: np.ndarray, what: str) -> None:
    """``images`` ``(lights, H, W, C)``: each side light brightens the slopes facing it."""
    h = heights()
    for i in SIDES:
        phi = LIGHTS[i][1]
        lum = np.asarray(images[i], np.float64).mean(axis=-1)
        towards = np.corrcoef(lum.ravel(), facing(h, phi).ravel())[0, 1]
        away = np.corrcoef(lum.ravel(), facing(h, phi + 180).ravel())[0, 1]
        assert towards > 0.9 and away < -0.9, (what, phi, towards, away)


def test_the_shading_here_is_in_the_frame():
    # one bump lit from phi = 90: its upper side (towards row 0) is the bright one
    rows, cols = np.mgrid[0:21, 0:21]
    lit = shade(np.exp(-((rows - 10) ** 2 + (cols - 10) ** 2) / 18.0), 50, 90).mean(axis=-1)
    assert lit[7, 10] > lit[13, 10] + 0.1 and abs(lit[10, 7] - lit[10, 13]) < 1e-9
    assert_upright(layers(), "numpy")


# --- the writers: one per format, from the format's description ----------------------------

def _srgb_bytes(values: np.ndarray) -> np.ndarray:
    v = np.clip(values, 0.0, 1.0)
    encoded = np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)
    return np.round(encoded * 255).astype(np.uint8)


def _ubo_zip(path, suffix: str, encode) -> None:
    """UBO2003/ATRIUM: members ``... tl{ddd} pl{ddd} tv{ddd} pv{ddd}.{suffix}``, by view."""
    tv, pv = VIEW
    with zipfile.ZipFile(path, "w") as z:
        for i, ((tl, pl), image) in enumerate(zip(LIGHTS, layers(), strict=True)):
            z.writestr(f"M/tv{tv:03d}_pv{pv:03d}/{i:05d} tl{tl:03d} pl{pl:03d} tv{tv:03d} "
                       f"pv{pv:03d}.{suffix}", encode(image))


def _jpeg(image: np.ndarray) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(_srgb_bytes(image)).save(buffer, "JPEG", quality=100, subsampling=0)
    return buffer.getvalue()


def _atrium_hdr(image: np.ndarray) -> bytes:
    """Flat RGBE, ATRIUM's '+X W -Y H' line, the picture's bottom row stored first."""
    top = image.max(axis=-1)
    mantissa, exponent = np.frexp(top)
    rgb = np.floor(image * (mantissa * 256.0 / top)[..., None])
    rgbe = np.concatenate([rgb, (exponent + 128)[..., None]], axis=-1).astype(np.uint8)
    head = f"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n+X {W} -Y {H}\n".encode()
    return head + rgbe[::-1].tobytes()


def _utia_name(light, suffix: str) -> str:
    (tl, pl), (tv, pv) = light, VIEW
    return f"tl{tl:03d}_pl{pl:03d}_tv{tv:03d}_pv{pv:03d}.{suffix}"


def _utia_png_folder(folder) -> None:
    from PIL import Image

    folder.mkdir()
    for light, image in zip(LIGHTS, layers(), strict=True):
        Image.fromarray(_srgb_bytes(image)).save(folder / _utia_name(light, "png"))


def _exr_folder(folder) -> None:
    """Float EXRs named in a manifest, written with OpenEXR directly."""
    import OpenEXR

    folder.mkdir()
    rows = ["file,theta_light,phi_light,theta_view,phi_view"]
    for i, ((tl, pl), image) in enumerate(zip(LIGHTS, layers(), strict=True)):
        planes = {c: np.ascontiguousarray(image[..., k]) for k, c in enumerate("RGB")}
        with OpenEXR.File({"compression": OpenEXR.NO_COMPRESSION}, planes) as f:
            f.write(str(folder / f"layer{i}.exr"))
        rows.append(f"layer{i}.exr,{tl},{pl},{VIEW[0]},{VIEW[1]}")
    (folder / "manifest.csv").write_text("\n".join(rows) + "\n")


def _big(path) -> None:
    """UTIA BIG: float images, row 0 first, (tl, pl, tv, pv) in radians per image."""
    def chunk(cid, payload):
        pad = -len(payload) % 8
        return struct.pack("<QQ", cid, len(payload) + pad) + payload + b"\0" * pad

    angles = np.radians([[tl, pl, *VIEW] for tl, pl in LIGHTS]).astype("<f8")
    path.write_bytes(b"BIG\0\0\0\0\0" + b"".join([
        chunk(1, struct.pack("<Q", len(LIGHTS))), chunk(3, struct.pack("<Q", H)),
        chunk(4, struct.pack("<Q", W)), chunk(5, struct.pack("<Q", 3)),
        chunk(7, struct.pack("<Q", 2)), chunk(16, angles.tobytes()),
        chunk(8, layers().astype("<f4").tobytes())]))


def _dfmf(path) -> None:
    """Colour model 0, each channel factored exactly, texel rows from the picture's bottom."""
    bottom_up = layers()[:, ::-1].reshape(len(LIGHTS), H * W, 3).astype(np.float64)
    u, sxv = [], []
    for c in range(3):
        left, s, right = np.linalg.svd(bottom_up[..., c], full_matrices=False)
        u.append(left * s)
        sxv.append(right.T)
    views = [tuple(np.radians(VIEW))]
    lights = [tuple(np.radians(light)) for light in LIGHTS]
    write_dfmf(path, views=views, lights=lights, u=u, sxv=sxv, width=W, height=H,
               color_model=0, scalar_size=4)


FORMATS = {
    "ubo2003 zip": ("m.zip", lambda p: _ubo_zip(p, "jpg", _jpeg)),
    "atrium hdr zip": ("h.zip", lambda p: _ubo_zip(p, "hdr", _atrium_hdr)),
    "utia png folder": ("utia", _utia_png_folder),
    "exr folder": ("exr", _exr_folder),
    "utia big": ("m.big", _big),
    "bonn dfmf": ("m.btf", _dfmf),
}


@pytest.mark.parametrize("fmt", sorted(FORMATS))
def test_every_format_is_read_the_right_way_up(tmp_path, btf, fmt):
    from pipeline.stores import open_layers

    name, write = FORMATS[fmt]
    write(tmp_path / name)
    r = btf("ingest", tmp_path / name, tmp_path / "s.zarr", "--quiet")
    assert r.code == 0, r.err
    ds = open_layers(tmp_path / "s.zarr")
    assert np.allclose(ds["phi_light"].values, [p for _, p in LIGHTS], atol=1e-4)
    assert_upright(ds["radiance"].values[0], fmt)


def test_btf_export_writes_images_the_right_way_up(tmp_path, btf):
    import csv

    import OpenEXR

    from pipeline.stores import open_layers

    _dfmf(tmp_path / "m.btf")
    assert btf("ingest", tmp_path / "m.btf", tmp_path / "m.zarr", "--quiet").code == 0
    assert btf("export", tmp_path / "m.zarr", tmp_path / "out", "--quiet").code == 0
    with open(tmp_path / "out" / "manifest.csv") as f:
        files = {(round(float(r["theta_light"])), round(float(r["phi_light"]))): r["file"]
                 for r in csv.DictReader(f)}
    images = []
    for light in LIGHTS:
        with OpenEXR.File(str(tmp_path / "out" / files[light]), separate_channels=True) as f:
            planes = f.channels()
            images.append(np.stack([np.asarray(planes[c].pixels) for c in "RGB"], axis=-1))
    assert_upright(np.stack(images), "exported EXR")
    # a scene of the store at the four side lights keeps the frame
    rows = "".join(f"  - [{t}, {p}, 0, 0]\n" for t, p in LIGHTS[1:])
    (tmp_path / "s.yaml").write_text(f"source: {tmp_path / 'm.zarr'}\ndirections:\n{rows}"
                                     "format: zarr\n")
    assert btf("scene", tmp_path / "s.yaml", tmp_path / "s.zarr", "--quiet").code == 0
    scene = open_layers(tmp_path / "m.zarr")["radiance"].values[0].copy()
    scene[1:] = zarr.open_group(tmp_path / "s.zarr", mode="r")["radiance"][...]
    assert_upright(scene, "scene")
    # a DFMF file written by btf export is read back the same way up
    assert btf("export", tmp_path / "m.zarr", tmp_path / "back.btf", "--quiet").code == 0
    assert btf("ingest", tmp_path / "back.btf", tmp_path / "back.zarr", "--quiet").code == 0
    assert_upright(open_layers(tmp_path / "back.zarr")["radiance"].values[0], "re-exported")


def test_btf_generate_shades_in_the_frame(tmp_path):
    from helpers import generate_store
    from pipeline.stores.radiance import open_radiance

    path = generate_store(tmp_path / "l.zarr", "--material", "leather", "--size", "48",
                          "--sampling", "abtf:4,2", "--seed", "5")
    ds = open_radiance(path)
    side_lights_brighten_the_slopes_facing_them(ds)
