"""From measured images' encodings to the store's linear values.

Two conversions: display-encoded integer pixels (8-bit JPEG, 8/16-bit PNG) to linear values by a
transfer curve, and CIE XYZ to linear RGB with the sRGB primaries (both under D65, so no
chromatic adaptation is involved).
"""

from __future__ import annotations

import functools

import numpy as np

from tasks.tonemap import srgb_decode

DECODINGS = ("srgb", "gamma2.2", "none")

# XYZ (D65) -> linear RGB with the sRGB/Rec. 709 primaries and D65 white: the inverse of the
# primaries' matrix of IEC 61966-2-1, to 7 digits (B. Lindbloom's derivation; the standard's
# own 4-digit matrix differs by < 2e-4).
XYZ_TO_LINEAR_SRGB = np.array([[3.2404542, -1.5371385, -0.4985314],
                               [-0.9692660, 1.8760108, 0.0415560],
                               [0.0556434, -0.2040259, 1.0572252]])


@functools.lru_cache(maxsize=8)
def decoding_table(decoding: str, levels: int = 256) -> np.ndarray:
    """Linear float32 value of every integer code ``0 .. levels - 1`` under ``decoding``.

    ``"srgb"``: the sRGB curve (IEC 61966-2-1), the same values as
    :func:`tasks.tonemap.srgb_decode`; ``"gamma2.2"``: ``(v / (levels - 1)) ** 2.2``, as the
    Mitsuba BTF plugin decodes UBO2003 JPEGs; ``"none"``: ``v / (levels - 1)``. The table is
    shared between calls and read-only.
    """
    codes = np.arange(levels, dtype=np.float32) * np.float32(1.0 / (levels - 1))
    table = decode_values(codes, decoding)
    table.flags.writeable = False
    return table


def decode_values(values: np.ndarray, decoding: str) -> np.ndarray:
    """Linear float32 values of display-encoded values in ``[0, 1]`` (see :func:`decoding_table`).

    For integer pixels :func:`decode_display` gives the same values faster.
    """
    values = np.asarray(values, np.float32)
    if decoding == "srgb":
        return srgb_decode(values)
    if decoding == "gamma2.2":  # float64 power: the table's values whatever the input size
        return (values.astype(np.float64) ** 2.2).astype(np.float32)
    if decoding == "none":
        return values
    raise ValueError(f"unknown decoding {decoding!r}; one of {', '.join(DECODINGS)}")


def decode_display(pixels: np.ndarray, decoding: str) -> np.ndarray:
    """Linear float32 values of 8 or 16-bit display-encoded ``pixels`` (a table lookup)."""
    pixels = np.asarray(pixels)
    if pixels.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"display-encoded pixels must be uint8 or uint16, not {pixels.dtype}")
    table = decoding_table(decoding, int(np.iinfo(pixels.dtype).max) + 1)
    return np.take(table, pixels)


def xyz_to_linear_srgb(xyz: np.ndarray) -> np.ndarray:
    """Linear sRGB (D65) of CIE XYZ (D65) values in the last axis, float32.

    Linear and lossless up to float32 rounding: colours outside the sRGB gamut get negative
    components, which are kept (``btf compress --clamp`` decides what to do with them).
    """
    xyz = np.asarray(xyz, np.float32)
    if xyz.shape[-1] != 3:
        raise ValueError(f"XYZ values need 3 components in the last axis, got {xyz.shape}")
    return xyz @ XYZ_TO_LINEAR_SRGB.T.astype(np.float32)
