"""How the values of a compressed store map to radiance: its range reduction and colour model.

A compressed store holds ``U``, ``S``, ``V`` of a matrix ``A`` whose row of (view, light,
channel) holds one texture of *values*, not radiance (paper 000, Fig. 2: the range reduction).
The store's ``transform`` attribute says which; per layer and texel the values
``a = (a_0, ..., a_{C-1})`` of its ``C`` channels decode to radiance as

``log``
    ``exp(a_c) - eps`` per channel: what ``btf compress`` writes (its ``--eps``), and Bonn's
    DFMF colour model 12 (``eps`` = 1e-5, fixed by Bonn's readers).
``linear``
    ``a`` itself: DFMF colour models 0 (RGB), 1 (YUV), 3 (PCA) and 4 (YCoCg), whose colour
    matrix and mean are linear and so are folded into ``U`` when a file is ingested.
``ylog-uv`` (DFMF colour model 9)
    ``Y = exp(a_0) - eps``, ``U = a_1``, ``V = a_2``, then YUV to RGB.
``ylog-ulog-vlog`` (model 10)
    ``Y = exp(a_0) - eps``, ``U = sign(a_1) exp(|a_1| + log eps)`` (``V`` alike), then YUV.
``ylog-uv-over-y`` (model 11, the Bonn UBO2014 files')
    ``Y = exp(a_0) - eps``, ``U = a_1 (Y + eps)``, ``V = a_2 (Y + eps)``, then YUV.

The colour models are those of Bonn's btflib (``undecorrelate.m``); YUV to RGB is its matrix
:data:`YUV_TO_RGB`. Decoded radiance below 0 (approximation error) is set to 0. :meth:`encode`
is the inverse, for values that must be compared with stored ones (constraint photos, levels of
detail).

``cosine`` (a DFMF file's cosine flag with a non-linear colour model): the decoded quantity is
radiance times ``cos(theta_light)``, so a layer's radiance is it divided by the cosine of its
light (:meth:`Transform.layer_scale`), after the colour model, as the flag means. The
division is per layer, so it is not part of :meth:`decode`: whoever rebuilds layers passes
their scale (:func:`tasks.svd.reconstruct`'s ``scale``). The linear models fold it into ``U``
instead, and keep ``cosine`` false.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

YUV_TO_RGB = np.array([[1.0, 0.0, 1.13983], [1.0, -0.39465, -0.5806], [1.0, 2.03211, 0.0]])
YCOCG_TO_RGB = np.array([[1.0, 1.0, -1.0], [1.0, 0.0, 1.0], [1.0, -1.0, -1.0]])
DFMF_EPS = 1e-5  # Bonn's readers' fixed eps of the log colour models; files do not store it
LOG_MAX = 88.0  # exp of more overflows float32

# DFMF colour model number -> (transform name, formula); models 0, 1, 3, 4 fold into U.
DFMF_MODELS: dict[int, tuple[str, str]] = {
    0: ("linear", "RGB"),
    1: ("linear", "YUV (its matrix folded into U)"),
    3: ("linear", "PCA: values @ M + mean (folded into U and a constant component)"),
    4: ("linear", "YCoCg (its matrix folded into U)"),
    9: ("ylog-uv", "Y = exp(a0) - eps, U = a1, V = a2, YUV to RGB"),
    10: ("ylog-ulog-vlog", "Y = exp(a0) - eps, U,V = sign(a) exp(|a| + log eps), YUV to RGB"),
    11: ("ylog-uv-over-y", "Y = exp(a0) - eps, U = a1 (Y + eps), V = a2 (Y + eps), YUV to RGB"),
    12: ("log", "exp(a) - eps"),
}
_YUV_NAMES = ("ylog-uv", "ylog-ulog-vlog", "ylog-uv-over-y")
NAMES = ("log", "linear", *_YUV_NAMES)


@dataclass(frozen=True)
class Transform:
    """A store's value model: ``name`` (see the module), its ``eps``, and the cosine flag."""

    name: str = "log"
    eps: float = 1e-3
    cosine: bool = False  # decoded values are radiance x cos(theta_light)

    def __post_init__(self):
        if self.name not in NAMES:
            raise ValueError(f"unknown transform {self.name!r}; known: {', '.join(NAMES)}")
        if self.name != "linear" and not self.eps > 0:
            raise ValueError(f"transform {self.name!r} needs eps > 0, got {self.eps}")

    @staticmethod
    def from_attrs(attrs: dict[str, Any]) -> Transform:
        """The transform a store's ``transform`` attribute describes (old stores: ``log``)."""
        return Transform(str(attrs.get("name", "log")), float(attrs.get("eps", 0.0)),
                         bool(attrs.get("cosine", False)))

    def layer_scale(self, theta_light) -> np.ndarray | None:
        """What multiplies decoded layers lit from ``theta_light`` (degrees) to give radiance.

        ``1 / cos(theta_light)`` (float32, the cosine at least 1e-6) for a cosine store; None
        for any other, where the decoded values are radiance already.
        """
        if not self.cosine:
            return None
        cos = np.cos(np.radians(np.asarray(theta_light, np.float64)))
        return (1.0 / np.maximum(cos, 1e-6)).astype(np.float32)

    @property
    def channels(self) -> int | None:
        """Channels decoded together (3 for the YUV models), None where each is on its own."""
        return 3 if self.name in _YUV_NAMES else None

    def decode(self, values: np.ndarray, *, axis: int = -1) -> np.ndarray:
        """Radiance (float32, >= 0) of ``values``, whose channels lie along ``axis``.

        The input is overwritten when it is a float32 array (blocks are large).
        """
        a = np.asarray(values, dtype=np.float32)
        eps = np.float32(self.eps)
        if self.name == "linear":
            return np.maximum(a, 0.0, out=a)
        if self.name == "log":
            np.minimum(a, np.float32(LOG_MAX), out=a)
            np.exp(a, out=a)
            a -= eps
            return np.maximum(a, 0.0, out=a)
        a = np.moveaxis(a, axis, 0)
        if a.shape[0] != 3:
            raise ValueError(f"transform {self.name!r} decodes 3 channels, got {a.shape[0]}")
        y = np.exp(np.minimum(a[0], np.float32(LOG_MAX)))  # Y + eps
        if self.name == "ylog-uv-over-y":
            u, v = a[1] * y, a[2] * y
        elif self.name == "ylog-ulog-vlog":
            u, v = (np.sign(c) * np.exp(np.minimum(np.abs(c), LOG_MAX) + np.log(eps))
                    for c in a[1:])
        else:
            u, v = a[1], a[2]
        y -= eps
        m = YUV_TO_RGB.astype(np.float32)
        out = np.stack([m[i, 0] * y + m[i, 1] * u + m[i, 2] * v for i in range(3)])
        np.maximum(out, 0.0, out=out)
        return np.moveaxis(out, 0, axis)

    def encode(self, radiance: np.ndarray, *, axis: int = -1) -> np.ndarray:
        """Values of non-negative ``radiance``: the inverse of :meth:`decode`.

        float64 input stays float64 (sums of many values); anything else becomes float32.
        """
        r = np.asarray(radiance)
        dtype = np.result_type(r.dtype, np.float32)
        r = np.maximum(r.astype(dtype, copy=False), 0.0)
        eps = dtype.type(self.eps)
        if self.name == "linear":
            return r
        if self.name == "log":
            return np.log(r + eps)
        r = np.moveaxis(r, axis, 0)
        if r.shape[0] != 3:
            raise ValueError(f"transform {self.name!r} encodes 3 channels, got {r.shape[0]}")
        rgb_to_yuv = np.linalg.inv(YUV_TO_RGB).astype(dtype)
        y, u, v = (sum(rgb_to_yuv[i, j] * r[j] for j in range(3)) for i in range(3))
        y = np.maximum(y, 0.0)
        out = [np.log(y + eps)]
        if self.name == "ylog-uv-over-y":
            out += [u / (y + eps), v / (y + eps)]
        elif self.name == "ylog-ulog-vlog":
            out += [np.sign(c) * np.maximum(np.log(np.maximum(np.abs(c), eps)) - np.log(eps), 0)
                    for c in (u, v)]
        else:
            out += [u, v]
        return np.moveaxis(np.stack(out).astype(dtype, copy=False), 0, axis)

    def decode_rows(self, values: np.ndarray) -> np.ndarray:
        """Radiance of BTF matrix rows ``(rows, texels)`` whose channel index runs fastest."""
        return self._by_rows(self.decode, values)

    def encode_rows(self, radiance: np.ndarray) -> np.ndarray:
        """Values of radiance rows ``(rows, texels)`` whose channel index runs fastest."""
        return self._by_rows(self.encode, radiance)

    def _by_rows(self, fn, rows: np.ndarray) -> np.ndarray:
        """``fn`` on matrix rows, each layer's channels taken together where they must be."""
        group = self.channels
        if group is None:
            return fn(rows)
        n, texels = rows.shape
        return fn(rows.reshape(n // group, group, texels), axis=1).reshape(n, texels)


def dfmf_colour_matrix(model: int, matrix: np.ndarray, mean: np.ndarray, channels: int
                       ) -> tuple[np.ndarray, np.ndarray]:
    """``(M, m)`` with radiance ``= values @ M + m`` for a linear DFMF colour model.

    Values are row vectors of the file's channels (btflib's ``undecorrelate``): model 0 is the
    identity, 1 YUV (``M = YUV_TO_RGB^T``), 3 PCA (the file's matrix and mean), 4 YCoCg.
    """
    if model == 0:
        return np.eye(channels), np.zeros(channels)
    if channels != 3:
        raise ValueError(f"colour model {model} needs 3 channels, the file has {channels}")
    if model == 1:
        return YUV_TO_RGB.T.copy(), np.zeros(3)
    if model == 3:
        return np.asarray(matrix, np.float64), np.asarray(mean, np.float64)
    if model == 4:
        return YCOCG_TO_RGB.T.copy(), np.zeros(3)
    raise ValueError(f"colour model {model} is not linear")
