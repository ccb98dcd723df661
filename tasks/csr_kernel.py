"""The compiled sparse row loop (numba) that applies prescriptions, ``P @ layer``.

Kept apart from :mod:`tasks.prescription`, which imports it on first use and only where the
work pays for loading numba (0.3-0.5 s to import and ~100 MB, and as long again for the first
call's set-up: :func:`tasks.prescription.compiled_pays`). Every loop releases the GIL
(``nogil``), so the pipeline's threads run them in parallel, and none uses numba's own threads
(they must not be entered from several dask threads at once). Compiled code is kept in numba's
on-disk cache (``__pycache__`` beside this file, or the user's cache folder where that is not
writable; keyed by the source and the CPU): compiling takes about 3 s, which every ``btf quilt``
and every new worker process paid before; loading it takes 30 ms once numba is set up.
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

AHEAD = 32  # output texels between prefetching a texel's sources and summing them


@intrinsic
def prefetch(typingctx, address):
    """Ask the CPU to bring the cache line at ``address`` (an integer) into cache.

    LLVM's ``llvm.prefetch`` (read, high locality, data cache): a hint, which never faults.
    """
    if not isinstance(address, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        i32 = ir.IntType(32)
        pointer = ir.IntType(8).as_pointer()
        llvm_prefetch = builder.module.declare_intrinsic(
            "llvm.prefetch", fnty=ir.FunctionType(ir.VoidType(), [pointer, i32, i32, i32]))
        address = builder.inttoptr(args[0], pointer)
        read, high_locality, data_cache = (ir.Constant(i32, v) for v in (0, 3, 1))
        builder.call(llvm_prefetch, [address, read, high_locality, data_cache])
        return context.get_dummy_value()

    return types.void(types.intp), codegen


@numba.njit(nogil=True, cache=True)
def _any_channels(indptr, indices, data, s, d):
    """``d = P @ s`` for one layer of any number of channels: a plain loop."""
    for r in range(indptr.size - 1):
        for k in range(s.shape[1]):
            a = np.float32(0)
            for j in range(indptr[r], indptr[r + 1]):
                a += data[j] * s[indices[j], k]
            d[r, k] = a


@numba.njit(nogil=True, cache=True)
def _rgb(indptr, indices, data, s, d):
    """``d = P @ s`` for one RGB layer, prefetching sources ``AHEAD`` texels on."""
    rows, stride, base = indptr.size - 1, s.strides[0], s.ctypes.data
    for r in range(rows):
        if r + AHEAD < rows:
            for j in range(indptr[r + AHEAD], min(indptr[r + AHEAD] + 2, indptr[r + AHEAD + 1])):
                prefetch(base + stride * indices[j])
        a0 = a1 = a2 = np.float32(0)
        for j in range(indptr[r], indptr[r + 1]):
            w, c = data[j], indices[j]
            a0 += w * s[c, 0]
            a1 += w * s[c, 1]
            a2 += w * s[c, 2]
        d[r, 0], d[r, 1], d[r, 2] = a0, a1, a2


@numba.njit(nogil=True, cache=True)
def _rgb_pair(indptr, indices, data, s, t, ds, dt):
    """``ds = P @ s`` and ``dt = P @ t`` for two RGB layers in one pass over ``P``."""
    rows, stride = indptr.size - 1, s.strides[0]
    base_s, base_t = s.ctypes.data, t.ctypes.data
    for r in range(rows):
        if r + AHEAD < rows:
            for j in range(indptr[r + AHEAD], min(indptr[r + AHEAD] + 2, indptr[r + AHEAD + 1])):
                prefetch(base_s + stride * indices[j])
                prefetch(base_t + stride * indices[j])
        a0 = a1 = a2 = b0 = b1 = b2 = np.float32(0)
        for j in range(indptr[r], indptr[r + 1]):
            w, c = data[j], indices[j]
            a0 += w * s[c, 0]
            a1 += w * s[c, 1]
            a2 += w * s[c, 2]
            b0 += w * t[c, 0]
            b1 += w * t[c, 1]
            b2 += w * t[c, 2]
        ds[r, 0], ds[r, 1], ds[r, 2] = a0, a1, a2
        dt[r, 0], dt[r, 1], dt[r, 2] = b0, b1, b2


@numba.njit(nogil=True, cache=True)
def csr_product(indptr, indices, data, src, dst):
    """``dst[l] = P @ src[l]`` for ``(layers, texels, channels)`` arrays, ``P`` as CSR arrays.

    Every output value is summed in float32 from 0 over its row's terms in CSR order, with a
    separate multiply and add, which is what scipy's ``csr_matvecs`` does for a float32 CSR
    matrix on x86-64 (whose wheels do not fuse them): the result is scipy's ``P @ src[l]`` bit
    for bit there (the tests check it). The sources of a texel are scattered over the sample, so
    the loop waits on memory; for three channels (RGB) it works on two layers at once (the same
    terms, two independent loads) and prefetches the sources of the texel ``AHEAD`` texels on,
    which together make it about 1.4x faster than a plain loop (BENCHMARKS.md, quilting).
    numba compiles it once for every combination of argument types it meets, and caches it.
    """
    layers, channels = src.shape[0], src.shape[2]
    if channels != 3:
        for layer in range(layers):
            _any_channels(indptr, indices, data, src[layer], dst[layer])
        return
    for layer in range(0, layers - 1, 2):
        _rgb_pair(indptr, indices, data, src[layer], src[layer + 1], dst[layer],
                  dst[layer + 1])
    if layers % 2:
        _rgb(indptr, indices, data, src[layers - 1], dst[layers - 1])
