"""Display transforms: sRGB encoding and decoding, exposure and highlight roll-off."""

from __future__ import annotations

import numpy as np


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """Linear values from sRGB-encoded values in ``[0, 1]`` (IEC 61966-2-1), as float32."""
    e = np.asarray(encoded, np.float32)
    return np.where(e <= 0.04045, e / 12.92, ((e + 0.055) / 1.055) ** 2.4).astype(np.float32)


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """sRGB-encoded values from linear values, clipped to ``[0, 1]``, as float32."""
    x = np.clip(np.asarray(linear, np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055).astype(np.float32)


def exposure(samples: np.ndarray, *, percentile: float = 99.0, target: float = 0.8) -> float:
    """Scale that maps the ``percentile`` of the finite ``samples`` to ``target``.

    Used once for a whole preview or export, so that every layer is shown with the same
    exposure and layers stay comparable.
    """
    finite = np.asarray(samples)[np.isfinite(samples)]
    level = float(np.percentile(finite, percentile)) if finite.size else 0.0
    return target / level if level > 0 else 1.0


def tonemap(radiance: np.ndarray, *, scale: float, knee: float = 0.8) -> np.ndarray:
    """Display values in ``[0, 1]`` (sRGB-encoded) of HDR radiance.

    Values are multiplied by ``scale``; below ``knee`` they are kept as they are, above it they
    roll off smoothly towards 1 so that HDR highlights keep some detail instead of clipping.
    """
    y = np.nan_to_num(np.asarray(radiance, np.float32) * np.float32(scale), nan=0.0, posinf=1e6)
    y = np.maximum(y, 0.0)
    over = np.maximum(y - knee, 0.0)
    rolled = knee + (1.0 - knee) * (1.0 - np.exp(-over / (1.0 - knee)))
    return srgb_encode(np.where(y > knee, rolled, y))


def to_uint8(display: np.ndarray) -> np.ndarray:
    """8-bit pixels from display values in ``[0, 1]``."""
    return np.round(np.clip(display, 0.0, 1.0) * 255.0).astype(np.uint8)
