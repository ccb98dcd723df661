"""Bonn's DFMF ``.btf`` files (UBO2014): the header, and the file's factors as an exact SVD.

A DFMF file ("decorrelated full matrix factorization") holds a BTF as one factorization per
colour channel after a colour transform: channel ``c``'s values are ``U_c (S V)_c^T`` with one
row per (view, light), light fastest, and one column per texel ``y * width + x``. The layout,
from Bonn's readers (cgbonn/btflib ``read_ubo_dfmf.m``, ``read_meta_data.m``,
``read_bidir_sampling.m``; the ``btf.hh`` decoder), all little-endian:

- signature ``!DFMF08FC``, then ``R`` if a rotations block follows the image size;
- metadata: ``u32`` its own size in bytes (this field included), ``u32`` version, three
  ``char[80]`` (measurement setup, image sensor, light source), ``f32`` ppmm, ``f32[3]`` RGB
  scale; version > 1: ``u32`` cosine flag; > 2: ``u32 n`` and ``n`` bytes of XML; > 3:
  ``u32`` channel count and per channel ``u32 n`` and its name (else R, G, B);
- sampling: ``u32`` views; per view ``f32 theta, f32 phi`` (radians), ``u32`` lights and their
  ``(theta, phi)`` list, the same for every view;
- ``u32`` width, ``u32`` height; with ``R``: ``u32 n`` and ``n`` 3 x 3 ``f32`` matrices;
- ``u32`` component count, ``i32`` colour model, ``f32[3]`` colour mean, ``f32[9]`` colour
  matrix (row-major);
- per channel: ``u8`` scalar size (2: float16, 4: float32, 8: float64), ``u32 k``, ``u32``
  rows, ``u32`` columns, ``k`` singular values, ``U`` (rows x k), ``S V`` (columns x k),
  row-major; the file ends there.

:func:`parse_header` reads all of it but the matrices (whose offsets it returns) through a
``read(offset, size)`` callable, so the caller decides how bytes are fetched.
:func:`header_bytes` writes the same layout. :func:`joint_u` and :func:`svd_map` turn the
per-channel factors into one orthonormal ``U``, decreasing ``S`` and a ``k x K`` map from the
file's ``S V`` rows to ``V`` (:mod:`tasks.transform` decodes the values).
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from tasks.transform import DFMF_MODELS, dfmf_colour_matrix

DFMF = b"!DFMF08FC"
# Bonn's other signatures: recognised, so that they are refused by name
OTHER_SIGNATURES = {b"!FMF12FCE": "FMF12 (one joint factorization, extended header)",
                    b"!FMF06FC": "FMF06 (one joint factorization)",
                    b"!PVF06FC": "PVF06 (per-view factorizations)",
                    b"!BDIF06R2!": "BDIF06 (uncompressed, in chunks)"}
SCALARS = {2: np.dtype("<f2"), 4: np.dtype("<f4"), 8: np.dtype("<f8")}
# btflib's colour models (undecorrelate.m) that btf does not decode: not linear in the values,
# and not among its transforms
UNREAD_MODELS = {2: "LAB, decoded by MATLAB's lab2srgb to display sRGB",
                 5: "SPECTRAL: channel ratios times a sum", 6: "SPECTRAL_LINEAR"}
_CHANNEL_HEAD = struct.Struct("<BIII")
MAX_TEXT = 1 << 24  # an XML string or channel name longer than this is corrupt


class DfmfError(ValueError):
    """A file that is not a readable DFMF file; the message says what and at which byte."""


@dataclass(frozen=True)
class ChannelBlock:
    """Where one channel's factors are: ``k`` components, byte offsets of S, U and S V.

    ``u_offset`` is always the (view, light) rows' matrix (``rows`` x ``k``) and ``sxv_offset``
    the texels' (``columns`` x ``k``): a file that stores them the other way round (texels
    first, which btflib also reads) has them swapped here, so readers need not know.
    """

    scalar: int  # bytes per value
    k: int
    rows: int
    columns: int
    s_offset: int
    u_offset: int
    sxv_offset: int

    @property
    def dtype(self) -> np.dtype:
        """The values' dtype (little-endian float16, float32 or float64)."""
        return SCALARS[self.scalar]

    @property
    def end(self) -> int:
        """The byte after this channel's last value."""
        return max(self.sxv_offset + self.columns * self.k * self.scalar,
                   self.u_offset + self.rows * self.k * self.scalar)


