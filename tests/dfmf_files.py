"""Small Bonn UBO2014 DFMF ``.btf`` files for tests, written from the format description.

Independent of the project's code on purpose (no ``pipeline`` import): a test oracle for the
DFMF reader and exporter. Byte layout (little-endian), as Bonn's own readers (cgbonn/btflib,
``btf.hh``) read it:

- signature ``!DFMF08FC`` (+ ``R`` when a rotations block follows the image size);
- metadata: ``u32`` size in bytes (this field included), ``u32`` version, 3 x ``char[80]``,
  ``f32`` ppmm, ``f32[3]`` RGB scale; version > 1: ``u32`` cosine flag; > 2: ``u32 n`` + n
  bytes of XML; > 3: ``u32`` channel count, per channel ``u32 n`` + n bytes of its name;
- ``u32 nV``; per view ``f32 theta, f32 phi`` (radians), ``u32 nL``, nL x ``(f32, f32)``;
- ``u32 width, u32 height``; with ``R``: ``u32 n`` + n row-major 3x3 ``f32`` matrices;
- ``u32`` component count (max k), ``i32`` colour model, ``f32[3]`` colour mean,
  ``f32[9]`` colour matrix (row-major);
- per channel: ``u8`` scalar size (2, 4, 8), ``u32 k``, ``u32 rows`` (nV x nL, light index
  fastest), ``u32 cols`` (width x height, x fastest), k singular values, ``U`` rows x k,
  ``S x V`` cols x k (row-major); the file ends there.

``reference_decode`` follows btflib's ``undecorrelate.m`` (colour models 0, 1, 3, 4, 9-12).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from pathlib import Path

import numpy as np

SIGNATURE = b"!DFMF08FC"
SCALAR_DTYPES = {2: "<f2", 4: "<f4", 8: "<f8"}
EPS = 1e-5  # fixed by Bonn's readers, not stored in the file
YUV_TO_RGB = np.array([[1.0, 0.0, 1.13983], [1.0, -0.39465, -0.5806], [1.0, 2.03211, 0.0]])
YCOCG_TO_RGB = np.array([[1.0, 1.0, -1.0], [1.0, 0.0, 1.0], [1.0, -1.0, -1.0]])


def _u32(n: int) -> bytes:
    return struct.pack("<I", n)


def _text(s: str | bytes) -> bytes:
    return s.encode() if isinstance(s, str) else s


def _fixed(s: str | bytes, n: int = 80) -> bytes:
    b = _text(s)[:n]
    return b + b"\0" * (n - len(b))


def _angles(dirs) -> bytes:
    return np.asarray(dirs, dtype="<f4").reshape(-1, 2).tobytes()


def write_dfmf(path, *, views: Sequence[tuple[float, float]],
               lights: Sequence[tuple[float, float]], u: Sequence[np.ndarray],
               sxv: Sequence[np.ndarray], width: int, height: int,
               s: Sequence[np.ndarray] | None = None, color_model: int = 0,
               scalar_size: int = 2, version: int = 4,
               channel_names: Sequence[str] = ("R", "G", "B"),
               rotations: bool | np.ndarray = False, cosine: bool = False,
               color_mean=(0.0, 0.0, 0.0), color_matrix=None, xml: str = "",
               setup: str = "test setup", sensor: str = "test sensor",
               light_source: str = "test light", ppmm: float = 10.0,
               rgb_scale=(1.0, 1.0, 1.0), n_components: int | None = None,
               light_lists: Sequence[Sequence[tuple[float, float]]] | None = None,
               signature: bytes | None = None, metadata_size_delta: int = 0,
               trailing: bytes = b"", transposed: bool = False) -> Path:
    """Write a DFMF ``.btf`` file; return its path.

    ``views``/``lights``: (theta, phi) in radians, as stored. ``u[c]``: (nV * nL, k_c), light
    index fastest; ``sxv[c]``: (width * height, k_c), texel ``y * width + x`` (``y`` from the
    bottom of the picture, as Bonn writes them; see :func:`reference_decode`). ``s[c]``: the
    k_c singular values (default: column norms of ``sxv[c]``; readers ignore them).
    ``rotations``: False, True (one identity per view) or an (n, 3, 3) array.

    For error tests: ``light_lists`` (one light list per view, overriding ``lights`` in the
    sampling block only), ``signature`` (replaces ``!DFMF08FC``), ``metadata_size_delta``
    (added to the stored metadata size), ``trailing`` (bytes appended after the data).
    ``transposed``: each channel stores its texels' matrix first (its head then says rows =
    texels, columns = views x lights), a layout btflib's ``decode_dfmf_texel.m`` also reads.
    """
    dtype = np.dtype(SCALAR_DTYPES[scalar_size])
    n_views, n_lights = len(views), len(lights)
    if len(u) != len(sxv):
        raise ValueError("u and sxv need one matrix per channel")
    if color_matrix is None:
        color_matrix = np.eye(3)

    meta = _u32(version) + _fixed(setup) + _fixed(sensor) + _fixed(light_source)
    meta += struct.pack("<f", ppmm) + np.asarray(rgb_scale, "<f4").tobytes()
    if version > 1:
        meta += _u32(int(cosine))
    if version > 2:
        meta += _u32(len(_text(xml))) + _text(xml)
    if version > 3:
        meta += _u32(len(channel_names))
        for name in channel_names:
            meta += _u32(len(_text(name))) + _text(name)
    meta = _u32(len(meta) + 4 + metadata_size_delta) + meta

    if rotations is True:
        rotations = np.broadcast_to(np.eye(3), (n_views, 3, 3))
    has_rot = rotations is not False and rotations is not None

    sampling = _u32(n_views)
    lists = light_lists if light_lists is not None else [lights] * n_views
    for view, ls in zip(views, lists, strict=True):
        sampling += _angles([view]) + _u32(len(ls)) + _angles(ls)
    sampling += _u32(width) + _u32(height)
    if has_rot:
        rot = np.asarray(rotations, "<f4").reshape(-1, 3, 3)
        sampling += _u32(len(rot)) + rot.tobytes()

    ks = [np.shape(m)[1] for m in u]
    block = _u32(max(ks) if n_components is None else n_components)
    block += struct.pack("<i", color_model) + np.asarray(color_mean, "<f4").tobytes()
    block += np.asarray(color_matrix, "<f4").reshape(9).tobytes()
    chunks = [block]
    for c, (uc, vc) in enumerate(zip(u, sxv, strict=True)):
        uc, vc = np.asarray(uc), np.asarray(vc)
        k = uc.shape[1]
        if uc.shape != (n_views * n_lights, k) or vc.shape != (width * height, k):
            raise ValueError(f"channel {c}: U {uc.shape}, SxV {vc.shape} do not fit")
        sc = np.linalg.norm(vc, axis=0) if s is None else np.asarray(s[c])
        first, second = (vc, uc) if transposed else (uc, vc)
        chunks.append(struct.pack("<B", scalar_size) + _u32(k) + _u32(first.shape[0])
                      + _u32(second.shape[0]))
        for m in (sc, first, second):
            chunks.append(np.ascontiguousarray(m, dtype=dtype).tobytes())

    path = Path(path)
    sig = SIGNATURE if signature is None else signature
    with open(path, "wb") as f:
        f.write(sig + (b"R" if has_rot else b"") + meta + sampling + b"".join(chunks) + trailing)
    return path


def truncated_copy(src, dst, *, drop: int = 1) -> Path:
    """Copy ``src`` to ``dst`` without its last ``drop`` bytes."""
    data = Path(src).read_bytes()
    Path(dst).write_bytes(data[: len(data) - drop])
    return Path(dst)


def resigned_copy(src, dst, signature: bytes = b"!DFMF09FC") -> Path:
    """Copy ``src`` to ``dst`` with its first ``len(signature)`` bytes replaced."""
    data = Path(src).read_bytes()
    Path(dst).write_bytes(signature + data[len(signature):])
    return Path(dst)


def reference_decode(u, sxv, *, color_model: int, width: int, height: int,
                     lights: Sequence[tuple[float, float]], eps: float = EPS,
                     color_mean=(0.0, 0.0, 0.0), color_matrix=None,
                     cosine: bool = False) -> np.ndarray:
    """Radiance (views, lights, height, width, channels), float64, as btflib decodes it.

    ``c_ch = U_ch @ SxV_ch.T`` per channel, then ``undecorrelate.m``'s colour model, then, with
    ``cosine``, a division by cos(theta_light) (``lights`` in radians, as stored). The images
    are upright: texel ``y * width + x`` of a file counts rows from the bottom (btf-extractor
    reverses them to make its images), so the file's last texel row is the image's row 0.
    """
    n_lights = len(lights)
    vals = np.stack([np.asarray(a, np.float64) @ np.asarray(b, np.float64).T
                     for a, b in zip(u, sxv, strict=True)], axis=-1)  # (rows, texels, C)
    if color_model == 0:
        pass
    elif color_model == 1:
        vals = vals @ YUV_TO_RGB.T
    elif color_model == 3:
        m = np.eye(3) if color_matrix is None else np.asarray(color_matrix, np.float64)
        vals = vals @ m.reshape(3, 3) + np.asarray(color_mean, np.float64)
    elif color_model == 4:
        vals = vals @ YCOCG_TO_RGB.T
    elif color_model in (9, 10, 11):
        y = np.exp(vals[..., 0]) - eps
        if color_model == 9:
            uv = vals[..., 1:]
        elif color_model == 10:
            uv = np.sign(vals[..., 1:]) * np.exp(np.abs(vals[..., 1:]) + np.log(eps))
        else:
            uv = vals[..., 1:] * (y + eps)[..., None]
        vals = np.concatenate([y[..., None], uv], axis=-1) @ YUV_TO_RGB.T
    elif color_model == 12:
        vals = np.exp(vals) - eps
    else:
        raise ValueError(f"unsupported colour model {color_model}")
    out = vals.reshape(-1, n_lights, height, width, vals.shape[-1])
    if cosine:
        theta_l = np.asarray(lights, np.float64).reshape(-1, 2)[:, 0]
        out = out / np.cos(theta_l)[None, :, None, None, None]
    return out[:, :, ::-1]
