"""btf ingest of measured BTF formats: UBO2003/ATRIUM zips, UTIA folders and BIG files.

Every input is written here from the formats' descriptions (docs/formats.md): Pillow
JPEGs, hand-made Radiance RGBE bytes, OpenEXR/PNG files with UTIA names, BIG chunks packed
with struct. Pictures are asymmetric and not square, so a flipped or transposed read fails.
"""

from __future__ import annotations

import io
import math
import re
import struct
import zipfile

import numpy as np
import pytest
import zarr

from helpers import HALF_ROUNDING, no_partial_outputs, stored_dtype
from pipeline.images import write_exr, write_png
from pipeline.stores.base import RADIANCE
from pipeline.stores.radiance import open_radiance

H, W = 8, 12  # not square: a transposed read changes the shape
VIEWS = [(0, 0), (30, 90)]
LIGHTS = [(0, 0), (15, 60), (45, 300)]


def _picture(k: int) -> np.ndarray:
    """Asymmetric uint8 picture number ``k``: gradients along y and x, a bright top-left."""
    y, x = np.mgrid[0:H, 0:W]
    img = np.stack([20 * y + 10, 15 * x + 5, np.full((H, W), 30 + 40 * k)], axis=-1)
    img[0, 0] = (250, 240, 230)
    return img.clip(0, 255).astype(np.uint8)


