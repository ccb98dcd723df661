"""Image files in and out: OpenEXR (official bindings) and PNG (libpng through imagecodecs).

Every reader returns float32 ``(height, width, channels)`` plus channel names, and every failure
is a :class:`~pipeline.errors.BTFError` naming the file.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from pipeline.errors import BTFError
from tasks.tonemap import srgb_decode

IMAGE_SUFFIXES = (".exr", ".png")
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_CHANNELS = {0: ("Y",), 2: ("R", "G", "B"), 3: ("R", "G", "B"), 4: ("Y",), 6: ("R", "G", "B")}


@dataclass(frozen=True)
class ImageInfo:
    """Size, channel names and sample type of an image file, read from its header only.

    ``sample``: ``uint8``, ``uint16``, ``half``, ``float``, ``double`` or ``rgbe`` (Radiance's
    shared-exponent bytes), the type the file stores its values in.
    """

    height: int
    width: int
    channels: tuple[str, ...]
    sample: str = "float"

    @property
    def precision(self) -> str:
        """The store type that holds every value of this type exactly, as decoded to linear.

        ``float16`` for 8-bit codes (each of the 256 decodes to a float16 that encodes back
        to it, for every decoding) and half floats; ``float32`` for anything finer.
        """
        return "float16" if self.sample in ("uint8", "half") else "float32"

    def same_size(self, other: ImageInfo) -> bool:
        """Whether ``other`` has this image's size and channels (whatever its sample type)."""
        return (self.height, self.width, self.channels) == (other.height, other.width,
                                                            other.channels)

    def widest(self, other: ImageInfo) -> ImageInfo:
        """The info of both images: ``other``'s sample type where that one needs float32."""
        return self if other.precision == "float16" else replace(self, sample=other.sample)


_EXR_SAMPLES = {0: "uint32", 1: "half", 2: "float"}


def _exr_sample(path: Path) -> str:
    """The widest pixel type of an EXR file's channels, from the ``channels`` header attribute.

    The bindings give the types only once the pixels are read; the header's ``chlist`` is
    (name, int32 type, uint8 pLinear, 3 reserved bytes, int32 xSampling, int32 ySampling)
    per channel, then a NUL.
    """
    with path.open("rb") as f:
        head = f.read(1 << 16)
    at = head.find(b"channels\0chlist\0")
    if at < 0:
        return "float"
    at += len(b"channels\0chlist\0")
    (size,) = struct.unpack_from("<i", head, at)
    body, types = head[at + 4 : at + 4 + size], []
    i = 0
    while i < len(body) and body[i] != 0:
        i = body.index(b"\0", i) + 1
        types.append(struct.unpack_from("<i", body, i)[0])
        i += 16
    found = {_EXR_SAMPLES.get(t, "float") for t in types}
    return "half" if found == {"half"} else "float"


def _exr_channels(names: list[str], path: Path) -> tuple[str, ...]:
    if {"R", "G", "B"} <= set(names):
        return ("R", "G", "B")
    if len(names) == 1:
        return (names[0],)
    if {"X", "Y", "Z"} <= set(names):  # CIE XYZ, kept as named (btf ingest converts it)
        return ("X", "Y", "Z")
    if "Y" in names:
        return ("Y",)
    raise BTFError(f"{path}: channels {sorted(names)} are neither R,G,B nor a single channel")


