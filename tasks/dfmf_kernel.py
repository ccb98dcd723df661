"""Compiled loops (numba) that decode DFMF files: float16 to float32, and the colour models.

numpy converts float16 at about 3.4 ns a value here (it does not use the CPU's conversion
instruction): slower than the products themselves. :func:`half` converts one value with the
CPU's instruction where it has one (x86's F16C, as every x86-64 CPU since 2013; ARM's
``fcvt``), which LLVM vectorises (8 values an instruction), or else with integer operations
and one bit cast. :func:`halves_to_float32` converts arrays; :func:`halves_product` converts
inside the product with a channel's ``U`` rows, so a file's bytes are read once and no
float32 copy is made. :func:`decode_colour` applies a colour model to a block of channel
values in one pass, where numpy's expression would make a temporary per step. All release
the GIL (the caller runs bands on threads), use no numba threads and keep their compiled
code in numba's on-disk cache, as :mod:`tasks.csr_kernel`. Kept apart from
:mod:`tasks.dfmf`, so that reading a header does not load numba.
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

# colour model codes of decode_colour
LINEAR, LOG, YLOG_UV, YLOG_ULOG_VLOG, YLOG_UV_OVER_Y = range(5)
CODES = {"linear": LINEAR, "log": LOG, "ylog-uv": YLOG_UV, "ylog-ulog-vlog": YLOG_ULOG_VLOG,
         "ylog-uv-over-y": YLOG_UV_OVER_Y}  # by tasks.transform's names
_YUV = np.array([[1.0, 0.0, 1.13983], [1.0, -0.39465, -0.5806], [1.0, 2.03211, 0.0]],
                np.float32)


@intrinsic
def _bits_to_float32(typingctx, bits):
    """The float32 whose bit pattern is the uint32 ``bits``."""
    if not isinstance(bits, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())

    return types.float32(types.uint32), codegen


@intrinsic
def _half_instruction(typingctx, bits):
    """The float16 whose bit pattern is the uint16 ``bits``, as float32, by the CPU.

    LLVM's ``fpext half``: exact for every value, infinities and NaN too.
    """
    if not isinstance(bits, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        return builder.fpext(builder.bitcast(args[0], ir.HalfType()), ir.FloatType())

    return types.float32(types.uint16), codegen


_MAGIC = np.float32(2.0**112)  # rescales a half's exponent field shifted into a float's


@numba.njit(inline="always")
def _half_integer(bits):
    """The float16 ``bits`` as float32 by integer operations.

    The exponent and mantissa fields moved into a float32's and scaled by 2^112 give every
    normal and subnormal half exactly (and 0); infinities and NaN come out as large finite
    values (a DFMF file holds neither: its readers would fail on them too).
    """
    h = np.uint32(bits)
    magnitude = _bits_to_float32(np.uint32((h & np.uint32(0x7FFF)) << np.uint32(13)))
    sign = np.float32(1.0) - np.float32(2.0) * np.float32(h >> np.uint32(15))
    return magnitude * _MAGIC * sign


def _has_half_instruction() -> bool:
    """Whether the JIT's target converts float16 in one instruction.

    Without one, LLVM would call a runtime helper that numba's linker may not have.
    """
    import platform

    import llvmlite.binding as llvm

    if platform.machine().lower() in ("aarch64", "arm64"):
        return True
    try:
        return bool(llvm.get_host_cpu_features().get("f16c", False))
    except RuntimeError:  # features unknown: take the portable path
        return False


HALF_INSTRUCTION = _has_half_instruction()
half = _half_instruction if HALF_INSTRUCTION else _half_integer


@numba.njit(nogil=True, cache=True)
def halves_to_float32(bits: np.ndarray, out: np.ndarray) -> None:
    """Float32 values of float16 ``bits`` (uint16, any shape, C order) into ``out``."""
    flat, dest = bits.ravel(), out.ravel()
    for i in range(flat.size):
        dest[i] = half(flat[i])


@numba.njit(nogil=True, fastmath=True, cache=True)
def halves_product(u: np.ndarray, bits: np.ndarray, out: np.ndarray) -> None:
    """``out = u @ halves(bits)^T``: rows ``u`` ``(n, k)`` float32 times float16 ``bits``.

    ``bits`` ``(texels, k)`` uint16 are a channel's ``S V`` rows as a DFMF file stores them;
    each texel's row is converted once and multiplied with every row of ``u``, so the file's
    bytes are read once and no float32 copy is made.
    """
    n, k = u.shape
    if n == 1:  # one image: convert and multiply in one vectorised loop, no row copy
        for t in range(bits.shape[0]):
            acc = np.float32(0.0)
            for j in range(k):
                acc += u[0, j] * half(bits[t, j])
            out[0, t] = acc
        return
    row = np.empty(k, np.float32)
    for t in range(bits.shape[0]):
        for j in range(k):
            row[j] = half(bits[t, j])
        for i in range(n):
            acc = np.float32(0.0)
            for j in range(k):
                acc += u[i, j] * row[j]
            out[i, t] = acc


@numba.njit(inline="always")
def _yuv(a0, a1, a2, model, e, top, log_eps):
    """Y, U and V of one texel's values under a YUV model (Y's log and eps undone)."""
    y1 = np.exp(min(a0, top))  # Y + eps
    if model == YLOG_UV_OVER_Y:
        u, w = a1 * y1, a2 * y1
    elif model == YLOG_ULOG_VLOG:
        u = np.sign(a1) * np.exp(min(abs(a1), top) + log_eps)
        w = np.sign(a2) * np.exp(min(abs(a2), top) + log_eps)
    else:
        u, w = a1, a2
    return y1 - e, u, w


@numba.njit(nogil=True, fastmath=True, cache=True)
def decode_colour(values: np.ndarray, model: int, eps: float, matrix: np.ndarray,
                  mean: np.ndarray, scale: np.ndarray) -> None:
    """Radiance of channel values ``(n, texels, C)`` float32, in place, clamped at 0.

    ``model``: :data:`LINEAR` (``values @ matrix + mean``), :data:`LOG` (``exp - eps`` per
    channel) or the YUV models (Bonn's 9, 10, 11: :mod:`tasks.transform`); ``scale`` ``(n,)``
    multiplies image ``i`` (``1 / cos(theta_light)`` for a cosine-flagged file, else 1).
    """
    n, texels, channels = values.shape
    e = np.float32(eps)
    zero, top = np.float32(0.0), np.float32(88.0)  # exp of more overflows float32
    log_eps = np.float32(np.log(eps)) if eps > 0 else zero
    yuv = _YUV
    tmp = np.empty(channels, np.float32)
    for i in range(n):
        f = np.float32(scale[i])
        for t in range(texels):
            if model == LOG:
                for c in range(channels):
                    x = (np.exp(min(values[i, t, c], top)) - e) * f
                    values[i, t, c] = x if x > zero else zero
            elif model == LINEAR:
                for d in range(channels):
                    acc = np.float32(mean[d])
                    for c in range(channels):
                        acc += values[i, t, c] * matrix[c, d]
                    tmp[d] = acc * f
                for d in range(channels):
                    values[i, t, d] = tmp[d] if tmp[d] > zero else zero
            else:
                y, u, w = _yuv(values[i, t, 0], values[i, t, 1], values[i, t, 2], model, e,
                               top, log_eps)
                for d in range(3):
                    x = (yuv[d, 0] * y + yuv[d, 1] * u + yuv[d, 2] * w) * f
                    values[i, t, d] = x if x > zero else zero


@numba.njit(nogil=True, cache=True)
def decode_layers(values: np.ndarray, out: np.ndarray, model: int, eps: float,
                  scale: np.ndarray) -> None:
    """Radiance layers ``out`` ``(n, texels, C)`` of BTF-matrix rows ``values`` ``(n, C, texels)``.

    :meth:`tasks.transform.Transform.decode` (``model``: :data:`LINEAR`, :data:`LOG` or a YUV
    model) and the move of the channels last, in one pass: the same float32 operations in
    the same order as numpy's, without its temporaries (no ``fastmath``). ``scale`` ``(n,)``
    multiplies layer ``i`` after the clamp (a cosine store's ``1 / cos theta_light``), as
    :func:`tasks.svd.reconstruct` does.
    """
    n, channels, texels = values.shape
    e = np.float32(eps)
    zero, top = np.float32(0.0), np.float32(88.0)
    log_eps = np.float32(np.log(np.float32(eps))) if eps > 0 else zero
    m = _YUV
    for i in range(n):
        f = scale[i]
        for t in range(texels):
            if model == LINEAR or model == LOG:
                for c in range(channels):
                    x = values[i, c, t]
                    if model == LOG:
                        x = np.exp(min(x, top)) - e
                    out[i, t, c] = (x if x > zero or x != x else zero) * f
            else:
                y, u, w = _yuv(values[i, 0, t], values[i, 1, t], values[i, 2, t], model, e,
                               top, log_eps)
                for d in range(3):
                    x = m[d, 0] * y + m[d, 1] * u + m[d, 2] * w
                    out[i, t, d] = (x if x > zero or x != x else zero) * f