@dataclass(frozen=True)
class DfmfHeader:
    """Everything of a DFMF file but its matrices. Angles are radians, as stored."""

    version: int
    rotations: int
    measurement_setup: str
    image_sensor: str
    light_source: str
    ppmm: float
    rgb_scale: tuple[float, float, float]
    cosine: bool
    xml: str
    channel_names: tuple[str, ...]
    theta_view: np.ndarray = field(repr=False)
    phi_view: np.ndarray = field(repr=False)
    theta_light: np.ndarray = field(repr=False)
    phi_light: np.ndarray = field(repr=False)
    width: int
    height: int
    components: int
    colour_model: int
    colour_mean: tuple[float, ...]
    colour_matrix: tuple[tuple[float, ...], ...]
    channels: tuple[ChannelBlock, ...]
    # what a reader tolerated where Bonn's readers differ (light lists, layout, trailing bytes)
    notes: tuple[str, ...] = ()

    @property
    def end(self) -> int:
        """The file's size as the header describes it."""
        return self.channels[-1].end

    def metadata(self) -> dict:
        """The header's descriptive fields as JSON-able values (kept in a store's attrs)."""
        return {"version": self.version, "measurement_setup": self.measurement_setup,
                "image_sensor": self.image_sensor, "light_source": self.light_source,
                "ppmm": self.ppmm, "rgb_scale": list(self.rgb_scale), "cosine": self.cosine,
                "xml": self.xml, "channel_names": list(self.channel_names),
                "colour_model": self.colour_model, "colour_mean": list(self.colour_mean),
                "colour_matrix": [list(r) for r in self.colour_matrix],
                "components": [c.k for c in self.channels],
                "scalar_bytes": self.channels[0].scalar, "rotations": self.rotations,
                **({"notes": list(self.notes)} if self.notes else {})}


class _Cursor:
    """Sequential reads through ``read(offset, size)``, with the offset in every error."""

    def __init__(self, read: Callable[[int, int], bytes], size: int, offset: int = 0):
        self.read, self.size, self.offset = read, size, offset

    def take(self, n: int, what: str) -> bytes:
        if self.offset + n > self.size:
            raise DfmfError(f"truncated: {what} needs bytes {self.offset} to {self.offset + n}, "
                            f"but the file has {self.size}")
        data = self.read(self.offset, n)
        if len(data) != n:
            raise DfmfError(f"truncated: {what} at byte {self.offset} could not be read whole")
        self.offset += n
        return data

    def unpack(self, fmt: str, what: str):
        s = struct.Struct("<" + fmt)
        return s.unpack(self.take(s.size, what))

    def text(self, what: str) -> str:
        (n,) = self.unpack("I", f"the length of {what}")
        if n > MAX_TEXT:
            raise DfmfError(f"{what} at byte {self.offset - 4} claims {n} bytes: corrupt header")
        return self.take(n, what).split(b"\0", 1)[0].decode("latin-1")