def _srgb(v):
    v = np.asarray(v, np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def _values(path):
    ds = open_radiance(path)
    coords = {k: ds[k].values.tolist() for k in
              ("theta_view", "phi_view", "theta_light", "phi_light")}
    return ds[RADIANCE].values, coords, [str(c) for c in ds["channel"].values]


def _grid():
    """(view index, light index, k, angles) of the test grid; k numbers the pictures."""
    return [(v, li, v * len(LIGHTS) + li, (*light, *view))
            for v, view in enumerate(VIEWS) for li, light in enumerate(LIGHTS)]


def _jpeg(pixels: np.ndarray) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(pixels).save(buffer, "JPEG", quality=100, subsampling=0)
    return buffer.getvalue()


def _bonn_name(angles, index: int, suffix: str = "jpg") -> str:
    tl, pl, tv, pv = angles
    return (f"UBO2003/MANYFILES/tv{tv:03d}_pv{pv:03d}/{index:05d} "
            f"tl{tl:03d} pl{pl:03d} tv{tv:03d} pv{pv:03d}.{suffix}")


def _ubo_zip(path, members: dict[str, bytes]):
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as z:
        z.writestr("UBO2003/readme.txt", b"not an image")
        for name, data in members.items():
            z.writestr(name, data)
            # as macOS's zip adds them: a resource fork per file, named like the image
            folder, _, base = name.rpartition("/")
            z.writestr(f"__MACOSX/{folder}/._{base}", b"\x00\x05\x16\x07 resource fork")
    return path


def _ubo_members():
    return {_bonn_name(angles, k): _jpeg(_picture(k)) for _, _, k, angles in _grid()}


def _decoded_jpeg(data: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB")) / 255.0


@pytest.mark.parametrize("decode", ["default", "gamma2.2", "none"])
def test_ubo2003_zip_is_read_upright_with_its_directions_and_decoding(tmp_path, btf, decode):
    members = _ubo_members()
    archive = _ubo_zip(tmp_path / "UBO_TEST.zip", members)
    args = () if decode == "default" else ("--decode", decode)
    result = btf("ingest", archive, tmp_path / "s.zarr", "--quiet", *args)
    assert result.code == 0, result.err
    values, coords, channels = _values(tmp_path / "s.zarr")
    assert channels == ["R", "G", "B"] and values.shape == (2, 3, H, W, 3)
    assert coords == {"theta_view": [0, 30], "phi_view": [0, 90], "theta_light": [0, 15, 45],
                      "phi_light": [0, 60, 300]}
    curve = {"default": _srgb, "gamma2.2": lambda v: v ** 2.2, "none": lambda v: v}[decode]
    for v, li, k, angles in _grid():
        encoded = _decoded_jpeg(members[_bonn_name(angles, k)])  # an independent decoder
        assert np.abs(encoded - _picture(k) / 255).max() <= 6 / 255  # the JPEG is the picture
        assert np.allclose(values[v, li], curve(encoded), rtol=HALF_ROUNDING, atol=1e-6), (v, li)
    if decode == "default":  # the default is sRGB, and a missing decoding would be caught
        assert not np.allclose(values[0, 0], _decoded_jpeg(members[_bonn_name(
            _grid()[0][3], 0)]), atol=0.02)
    attrs = zarr.open_group(tmp_path / "s.zarr").attrs["ingest"]
    assert attrs["decoding"] == ("srgb" if decode == "default" else decode)


def test_old_srgb_flag_still_works_and_contradictions_are_refused(tmp_path, btf):
    archive = _ubo_zip(tmp_path / "a.zip", _ubo_members())
    assert btf("ingest", archive, tmp_path / "s.zarr", "--srgb", "--quiet").code == 0
    result = btf("ingest", archive, tmp_path / "t.zarr", "--srgb", "--decode", "none",
                 "--quiet")
    assert result.code != 0 and "--srgb" in result.err
    assert no_partial_outputs(tmp_path / "t.zarr")


# --- ATRIUM HDR ------------------------------------------------------------------------------

def _rgbe_pixels(values: np.ndarray) -> np.ndarray:
    """RGBE bytes (..., 4) of float values: the shared exponent of the largest component."""
    top = values.max(axis=-1)
    mantissa, exponent = np.frexp(top)  # top = mantissa * 2**exponent, 0.5 <= mantissa < 1
    scale = np.where(top > 1e-32, mantissa * 256.0 / np.where(top > 0, top, 1), 0.0)
    rgb = np.floor(values * scale[..., None]).clip(0, 255)
    e = np.where(top > 1e-32, exponent + 128, 0)
    return np.concatenate([rgb, e[..., None]], axis=-1).astype(np.uint8)


def _rle_row(row: np.ndarray) -> bytes:
    """One new-style RLE scanline: 2, 2, width, then each channel in literal runs of <= 128."""
    out = bytearray([2, 2, len(row) >> 8, len(row) & 255])
    for c in range(4):
        channel = row[:, c].tobytes()
        for start in range(0, len(channel), 128):
            piece = channel[start:start + 128]
            out += bytes([len(piece)]) + piece
    return bytes(out)


def _atrium_hdr(picture: np.ndarray, *, rle: bool) -> bytes:
    """An ATRIUM-style .hdr: '+X W -Y H', rows stored bottom row first."""
    rows = _rgbe_pixels(picture)[::-1]
    header = f"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\nEXPOSURE=1\n\n+X {W} -Y {H}\n".encode()
    body = b"".join(_rle_row(r) for r in rows) if rle else rows.tobytes()
    return header + body


def _hdr_picture(k: int) -> np.ndarray:
    return _picture(k).astype(np.float32) / 16.0 + 0.25  # HDR values above 1


@pytest.mark.parametrize("rle", [False, True])
def test_atrium_hdr_zip_is_read_linear_and_bottom_up(tmp_path, btf, rle):
    members = {_bonn_name(angles, k, "hdr"): _atrium_hdr(_hdr_picture(k), rle=rle)
               for _, _, k, angles in _grid()}
    archive = _ubo_zip(tmp_path / "ATRIUM_HDR.zip", members)
    assert btf("ingest", archive, tmp_path / "s.zarr", "--quiet").code == 0
    values, coords, _ = _values(tmp_path / "s.zarr")
    assert values.shape == (2, 3, H, W, 3) and coords["phi_light"] == [0, 60, 300]
    for v, li, k, _ in _grid():
        # RGBE keeps 8 bits of mantissa: within 1/128 of the value, far from a flipped picture
        assert np.allclose(values[v, li], _hdr_picture(k), rtol=1 / 128), (v, li)
    assert btf("ingest", archive, tmp_path / "t.zarr", "--hdr-rows", "top-down",
               "--quiet").code == 0
    flipped, _, _ = _values(tmp_path / "t.zarr")
    assert np.array_equal(flipped[:, :, ::-1], values)


# --- UTIA folders ------------------------------------------------------------------------------

def _utia_name(angles, suffix):
    tl, pl, tv, pv = angles
    return f"tl{tl:03d}_pl{pl:03d}_tv{tv:03d}_pv{pv:03d}.{suffix}"


def _utia_folder(tmp_path, write, suffix):
    src = tmp_path / "utia"
    for _, _, k, angles in _grid():
        folder = src / f"tv{angles[2]:03d}_pv{angles[3]:03d}"  # a folder per view
        folder.mkdir(parents=True, exist_ok=True)
        write(folder / _utia_name(angles, suffix), k)
    return src


def test_utia_png_folder_per_view_is_decoded_from_srgb(tmp_path, btf):
    src = _utia_folder(tmp_path, lambda path, k: write_png(path, _picture(k)), "png")
    assert btf("ingest", src, tmp_path / "s.zarr", "--quiet").code == 0
    values, coords, channels = _values(tmp_path / "s.zarr")
    assert channels == ["R", "G", "B"] and coords["theta_view"] == [0, 30]
    assert stored_dtype(tmp_path / "s.zarr") == "float16"  # 8-bit codes: float16 holds them
    for v, li, k, _ in _grid():
        assert np.allclose(values[v, li], _srgb(_picture(k) / 255), rtol=HALF_ROUNDING,
                           atol=1e-7)


# XYZ (D65) -> linear sRGB, IEC 61966-2-1 (written out here, not taken from the pipeline)
_M = np.array([[3.2404542, -1.5371385, -0.4985314], [-0.9692660, 1.8760108, 0.0415560],
               [0.0556434, -0.2040259, 1.0572252]])


def _xyz(k: int) -> np.ndarray:
    return (_picture(k) / 200.0).astype(np.float16)


@pytest.mark.parametrize("names", [("X", "Y", "Z"), ("R", "G", "B")])
def test_utia_xyz_exr_folder_becomes_linear_srgb_or_stays_xyz(tmp_path, btf, names):
    src = _utia_folder(tmp_path, lambda path, k: write_exr(path, _xyz(k), names, half=True),
                       "exr")
    assert btf("ingest", src, tmp_path / "s.zarr", "--quiet").code == 0
    values, _, channels = _values(tmp_path / "s.zarr")
    assert channels == ["R", "G", "B"]
    for v, li, k, _ in _grid():
        expected = _xyz(k).astype(np.float64) @ _M.T
        assert np.allclose(values[v, li], expected, rtol=HALF_ROUNDING, atol=1e-5), (v, li)
    assert "XYZ" in zarr.open_group(tmp_path / "s.zarr").attrs["ingest"]["colour"]
    assert btf("ingest", src, tmp_path / "k.zarr", "--xyz", "keep", "--quiet").code == 0
    kept, _, channels = _values(tmp_path / "k.zarr")
    assert channels == ["X", "Y", "Z"]
    assert np.array_equal(kept[1, 2], _xyz(5).astype(np.float32))
    # --xyz none: the channels as named, all three of them
    assert btf("ingest", src, tmp_path / "n.zarr", "--xyz", "none", "--quiet").code == 0
    raw, _, channels = _values(tmp_path / "n.zarr")
    assert channels == list(names)
    assert np.array_equal(raw[1, 2], _xyz(5).astype(np.float32))


# --- UTIA BIG -----------------------------------------------------------------------------

def _chunk(cid: int, payload: bytes) -> bytes:
    pad = -len(payload) % 8
    return struct.pack("<QQ", cid, len(payload) + pad) + payload + b"\0" * pad


def _big(path, *, dtype="<f2", type_id=1, radians=True, list_id=True, images=None,
         order=(1, 2, 3, 4, 5)):
    grid = _grid()
    pictures = [_picture(k).astype(np.float32) / 100 for _, _, k, _ in grid]
    angles = np.array([a for *_, a in grid], np.float64)
    if radians:
        angles = np.radians(angles)
    directions = (struct.pack("<Q", 3) if list_id else b"") + angles.astype("<f8").tobytes()
    data = b"".join(p.astype(dtype).tobytes() for p in pictures)
    body = b"".join([
        _chunk(1, struct.pack("<Q", images or len(grid))), _chunk(3, struct.pack("<Q", H)),
        _chunk(4, struct.pack("<Q", W)), _chunk(5, struct.pack("<Q", 3)),
        _chunk(6, struct.pack(f"<{len(order)}Q", *order)),
        _chunk(7, struct.pack("<Q", type_id)), _chunk(16, directions), _chunk(8, data)])
    path.write_bytes(b"BIG\0\0\0\0\0" + body)
    return path, pictures


@pytest.mark.parametrize(("dtype", "type_id", "radians", "list_id"),
                         [("<f2", 1, True, True), ("<f4", 2, False, False)])
def test_big_file_is_read_image_by_image_with_its_directions(tmp_path, btf, dtype, type_id,
                                                             radians, list_id):
    path, pictures = _big(tmp_path / "m.big", dtype=dtype, type_id=type_id, radians=radians,
                          list_id=list_id)
    assert btf("ingest", path, tmp_path / "s.zarr", "--quiet").code == 0
    values, coords, channels = _values(tmp_path / "s.zarr")
    assert channels == ["R", "G", "B"] and values.shape == (2, 3, H, W, 3)
    assert coords == {"theta_view": [0, 30], "phi_view": [0, 90], "theta_light": [0, 15, 45],
                      "phi_light": [0, 60, 300]}
    for (v, li, _, _), picture in zip(_grid(), pictures, strict=True):
        assert np.array_equal(values[v, li], picture.astype(dtype).astype(np.float32))
    unit = "radians" if radians else "degrees"
    assert unit in zarr.open_group(tmp_path / "s.zarr").attrs["ingest"]["directions"]


# --- errors: one message naming the file or member, exit 1, nothing at OUT -----------------

def _zip_bad_name(tmp_path):
    members = _ubo_members()
    members["UBO2003/MANYFILES/tv000_pv000/picture.jpg"] = _jpeg(_picture(0))
    return _ubo_zip(tmp_path / "a.zip", members), "picture.jpg", "name does not end in"


def _zip_missing(tmp_path):
    members = _ubo_members()
    del members[_bonn_name(_grid()[4][3], 4)]
    return _ubo_zip(tmp_path / "a.zip", members), "a.zip", "no image for light 15/60"


def _zip_twice(tmp_path):
    members = _ubo_members()
    members[_bonn_name(_grid()[2][3], 99)] = _jpeg(_picture(0))  # index 99: same directions
    return _ubo_zip(tmp_path / "a.zip", members), "00099 tl045", "same directions as"


def _zip_wrong_size(tmp_path):
    members = _ubo_members()
    name = _bonn_name(_grid()[5][3], 5)
    members[name] = _jpeg(np.zeros((H, W + 2, 3), np.uint8))
    return _ubo_zip(tmp_path / "a.zip", members), name, f"image of {H}x{W + 2}"


def _zip_corrupt_jpeg(tmp_path):
    members = _ubo_members()
    name = _bonn_name(_grid()[3][3], 3)
    members[name] = members[name][:50]
    return _ubo_zip(tmp_path / "a.zip", members), name, "corrupt JPEG"


def _not_a_zip(tmp_path):
    (tmp_path / "a.zip").write_bytes(b"PK\x03\x04 and then nothing useful")
    return tmp_path / "a.zip", "a.zip", "not a readable zip archive"


def _big_truncated(tmp_path):
    path, _ = _big(tmp_path / "m.big")
    path.write_bytes(path.read_bytes()[:-100])
    return path, "m.big", "truncated"


def _big_magic(tmp_path):
    path, _ = _big(tmp_path / "m.big")
    path.write_bytes(b"BIG\0\0\0\0\1" + path.read_bytes()[8:])
    return path, "m.big", "not a BIG file"


def _big_type(tmp_path):
    path, _ = _big(tmp_path / "m.big", type_id=5)
    return path, "m.big", "data type 5 (unsigned char) is not supported"


def _big_count(tmp_path):
    path, _ = _big(tmp_path / "m.big", images=7)
    return path, "m.big", "the number of images or their size disagrees with the data"


def _big_order(tmp_path):
    path, _ = _big(tmp_path / "m.big", order=(3, 1, 4, 5))
    return path, "m.big", "data order row, image, pixel, plane is not supported"


@pytest.mark.parametrize("damage", [_zip_bad_name, _zip_missing, _zip_twice, _zip_wrong_size,
                                    _zip_corrupt_jpeg, _not_a_zip, _big_truncated, _big_magic,
                                    _big_type, _big_count, _big_order])
def test_bad_archives_name_the_member_and_leave_nothing(tmp_path, btf, damage):
    src, where, what = damage(tmp_path)
    out = tmp_path / "out.zarr"
    result = btf("ingest", src, out, "--quiet")
    assert result.code == 1, result.err
    assert where in result.err and what in result.err, result.err
    assert result.err.count("error") <= 1 and "Traceback" not in result.err
    assert no_partial_outputs(out)


def test_angles_of_a_big_file_in_radians_and_degrees_agree():
    from tasks.container_formats import angles_in_degrees

    degrees = np.array([[0, 0, 75, 345], [15, 60, 30, 90]], np.float64)
    back, unit = angles_in_degrees(np.radians(degrees))
    assert unit == "radians" and np.array_equal(back, degrees)
    same, unit = angles_in_degrees(degrees)
    assert unit == "degrees" and same is not None and np.array_equal(same, degrees)
    assert math.isclose(angles_in_degrees(np.array([math.pi / 2]))[0][0], 90.0)


# --- resume -----------------------------------------------------------------------------------

class Crash(Exception):
    pass


@pytest.mark.parametrize("route", ["whole images", "staged"])
def test_a_killed_zip_ingest_resumes_with_the_images_left(tmp_path, btf, monkeypatch, route):
    import pipeline.sources.zip as sources

    if route == "staged":  # layers larger than a task block go through the scratch array
        monkeypatch.setattr("pipeline.graphs.blocks.TASK_TEXELS", 4)
    archive = _ubo_zip(tmp_path / "a.zip", _ubo_members())
    args = ("ingest", archive, tmp_path / "out.zarr", "--scheduler", "synchronous",
            "--dir-chunk", "1", "--chunk", "8")
    assert btf(*args[:2], tmp_path / "ref.zarr", *args[3:], "--quiet").code == 0
    reads, real = [], sources.read_member

    def read(path, member, fail_after=None):
        if fail_after is not None and len(reads) >= fail_after:
            raise Crash("killed")
        reads.append(member)
        return real(path, member)

    with monkeypatch.context() as m:  # the 4th read dies: the first image (sizes) + 2 layers
        m.setattr(sources, "read_member", lambda p, n: read(p, n, fail_after=3))
        m.setattr("pipeline.atomic._remove", lambda path: None)  # as kill -9 leaves it
        with pytest.raises(Crash):
            btf(*args, "--quiet")
    (partial,) = tmp_path.glob(".out.resume-*")
    assert (partial / "_staging").is_dir() == (route == "staged")
    assert not (tmp_path / "out.zarr").exists()
    reads.clear()
    with monkeypatch.context() as m:
        m.setattr(sources, "read_member", lambda p, n: read(p, n))
        result = btf(*args)
    assert result.code == 0 and "resuming" in result.err, result.err
    assert len(reads) == 1 + len(_grid()) - 2  # the first image, then the layers left
    assert np.array_equal(_values(tmp_path / "out.zarr")[0], _values(tmp_path / "ref.zarr")[0])
    assert not list(tmp_path.glob(".out.resume-*"))
    assert "_staging" not in zarr.open_group(tmp_path / "out.zarr").array_keys()


# --- pure parsers ----------------------------------------------------------------------------

@pytest.mark.parametrize(("line", "rows", "flip_rows", "flip_columns"), [
    ("-Y 8 +X 12", "bottom-up", False, False),  # the standard orientation
    ("+Y 8 +X 12", "bottom-up", True, False),
    ("-Y 8 -X 12", "bottom-up", False, True),
    ("+X 12 -Y 8", "bottom-up", True, False),  # ATRIUM's header, read as btf-extractor does
    ("+X 12 -Y 8", "top-down", False, False),
])
def test_rgbe_resolution_lines(line, rows, flip_rows, flip_columns):
    from tasks.container_formats import parse_rgbe_header

    data = f"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n{line}\n".encode() + b"\0" * 8
    header = parse_rgbe_header(data, atrium_rows=rows)
    assert (header.height, header.width) == (8, 12)
    assert (header.flip_rows, header.flip_columns) == (flip_rows, flip_columns)
    assert data[header.offset:] == b"\0" * 8


@pytest.mark.parametrize(("text", "message"), [
    ("#?RADIANCE\nFORMAT=32-bit_rle_xyze\n\n-Y 8 +X 12\n", "32-bit_rle_xyze"),
    ("#?RADIANCE\n\n+X 12 +Y 8\n", "stores columns"),
    ("#?RADIANCE\n\n-Y 8 +Y 12\n", "one X and one Y"),
    ("P6\n12 8\n255\n", "does not start with '#?'"),
    ("#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n", "no end of the RGBE header"),
])
def test_rgbe_headers_refused(text, message):
    from tasks.container_formats import FormatError, parse_rgbe_header

    with pytest.raises(FormatError, match=re.escape(message)):
        parse_rgbe_header(text.encode())


def test_big_prefers_spherical_directions_and_names_missing_chunks():
    from tasks.container_formats import FormatError, big_layout

    n = 2
    sizes = {1: struct.pack("<Q", n), 3: struct.pack("<Q", 1), 4: struct.pack("<Q", 1)}
    device = struct.pack("<Q", 1) + np.full(4 * n, 7.0).tobytes()
    spherical = struct.pack("<Q", 3) + np.array([0, 0, 10, 20, 30, 40, 50, 60.0]).tobytes()
    chunks = {k: [v] for k, v in sizes.items()} | {16: [device, spherical]}
    layout = big_layout(chunks, (100, n * 4))
    assert layout.direction_list == "ideal spherical angles" and layout.angle_unit == "degrees"
    assert layout.directions.tolist() == [[0, 0, 10, 20], [30, 40, 50, 60]]
    assert layout.dtype == "<f4" and layout.planes == 1  # BIG's defaults: float, one plane
    with pytest.raises(FormatError, match="no chunk 'image height'"):
        big_layout({1: [sizes[1]], 4: [sizes[4]]}, (100, 8))
    with pytest.raises(FormatError, match="no list of directions"):
        big_layout({k: [v] for k, v in sizes.items()}, (100, 8))


def test_archive_names():
    from tasks.archive_names import bonn_angles, utia_angles

    assert bonn_angles("UBO2003/MANYFILES/tv030_pv030/00008 tl000 pl000 tv030 pv030.jpg") == (
        0, 0, 30, 30)
    assert bonn_angles("tl075 pl345 tv060 pv018.hdr") == (75, 345, 60, 18)
    assert bonn_angles("UBO2003/tv030_pv030/tl000_pl000_tv030_pv030.jpg") is None
    assert utia_angles("tv000_pv000/tl015_pl060_tv000_pv000.png") == (15, 60, 0, 0)
    assert utia_angles("tl15_pl60_tv0_pv0.png") is None  # btf export's names, not UTIA's


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("decoding", ["srgb", "gamma2.2", "none"])
def test_display_codes_become_the_curve_of_their_value(dtype, decoding):
    from tasks.colour import decode_display, decode_values

    top = np.iinfo(dtype).max
    codes = np.random.default_rng(3).permutation(np.arange(top + 1, dtype=dtype))
    pixels = codes[: (top + 1) // 3 * 3].reshape(-1, 1, 3)[::-1]  # any order, not contiguous
    want = decode_values(pixels.astype(np.float64) / top, decoding)
    got = decode_display(pixels, decoding)
    assert got.dtype == np.float32 and got.shape == pixels.shape
    assert np.allclose(got, want, rtol=2e-6, atol=1e-7)
