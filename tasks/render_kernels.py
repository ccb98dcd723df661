"""The renderer's compiled loops (numba): cast shadows and shading, texel by texel.

Kept apart from :mod:`tasks.shading` and :mod:`tasks.heightfield`, which import them on first
use, like :mod:`tasks.csr_kernel`. Each loop does, texel by texel and in the same order, the
float32 operations that numpy does over whole arrays in :func:`tasks.heightfield.visibility`
and :func:`tasks.shading.shade`, so both give the same bits (tests/test_shading.py compares
them). They make no temporaries and release the GIL (``nogil``), so the pipeline's threads
render in parallel; none uses threads of its own. Compiled code is kept in numba's on-disk
cache.
"""

from __future__ import annotations

import numba
import numpy as np

_f32 = np.float32


@numba.njit(nogil=True, cache=True, error_model="numpy")
def shade_lights(nx, ny, nz, albedo, a2, f0, masking, vis, terms, out):
    """Radiance of one view under each light, written to ``out`` ``(lights, ny, nx, 3)``.

    ``nx, ny, nz``, ``a2``, ``f0``, ``masking``: the view's :class:`tasks.shading.Surface`
    (``ny x nx`` float32); ``albedo`` ``(ny, nx, 3)``; ``vis`` ``(lights, ny, nx)``, the
    unshadowed fraction of each light. ``terms`` ``(lights, 8)`` float32 holds each light's
    ``lx, ly, lz, hx, hy, hz``, its Schlick factor ``(1 - v.h)^5`` and its ambient irradiance.
    """
    one, two, zero = _f32(1.0), _f32(2.0), _f32(0.0)
    cols = nx.shape[1]
    diffuse = np.empty(cols, np.float32)
    glossy = np.empty(cols, np.float32)
    for i in range(nx.shape[0]):
        # Row by row, every light of a row in turn, so the row's surface stays in cache; the
        # first loop over the row has no branch and vectorizes.
        x, y, z, a2_, f0_, mask, colour = nx[i], ny[i], nz[i], a2[i], f0[i], masking[i], albedo[i]
        for il in range(terms.shape[0]):
            lx, ly, lz, hx, hy, hz, schlick, ambient = (
                terms[il, 0], terms[il, 1], terms[il, 2], terms[il, 3], terms[il, 4],
                terms[il, 5], terms[il, 6], terms[il, 7])
            v = vis[il, i]
            for j in range(cols):
                cos_l = x[j] * lx + y[j] * ly + z[j] * lz
                cos_l = cos_l if cos_l > zero else zero
                cos_h = x[j] * hx + y[j] * hy + z[j] * hz
                cos_h = cos_h if cos_h > zero else zero
                a = a2_[j]
                denom = cos_h * cos_h * (a - one) + one
                fresnel = f0_[j] + (one - f0_[j]) * schlick
                g1 = two * cos_l / (cos_l + np.sqrt(a + (one - a) * cos_l * cos_l))
                specular = a / (denom * denom) * g1 * mask[j] * fresnel
                diffuse[j] = v[j] * cos_l + ambient
                glossy[j] = v[j] * specular
            row = out[il, i]
            for j in range(cols):
                for c in range(3):
                    row[j, c] = colour[j, c] * diffuse[j] + glossy[j]
    return out


@numba.njit(nogil=True, cache=True, error_model="numpy")
def shadow_tops(h, r0, c0, rows, cols, dy, dx, fy, fx, rise, out):
    """The highest point of each texel's shadow ray above the ray, ``out`` ``(rows, cols)``.

    Step ``t`` of the ray samples ``h`` at ``(r0 + i + dy[t] + fy[t], c0 + j + dx[t] +
    fx[t])`` (integer and fractional parts; a fraction of 0 skips its blend) and lowers it by
    ``rise[t]``: the maximum over the steps of :func:`tasks.heightfield.shifted` minus the ray.
    Step by step over whole rows, so that the inner loop has no branch and vectorizes.
    """
    out[:] = -np.inf
    for t in range(dy.shape[0]):
        a, b, ray = fy[t], fx[t], rise[t]
        for i in range(rows):
            r = r0 + i + dy[t]
            c = c0 + dx[t]
            here, below = h[r, c : c + cols], h[r + 1, c : c + cols]
            right, corner = h[r, c + 1 : c + 1 + cols], h[r + 1, c + 1 : c + 1 + cols]
            top = out[i]
            if a != 0 and b != 0:
                for j in range(cols):
                    left = here[j] + a * (below[j] - here[j])
                    side = right[j] + a * (corner[j] - right[j])
                    top[j] = max(top[j], left + b * (side - left) - ray)
            elif a != 0:
                for j in range(cols):
                    top[j] = max(top[j], here[j] + a * (below[j] - here[j]) - ray)
            elif b != 0:
                for j in range(cols):
                    top[j] = max(top[j], here[j] + b * (right[j] - here[j]) - ray)
            else:
                for j in range(cols):
                    top[j] = max(top[j], here[j] - ray)
    return out


@numba.njit(nogil=True, cache=True, error_model="numpy")
def bilinear_layers(a, r0, c0, oy, ox, out):
    """Every layer of ``a`` ``(layers, h, w)`` sampled at ``(r0 + i + oy, c0 + j + ox)``.

    :func:`tasks.heightfield.bilinear` for a stack of layers that share the offsets: the
    positions and weights are found once, then each layer is gathered in turn. ``out``
    ``(layers, ny, nx)``.
    """
    ny, nx = oy.shape
    rows = np.empty((ny, nx), np.intp)
    cols = np.empty((ny, nx), np.intp)
    fy = np.empty((ny, nx), np.float32)
    fx = np.empty((ny, nx), np.float32)
    for i in range(ny):
        for j in range(nx):
            y, x = np.floor(oy[i, j]), np.floor(ox[i, j])
            fy[i, j], fx[i, j] = oy[i, j] - y, ox[i, j] - x
            rows[i, j], cols[i, j] = r0 + i + int(y), c0 + j + int(x)
    for k in range(a.shape[0]):
        layer, dest = a[k], out[k]
        for i in range(ny):
            for j in range(nx):
                r, c, wy, wx = rows[i, j], cols[i, j], fy[i, j], fx[i, j]
                top = layer[r, c] + wx * (layer[r, c + 1] - layer[r, c])
                bottom = layer[r + 1, c] + wx * (layer[r + 1, c + 1] - layer[r + 1, c])
                dest[i, j] = top + wy * (bottom - top)
    return out