def _c_string(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("latin-1").strip()


def _metadata(cur: _Cursor) -> dict:
    start = cur.offset
    size, version = cur.unpack("II", "the metadata size and version")
    strings = [_c_string(cur.take(80, name)) for name in
               ("the measurement setup", "the image sensor", "the light source")]
    ppmm, *rgb = cur.unpack("4f", "ppmm and the RGB scale")
    out = {"version": version, "measurement_setup": strings[0], "image_sensor": strings[1],
           "light_source": strings[2], "ppmm": ppmm, "rgb_scale": tuple(rgb), "cosine": False,
           "xml": "", "channel_names": ("R", "G", "B")}
    if version > 1:
        out["cosine"] = bool(cur.unpack("I", "the cosine flag")[0])
    if version > 2:
        out["xml"] = cur.text("the XML string")
    if version > 3:
        (count,) = cur.unpack("I", "the channel count")
        if not 1 <= count <= 1024:
            raise DfmfError(f"the metadata names {count} channels: corrupt header")
        out["channel_names"] = tuple(cur.text(f"the name of channel {c}") for c in range(count))
    if cur.offset - start != size:
        raise DfmfError(f"the metadata block says it is {size} bytes, but version {version}'s "
                        f"fields take {cur.offset - start}")
    return out


def _sampling(cur: _Cursor) -> tuple[tuple[np.ndarray, ...], list[str]]:
    """The view and light directions, and a note if later views list other lights.

    Like btflib (``read_bidir_sampling.m``) and btf-extractor, the lights of view 0 are the
    file's: a later view with as many lights but other directions is read with view 0's (and
    noted, with how far they differ); another number of lights is refused, as they refuse it.
    """
    (views,) = cur.unpack("I", "the view count")
    if views == 0:
        raise DfmfError("the sampling has no views")
    view_angles, lights, differ = [], None, []
    for v in range(views):
        view_angles.append(cur.unpack("2f", f"the direction of view {v}"))
        (n,) = cur.unpack("I", f"the light count of view {v}")
        if n == 0:
            raise DfmfError(f"view {v} has no lights")
        these = np.frombuffer(cur.take(8 * n, f"the lights of view {v}"), "<f4").reshape(n, 2)
        if lights is None:
            lights = these
        elif these.shape != lights.shape:
            raise DfmfError(f"view {v} lists {n} lights where view 0 has {len(lights)}: Bonn's "
                            "readers (btflib, btf-extractor) and btf read only files with as "
                            "many lights for every view")
        elif not np.array_equal(these, lights):
            differ.append((v, float(np.degrees(_angle_between(these, lights)).max())))
    va = np.asarray(view_angles, np.float64)
    la = lights.astype(np.float64)
    notes = []
    if differ:
        worst = max(d for _, d in differ)
        notes.append(f"{len(differ)} view(s) (the first: view {differ[0][0]}) list other light "
                     f"directions than view 0, up to {worst:.3g} degrees apart: read with view "
                     "0's, as btflib and btf-extractor read them")
    return (va[:, 0], va[:, 1], la[:, 0], la[:, 1]), notes


def _angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles (radians) between ``(theta, phi)`` directions of two lists, pair by pair."""
    def unit(d):
        t, p = np.asarray(d, np.float64).T
        return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)

    return np.arccos(np.clip(np.sum(unit(a) * unit(b), axis=-1), -1.0, 1.0))


def _signature(head: bytes) -> bool:
    """Check the file's signature; whether a rotations block follows the image size.

    Bonn's other formats are refused by name.
    """
    if not head.startswith(DFMF):
        for sig, name in OTHER_SIGNATURES.items():
            if head.startswith(sig):
                raise DfmfError(f"a Bonn {name} file ({sig.decode()}): btf reads the DFMF "
                                "variant (!DFMF08FC) of Bonn's formats only")
        raise DfmfError(f"not a DFMF file: it starts with {head[:10]!r}, not {DFMF.decode()!r}")
    return head[len(DFMF) : len(DFMF) + 1] == b"R"


def _colour_model(cur: _Cursor, channel_names: tuple[str, ...]) -> tuple:
    """The component count, colour model, colour mean and colour matrix (flat), checked."""
    components, model = cur.unpack("Ii", "the component count and colour model")
    mean = cur.unpack("3f", "the colour mean")
    matrix = cur.unpack("9f", "the colour matrix")
    if model in UNREAD_MODELS:
        raise DfmfError(f"colour model {model} ({UNREAD_MODELS[model]}): btflib decodes it, "
                        f"btf does not yet (it reads {', '.join(map(str, DFMF_MODELS))}); "
                        "btflib can write the file's layers as images for btf ingest")
    if model not in DFMF_MODELS:
        raise DfmfError(f"unknown colour model {model} (btf reads "
                        f"{', '.join(map(str, DFMF_MODELS))}, btflib also 2, 5 and 6)")
    if model not in (0, 12) and len(channel_names) != 3:
        raise DfmfError(f"colour model {model} needs 3 channels, the metadata names "
                        f"{len(channel_names)} ({', '.join(channel_names)})")
    return components, model, mean, matrix


def _channel_block(cur: _Cursor, name: str, rows: int, columns: int,
                   size: int) -> tuple[ChannelBlock, bool]:
    """One channel's head, checked against the sampling and image size; the cursor skips it.

    Also whether the channel stores its texels' matrix first (btflib reads that layout too:
    its ``U`` then has a row per texel): the block's offsets are swapped to the usual roles.
    """
    scalar, k, r, cols = _CHANNEL_HEAD.unpack(cur.take(_CHANNEL_HEAD.size,
                                                       f"the header of channel {name}"))
    if scalar not in SCALARS:
        raise DfmfError(f"channel {name}: scalar size {scalar} at byte {cur.offset - 13} "
                        "(2, 4 or 8 expected)")
    transposed = (r, cols) == (columns, rows) and rows != columns
    if (r, cols) != (rows, columns) and not transposed:
        raise DfmfError(f"channel {name}: {r} rows x {cols} columns, but the sampling "
                        f"and image size give {rows} (views x lights) x {columns} texels")
    if k == 0:
        raise DfmfError(f"channel {name}: 0 components")
    first, second = cur.offset + k * scalar, cur.offset + (k + r * k) * scalar
    block = ChannelBlock(scalar, k, rows, columns, cur.offset,
                         second if transposed else first, first if transposed else second)
    if block.end > size:
        raise DfmfError(f"truncated: channel {name}'s factors end at byte {block.end}, "
                        f"but the file has {size} bytes")
    cur.offset = block.end
    return block, transposed


def parse_header(read: Callable[[int, int], bytes], size: int) -> DfmfHeader:
    """The header of a DFMF file of ``size`` bytes, read through ``read(offset, n)``.

    Raises
    ------
    DfmfError
        A wrong signature (Bonn's other formats named), a truncated file, a metadata size that
        does not match its fields (btflib refuses it too), views with other numbers of lights,
        a colour model btf does not decode, matrices whose shapes disagree with the sampling
        and image size. What Bonn's readers differ on is read as btflib reads it and said in
        the header's ``notes``: later views' light lists, channels stored texels first, bytes
        after the last channel, channels with more components than the file's count.
    """
    cur = _Cursor(read, size)
    rotations_block = _signature(read(0, min(size, 12)))
    cur.offset = len(DFMF) + rotations_block
    meta = _metadata(cur)
    (theta_view, phi_view, theta_light, phi_light), notes = _sampling(cur)
    width, height = cur.unpack("II", "the image size")
    if width == 0 or height == 0:
        raise DfmfError(f"the image size is {width} x {height}")
    rotations = 0
    if rotations_block:
        (rotations,) = cur.unpack("I", "the rotation count")
        cur.take(36 * rotations, f"{rotations} rotation matrices")
    components, model, mean, matrix = _colour_model(cur, meta["channel_names"])
    rows, columns = len(theta_view) * len(theta_light), width * height
    read = [_channel_block(cur, name, rows, columns, size) for name in meta["channel_names"]]
    blocks = [b for b, _ in read]
    swapped = [name for name, (_, t) in zip(meta["channel_names"], read, strict=True) if t]
    if swapped:
        notes.append(f"channel(s) {','.join(swapped)} store the texels' matrix first (a row "
                     "per texel, then one per view and light), as btflib also reads")
    if max(b.k for b in blocks) > components:
        notes.append(f"channels hold up to {max(b.k for b in blocks)} components where the "
                     f"file's count says {components}: each channel's own count is read, as "
                     "btflib reads it")
    if cur.offset != size:
        notes.append(f"{size - cur.offset} bytes after the last channel's factors (byte "
                     f"{cur.offset} on) are ignored, as btflib ignores them (btf.hh and "
                     "btf-extractor refuse such a file)")
    return DfmfHeader(
        version=meta["version"], rotations=rotations,
        measurement_setup=meta["measurement_setup"], image_sensor=meta["image_sensor"],
        light_source=meta["light_source"], ppmm=meta["ppmm"], rgb_scale=meta["rgb_scale"],
        cosine=meta["cosine"], xml=meta["xml"], channel_names=meta["channel_names"],
        theta_view=theta_view, phi_view=phi_view, theta_light=theta_light,
        phi_light=phi_light, width=width, height=height, components=components,
        colour_model=model, colour_mean=tuple(mean),
        colour_matrix=tuple(tuple(matrix[3 * i : 3 * i + 3]) for i in range(3)),
        channels=tuple(blocks), notes=tuple(notes))


def _text(s: str) -> bytes:
    data = s.encode("latin-1", "replace")
    return struct.pack("<I", len(data)) + data


def header_bytes(header: DfmfHeader) -> bytes:
    """The bytes of a DFMF file up to its first channel's factors (metadata version 4).

    ``header.channels`` gives each channel's scalar size and ``k``; the caller writes each
    channel's head (:func:`channel_head`), singular values, ``U`` and ``S V`` after it.
    """
    fixed = b"".join(s.encode("latin-1", "replace")[:79].ljust(80, b"\0") for s in
                     (header.measurement_setup, header.image_sensor, header.light_source))
    body = (struct.pack("<I", 4) + fixed + struct.pack("<4f", header.ppmm, *header.rgb_scale)
            + struct.pack("<I", int(header.cosine)) + _text(header.xml)
            + struct.pack("<I", len(header.channel_names))
            + b"".join(_text(n) for n in header.channel_names))
    meta = struct.pack("<I", len(body) + 4) + body
    lights = np.stack([header.theta_light, header.phi_light], -1).astype("<f4").tobytes()
    lights = struct.pack("<I", len(header.theta_light)) + lights
    sampling = struct.pack("<I", len(header.theta_view)) + b"".join(
        struct.pack("<2f", t, p) + lights
        for t, p in zip(header.theta_view, header.phi_view, strict=True))
    colour = (struct.pack("<Ii", header.components, header.colour_model)
              + struct.pack("<3f", *header.colour_mean)
              + struct.pack("<9f", *(x for row in header.colour_matrix for x in row)))
    return (DFMF + meta + sampling + struct.pack("<II", header.width, header.height)
            + colour)


def channel_head(block: ChannelBlock) -> bytes:
    """The bytes that open a channel: scalar size, ``k``, rows, columns."""
    return _CHANNEL_HEAD.pack(block.scalar, block.k, block.rows, block.columns)


def layout(start: int, scalar: int, ks: list[int], rows: int, columns: int
           ) -> tuple[ChannelBlock, ...]:
    """Offsets of channels with ``ks`` components written from byte ``start`` on."""
    blocks, offset = [], start
    for k in ks:
        s = offset + _CHANNEL_HEAD.size
        block = ChannelBlock(scalar, k, rows, columns, s, s + k * scalar,
                             s + (k + rows * k) * scalar)
        blocks.append(block)
        offset = block.end
    return tuple(blocks)


def joint_u(header: DfmfHeader, u: list[np.ndarray]) -> tuple[np.ndarray, bool]:
    """The file's factors as one matrix: ``U`` with rows (view, light, channel), and a flag.

    ``u`` holds each channel's ``U_c`` (rows x k_c). For the log and YUV colour models the
    channels stay apart: column block ``c`` is ``U_c`` on channel ``c``'s rows and 0
    elsewhere. For the linear models (0, 1, 3, 4) the colour matrix is applied
    (``radiance = values @ M + mean``): channel ``d``'s row gets ``U_c M[c, d]`` in column block
    ``c``, and a non-zero mean adds a last column (the flag says so) whose ``V`` is 1 on every
    texel. A set cosine flag divides the linear models' rows by ``cos(theta_light)``; with
    the non-linear models it comes after the colour model, so the store's transform keeps it
    (:attr:`tasks.transform.Transform.cosine`) and ``U`` is the file's.
    """
    name = DFMF_MODELS[header.colour_model][0]
    nc, views, lights = len(u), len(header.theta_view), len(header.theta_light)
    ks = [x.shape[1] for x in u]
    offsets = np.cumsum([0, *ks])
    if name != "linear":
        out = np.zeros((views * lights, nc, offsets[-1]))
        for c, uc in enumerate(u):
            out[:, c, offsets[c] : offsets[c + 1]] = uc
        return out.reshape(-1, offsets[-1]), False
    m, mean = dfmf_colour_matrix(header.colour_model, np.asarray(header.colour_matrix),
                                 np.asarray(header.colour_mean), nc)
    has_mean = bool(np.any(mean != 0))
    out = np.zeros((views * lights, nc, offsets[-1] + has_mean))
    for c, uc in enumerate(u):
        out[:, :, offsets[c] : offsets[c + 1]] = uc[:, None, :] * m[c][None, :, None]
    if has_mean:
        out[:, :, -1] = mean
    if header.cosine:
        cos = np.cos(np.asarray(header.theta_light, np.float64))
        out /= np.tile(np.maximum(cos, 1e-6), views)[:, None, None]
    return out.reshape(-1, out.shape[-1]), has_mean


def svd_map(u: np.ndarray, gram: np.ndarray, *, floor: float = 1e-14
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An exact SVD of ``u @ c^T`` from ``u`` and the Gram matrix ``c^T c`` of ``c``.

    With ``u = Q R`` and ``R c^T c R^T = W diag(S^2) W^T``: ``u c^T = (Q W) diag(S) V^T`` with
    ``V = c (R^T W / S)``. Returns ``U = Q W`` (orthonormal), ``S`` (decreasing) and the map
    ``R^T W / S`` that takes rows of ``c`` to rows of ``V`` (orthonormal). Components whose
    ``S^2`` is at most ``floor`` of the largest carry nothing and are dropped.
    """
    from scipy.linalg import qr

    q, r = qr(np.asarray(u, np.float64), mode="economic")
    evals, w = np.linalg.eigh(r @ np.asarray(gram, np.float64) @ r.T)
    order = np.argsort(evals)[::-1]
    evals, w = evals[order], w[:, order]
    kept = evals > max(evals[0], 0.0) * floor if evals.size and evals[0] > 0 else evals > np.inf
    s = np.sqrt(evals[kept])
    return q @ w[:, kept], s, (r.T @ w[:, kept]) / s


def per_channel(u: np.ndarray, s: np.ndarray, *, tol: float = 1e-7
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One channel of a store's factors at its own rank, for a DFMF file.

    ``u`` is the channel's rows of ``U`` (rows x K) and ``s`` the singular values: the
    channel's values are ``(u diag(s)) V^T``. With the SVD ``u diag(s) = P diag(sigma) Q^T``
    they are ``P (V Q diag(sigma))^T``: returns ``P`` (the file's ``U_c``), ``sigma`` and the
    ``K x k_c`` map ``Q diag(sigma)`` that takes rows of ``V`` to rows of the file's ``S V``.
    Components with ``sigma`` at most ``tol`` of the largest are dropped (a channel of a
    store ingested from DFMF gets its own ``k_c`` back).
    """
    p, sigma, qt = np.linalg.svd(np.asarray(u, np.float64) * np.asarray(s, np.float64),
                                 full_matrices=False)
    keep = max(1, int(np.sum(sigma > sigma[0] * tol))) if sigma.size and sigma[0] > 0 else 1
    return p[:, :keep], sigma[:keep], qt[:keep].T * sigma[:keep]


def degrees(theta: np.ndarray, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Radian angles of a file as the store's degrees: phi in [0, 360), 0 straight above."""
    t = np.degrees(np.asarray(theta, np.float64))
    p = np.degrees(np.asarray(phi, np.float64)) % 360.0
    return t, np.where(t > 0, p, 0.0)


def radians(theta: np.ndarray, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A store's degrees as a file's radians, phi in (-180, 180] degrees as Bonn's files."""
    p = np.asarray(phi, np.float64) % 360.0
    p = np.where(p > 180.0, p - 360.0, p)
    return np.radians(np.asarray(theta, np.float64)), np.radians(p)