def image_info(path: str | Path) -> ImageInfo:
    """Read the header of an EXR or PNG file."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".exr":
        import OpenEXR

        try:
            # The header is only valid while the file is open: copy what is needed.
            with OpenEXR.File(str(path), header_only=True) as f:
                header = f.header()
                (x0, y0), (x1, y1) = (np.asarray(v).copy() for v in header["dataWindow"])
                names = [str(c.name) for c in header["channels"]]
        except Exception as exc:  # the bindings raise RuntimeError with a short text
            raise BTFError(f"{path}: corrupt or unreadable EXR file ({exc})") from None
        return ImageInfo(int(y1 - y0 + 1), int(x1 - x0 + 1), _exr_channels(names, path),
                         _exr_sample(path))
    if suffix == ".png":
        try:
            with path.open("rb") as f:
                head = f.read(26)
        except OSError as exc:
            raise BTFError(f"{path}: cannot read ({exc.strerror})") from None
        if len(head) < 26 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
            raise BTFError(f"{path}: not a PNG file (bad signature or header)")
        width, height, depth, colour = struct.unpack(">IIBB", head[16:26])
        if colour not in _PNG_CHANNELS or depth not in (8, 16):
            raise BTFError(f"{path}: PNG with bit depth {depth} and colour type {colour} "
                           "is not supported (use 8 or 16-bit grey, RGB or RGBA)")
        return ImageInfo(height, width, _PNG_CHANNELS[colour], f"uint{depth}")
    raise BTFError(f"{path}: not an image the pipeline reads (use .exr or .png)")


def read_image(path: str | Path, *, srgb: bool = False) -> tuple[np.ndarray, tuple[str, ...]]:
    """Pixels of an EXR or PNG file as float32 ``(height, width, channels)`` and channel names.

    EXR values are taken as they are (half or float). PNG values are scaled to ``[0, 1]`` and,
    with ``srgb``, decoded from the sRGB transfer curve to linear values. Alpha is dropped.
    """
    path = Path(path)
    info = image_info(path)
    if path.suffix.lower() == ".exr":
        import OpenEXR

        try:
            with OpenEXR.File(str(path), separate_channels=True) as f:
                channels = f.channels()
                planes = [np.asarray(channels[name].pixels) for name in info.channels]
        except Exception as exc:
            raise BTFError(f"{path}: corrupt or unreadable EXR file ({exc})") from None
        if any(p.dtype.kind != "f" for p in planes):
            raise BTFError(f"{path}: EXR channels must be half or float, not integer")
        return np.stack(planes, axis=-1).astype(np.float32, copy=False), info.channels
    import imagecodecs

    try:
        pixels = imagecodecs.png_decode(path.read_bytes())
    except Exception as exc:
        raise BTFError(f"{path}: corrupt PNG file ({exc})") from None
    scale = np.float32(1.0 / np.iinfo(pixels.dtype).max)
    pixels = pixels.reshape(info.height, info.width, -1)[..., : len(info.channels)]
    values = pixels.astype(np.float32) * scale
    return (srgb_decode(values) if srgb else values), info.channels


def write_exr(path: str | Path, pixels: np.ndarray, channels: tuple[str, ...], *,
              half: bool = False) -> None:
    """Write ``(height, width, channels)`` pixels as a ZIP-compressed scanline EXR."""
    import OpenEXR

    pixels = np.asarray(pixels)
    dtype = np.float16 if half else np.float32
    planes = {name: np.ascontiguousarray(pixels[..., i], dtype=dtype)
              for i, name in enumerate(channels)}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, planes) as f:
        f.write(str(path))


def write_png(path: str | Path, pixels: np.ndarray, text: dict[str, str] | None = None) -> None:
    """Write 8 or 16-bit ``(height, width[, channels])`` pixels as PNG.

    ``text``: Latin-1 key/value pairs stored as PNG ``tEXt`` chunks (read by :func:`png_text`).
    """
    import imagecodecs

    data = imagecodecs.png_encode(np.ascontiguousarray(pixels))
    if text:
        chunks = b"".join(_png_chunk(b"tEXt", key.encode("latin-1") + b"\0"
                                     + value.encode("latin-1", "replace"))
                          for key, value in text.items())
        end = data.rindex(b"IEND") - 4  # the IEND chunk's length field
        data = data[:end] + chunks + data[end:]
    Path(path).write_bytes(data)


def _png_chunk(kind: bytes, body: bytes) -> bytes:
    import struct
    import zlib

    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def png_text(data: bytes) -> dict[str, str]:
    """The ``tEXt`` key/value pairs of a PNG file's bytes (empty if none or not a PNG)."""
    import struct

    out, at = {}, 8
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        return out
    while at + 8 <= len(data):
        (length,), kind = struct.unpack(">I", data[at : at + 4]), data[at + 4 : at + 8]
        if kind == b"tEXt":
            key, _, value = data[at + 8 : at + 8 + length].partition(b"\0")
            out[key.decode("latin-1")] = value.decode("latin-1")
        if kind == b"IEND":
            break
        at += 12 + length
    return out
