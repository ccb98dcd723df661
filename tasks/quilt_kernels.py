"""Compiled loops (numba) of quilting's planning: the cut, the blend, the check's distances.

Threads plan the tiles of a set at once (:func:`tasks.corner_tiles.plan_tiles`); these are the
steps that would hold the GIL (or make the most memory traffic) per patch in numpy, each one
loop that releases it (``nogil``) and keeps a fixed order, so the same inputs give the same
bits on every thread and run. Compiled code is kept in numba's on-disk cache, as
:mod:`tasks.sketch_kernel`'s. BENCHMARKS.md, "Quilting", has the figures.

- :func:`cheapest_loop`, the boundary cut's search (:func:`tasks.quilting.boundary_cut`). The
  error image is a grid of node costs (infinite where the cut may not run); the cut is the
  cheapest closed loop, 4-connected, each step costing the mean of its two nodes, that
  crosses the slit above the kept square once. A loop crossing it at row ``r`` is the
  cheapest path from ``(r, col)`` to ``(r, col + 1)`` that does not step across the slit,
  plus that step: Dijkstra's search from each such row in turn, with a binary heap on
  arrays, each search stopped once nothing it could still reach beats the best loop so far.
  It finds the loops scipy's Dijkstra finds on a sparse graph built per patch, up to the
  choice among loops of equal cost, without building the graph in Python.
- :func:`blend`, a patch blended into a canvas (:meth:`tasks.canvas.Canvas.place`), pixel by
  pixel in the arithmetic of twenty numpy calls (float32 products, a float64 sum of a
  pixel's weights; the tests' reference): the same bits.
- :func:`smallest`, the candidate search's ``k`` best positions
  (:meth:`tasks.quilting.CandidateSearch.choose`) in one pass over the error image, where
  ``argpartition`` and ``argsort`` would hold the GIL for 1-2 ms a patch (29% of the
  default ``btf quilt``'s samples on a fabric sample); ties go to the lower index.
- :func:`search_kernels` and :func:`clipped_errors`, the candidate search's kernels and its
  error image; :func:`window_state`, what a patch's window holds; :func:`cut_costs`,
  :func:`filled_holes` and :func:`feathered`, the cut's costs, its inside and the blend
  weights: each one pass where numpy made several calls holding the GIL (a fill of 16 tiles
  on two threads 1.49 -> 0.92 s), the same regions and weights as scipy's.
- :func:`nearest_ssd`, the border check's re-ranking (:meth:`tasks.seams.PatchExemplar.
  distances`): each query patch's squared distance to the nearest of its candidates, read
  from the sample in place instead of gathering every candidate's patch (19 MB a check);
  :func:`grouped_patches`, its queries over the channels a grey sample repeats.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(nogil=True, cache=True)
def _push(heap_d, heap_v, size, d, v):  # pragma: no cover - compiled
    i = size
    heap_d[i], heap_v[i] = d, v
    while i > 0:
        parent = (i - 1) // 2
        # ties by node number: a fixed order whatever was pushed first
        if heap_d[parent] < heap_d[i] or (heap_d[parent] == heap_d[i]
                                          and heap_v[parent] <= heap_v[i]):
            break
        heap_d[parent], heap_d[i] = heap_d[i], heap_d[parent]
        heap_v[parent], heap_v[i] = heap_v[i], heap_v[parent]
        i = parent
    return size + 1


@numba.njit(nogil=True, cache=True)
def _pop(heap_d, heap_v, size):  # pragma: no cover - compiled
    d, v = heap_d[0], heap_v[0]
    size -= 1
    heap_d[0], heap_v[0] = heap_d[size], heap_v[size]
    i = 0
    while True:
        left, right, low = 2 * i + 1, 2 * i + 2, i
        for c in (left, right):
            if c < size and (heap_d[c] < heap_d[low] or (heap_d[c] == heap_d[low]
                                                         and heap_v[c] < heap_v[low])):
                low = c
        if low == i:
            break
        heap_d[low], heap_d[i] = heap_d[i], heap_d[low]
        heap_v[low], heap_v[i] = heap_v[i], heap_v[low]
        i = low
    return d, v, size


@numba.njit(nogil=True, cache=True)
def cheapest_loop(cost, col, top):  # pragma: no cover - compiled
    """The cheapest loop's nodes, ``(n, n)`` bool, and whether there is one.

    ``cost``: ``(n, n)`` node costs (``inf``: not on a loop); the slit runs between columns
    ``col`` and ``col + 1`` over rows ``0 .. top - 1``. Among loops of equal cost the one
    crossing the slit highest is kept.
    """
    n = cost.shape[0]
    size = n * n
    dist = np.empty(size)
    pred = np.empty(size, np.int64)
    done = np.empty(size, np.bool_)
    heap_d = np.empty(4 * size + 1)
    heap_v = np.empty(4 * size + 1, np.int64)
    best_total = np.inf
    best_pred = np.full(size, -1, np.int64)
    best_target = -1
    for r in range(top):
        if not (np.isfinite(cost[r, col]) and np.isfinite(cost[r, col + 1])):
            continue
        closing = 0.5 * (cost[r, col] + cost[r, col + 1])
        source, target = r * n + col, r * n + col + 1
        dist[:] = np.inf
        pred[:] = -1
        done[:] = False
        dist[source] = 0.0
        heap = _push(heap_d, heap_v, 0, 0.0, source)
        while heap > 0:
            d, v, heap = _pop(heap_d, heap_v, heap)
            if done[v]:
                continue
            if d + closing >= best_total:
                break  # nothing left beats the best loop so far
            done[v] = True
            if v == target:
                best_total = d + closing
                best_pred[:] = pred
                best_target = target
                break
            y, x = v // n, v % n
            for k in range(4):
                yy, xx = y + (k == 1) - (k == 0), x + (k == 3) - (k == 2)
                if yy < 0 or yy >= n or xx < 0 or xx >= n:
                    continue
                if y < top and yy == y and min(x, xx) == col:
                    continue  # no step across the slit
                if not np.isfinite(cost[yy, xx]):
                    continue
                u = yy * n + xx
                nd = d + 0.5 * (cost[y, x] + cost[yy, xx])
                if nd < dist[u]:
                    dist[u] = nd
                    pred[u] = v
                    heap = _push(heap_d, heap_v, heap, nd, u)
    loop = np.zeros((n, n), np.bool_)
    node = best_target
    while node >= 0:
        loop[node // n, node % n] = True
        node = best_pred[node]
    return loop, best_target >= 0


@numba.njit(nogil=True, cache=True)
def blend(index, weight, value, filled, patch_index, patch_value, alpha, y0, x0, py0, px0,
          negligible):  # pragma: no cover - compiled
    """Blend ``alpha`` of the patch into the canvas window at ``(y0, x0)`` (clipped).

    ``index``, ``weight`` ``(h, w, terms)``, ``value`` ``(h, w, c)`` and ``filled`` are the
    canvas's, changed in place over the window ``[y0, y0 + ny) x [x0, x0 + nx)``, where
    ``(ny, nx)`` is the part of ``alpha`` from ``(py0, px0)`` on that lies on the canvas.
    Returns False, changing nothing, when a pixel still empty would get a weight below 1.
    """
    ny = min(alpha.shape[0] - py0, filled.shape[0] - y0)
    nx = min(alpha.shape[1] - px0, filled.shape[1] - x0)
    terms, channels = index.shape[2], value.shape[2]
    one = np.float32(1.0)
    for i in range(ny):
        for j in range(nx):
            if not filled[y0 + i, x0 + j] and alpha[py0 + i, px0 + j] < one:
                return False
    wt = np.empty(terms, np.float32)
    idx = np.empty(terms, np.int32)
    for i in range(ny):
        for j in range(nx):
            y, x = y0 + i, x0 + j
            a = alpha[py0 + i, px0 + j]
            rest = one - a
            for t in range(terms):
                wt[t] = weight[y, x, t] * rest
                idx[t] = index[y, x, t]
                if wt[t] < negligible:
                    wt[t] = 0.0
                if wt[t] == 0.0:
                    idx[t] = -1
            if a > 0:  # a free slot, else the lightest (the first of equals)
                slot, low = 0, np.inf
                for t in range(terms):
                    key = wt[t] if idx[t] >= 0 else -1.0
                    if key < low:
                        slot, low = t, key
                idx[slot] = patch_index[py0 + i, px0 + j]
                wt[slot] = a
            total = 0.0
            for t in range(terms):
                total += np.float64(wt[t])
            for t in range(terms):
                weight[y, x, t] = np.float32(wt[t] / total) if total > 0 else np.float32(0.0)
                index[y, x, t] = idx[t]
            if a > 0:
                for c in range(channels):
                    value[y, x, c] = a * patch_value[py0 + i, px0 + j, c] + rest * value[y, x, c]
                filled[y, x] = True
    return True


@numba.njit(nogil=True, cache=True)
def nearest_ssd(sample, queries, sy, sx):  # pragma: no cover - compiled
    """Each query's squared distance to the nearest of its candidate sample patches.

    ``sample`` ``(h, w, c)`` float32; ``queries`` ``(q, p, p, c)`` float32 patches; ``sy, sx``
    ``(q, k)`` the candidates' top-left corners. Each patch row's sum is float32 (``p * c``
    terms), the rows' sum float64; a candidate stops once past the best so far (it cannot
    be the nearest).
    """
    count, k = sy.shape
    patch, run = queries.shape[1], queries.shape[2] * queries.shape[3]
    rows = sample.reshape(sample.shape[0], sample.shape[1] * sample.shape[2])
    channels = sample.shape[2]
    out = np.empty(count)
    for n in range(count):
        best = np.inf
        query = queries[n].reshape(patch, run)
        for m in range(k):
            y0, start = sy[n, m], sx[n, m] * channels
            total = 0.0
            for i in range(patch):
                line = rows[y0 + i, start : start + run]
                part = np.float32(0.0)
                for t in range(run):
                    d = line[t] - query[i, t]
                    part += d * d
                total += part
                if total >= best:
                    break
            if total < best:
                best = total
        out[n] = best
    return out


@numba.njit(nogil=True, cache=True)
def grouped_patches(queries, group, scale):  # pragma: no cover - compiled
    """Patches over channel groups, and what the groups leave out of their squared distances.

    ``queries`` ``(q, p, p, c)`` float32; ``group`` ``(c,)`` each channel's group and
    ``scale`` ``(g,)`` the square root of each group's count (:class:`tasks.seams.
    PatchExemplar`). Returns ``(q, p, p, g)`` float32 patches, each group's channels summed
    (in channel order) over its scale, and per query ``sum (Q_c - mean_g)^2`` over every
    channel (float64): a patch whose channels are alike within each group has 0, up to the
    rounding of the group's mean (about 1e-14 for a grey patch). Against a sample whose
    channels are alike within each group, scaled the same, :func:`nearest_ssd` plus that is
    the squared distance over every channel, up to float32 rounding.
    """
    count, p, _, channels = queries.shape
    groups = scale.shape[0]
    out = np.zeros((count, p, p, groups), np.float32)
    rest = np.zeros(count)
    total = np.empty(groups, np.float32)
    counts = np.zeros(groups, np.float32)
    for c in range(channels):
        counts[group[c]] += 1
    for n in range(count):
        for i in range(p):
            for j in range(p):
                total[:] = 0.0
                for c in range(channels):
                    total[group[c]] += queries[n, i, j, c]
                for g in range(groups):
                    out[n, i, j, g] = total[g] / scale[g]
                for c in range(channels):
                    mean = total[group[c]] / counts[group[c]]
                    d = queries[n, i, j, c] - mean
                    rest[n] += d * d
    return out, rest


@numba.njit(nogil=True, cache=True)
def smallest(err, allowed, use_allowed, k):  # pragma: no cover - compiled
    """Flat indices of the ``k`` smallest of ``err`` (2-D), ordered by value, then index.

    With ``use_allowed``, only positions where ``allowed`` (``err``'s shape) is true; there
    must be at least ``k`` of them. One pass, keeping the best ``k`` in an insertion-sorted
    list: a later equal value never displaces an earlier one. NaN is never taken (fewer than
    ``k`` indices come back if only NaN is left).
    """
    flat = err.reshape(err.size)
    mask = allowed.reshape(allowed.size)
    value = np.full(k, np.inf, np.float64)
    index = np.full(k, -1, np.int64)
    count = 0
    for i in range(flat.size):
        if use_allowed and not mask[i]:
            continue
        v = flat[i]
        if v != v or (count == k and not v < value[k - 1]):
            continue
        j = count if count < k else k - 1
        while j > 0 and v < value[j - 1]:
            value[j], index[j] = value[j - 1], index[j - 1]
            j -= 1
        value[j], index[j] = v, i
        if count < k:
            count += 1
    return index[:count]


@numba.njit(nogil=True, cache=True)
def search_kernels(target, mask, group, groups):  # pragma: no cover - compiled
    """The candidate search's kernels of a target and the target's masked squared norm.

    ``target`` ``(b, b, c)`` and ``mask`` ``(b, b)`` (any real type); ``group`` ``(c,)`` the
    channel group of each channel, ``0 .. groups - 1`` (channels the sample holds bit for
    bit alike share one: :class:`tasks.quilting.CandidateSearch`). Returns the
    ``(1 + groups, b, b)`` float32 kernels ``[M, M T_g0, ...]`` flipped in both axes (a
    correlation as a convolution), ``T_g`` the sum of group ``g``'s target channels in channel
    order, and ``sum M |T|^2`` over every channel: float32 products, summed in float64. One
    pass instead of six numpy calls holding the GIL
    (:meth:`tasks.quilting.CandidateSearch.errors`).
    """
    b, _, channels = target.shape
    out = np.zeros((1 + groups, b, b), np.float32)
    norm = 0.0
    for i in range(b):
        for j in range(b):
            m = np.float32(mask[i, j])
            out[0, b - 1 - i, b - 1 - j] = m
            for c in range(channels):
                t = np.float32(target[i, j, c])
                out[1 + group[c], b - 1 - i, b - 1 - j] += m * t
                norm += m * (t * t)
    return out, norm


@numba.njit(nogil=True, cache=True)
def clipped_errors(full, offset, rows, cols, norm):  # pragma: no cover - compiled
    """``max(full[offset:offset + rows, offset:offset + cols] + norm, 0)``, float32."""
    out = np.empty((rows, cols), np.float32)
    add = np.float32(norm)
    for i in range(rows):
        for j in range(cols):
            v = full[offset + i, offset + j] + add
            out[i, j] = v if v > 0 else np.float32(0.0)
    return out


@numba.njit(nogil=True, cache=True)
def window_state(filled, value, y0, x0, b):  # pragma: no cover - compiled
    """What a ``b x b`` window at ``(y0, x0)`` of a canvas holds, and the cut's free ring.

    Returns ``inside`` (on the canvas), ``filled`` (on it and filled), ``target`` (the canvas
    values, 0 off it; float32) and ``outside_free`` ``(b + 2, b + 2)``: the positions just
    outside the window that the boundary cut may use at no cost, those next to (8-connected)
    an empty or off-canvas window pixel, or off the canvas themselves; false inside the
    window (:func:`tasks.quilting.boundary_cut`).
    """
    h, w = filled.shape
    channels = value.shape[2]
    inside = np.zeros((b, b), np.bool_)
    here = np.zeros((b, b), np.bool_)
    target = np.zeros((b, b, channels), np.float32)
    for i in range(b):
        y = y0 + i
        if y < 0 or y >= h:
            continue
        for j in range(b):
            x = x0 + j
            if x < 0 or x >= w:
                continue
            inside[i, j] = True
            here[i, j] = filled[y, x]
            for c in range(channels):
                target[i, j, c] = value[y, x, c]
    free = np.zeros((b + 2, b + 2), np.bool_)
    for p in range(b + 2):
        for q in range(b + 2):
            if 0 < p < b + 1 and 0 < q < b + 1:
                continue  # the window itself
            y, x = y0 - 1 + p, x0 - 1 + q
            if y < 0 or y >= h or x < 0 or x >= w:
                free[p, q] = True
                continue
            for i in range(max(p - 2, 0), min(p + 1, b)):
                for j in range(max(q - 2, 0), min(q + 1, b)):
                    if not here[i, j]:
                        free[p, q] = True
    return inside, here, target, free


@numba.njit(nogil=True, cache=True)
def cut_costs(error, keep, outside_free):  # pragma: no cover - compiled
    """The boundary cut's node costs and the row where its slit ends.

    For :func:`tasks.quilting.boundary_cut`: ``(b + 2)^2`` float64 costs, infinite on
    ``keep``, on a window pixel next to filled canvas outside, and outside except where
    ``outside_free`` (cost 0); the window's pixels cost their error plus a little length
    penalty (float32 arithmetic). The row: the first of ``keep`` in the middle column
    (``n // 2`` if none).
    """
    b = error.shape[0]
    n = b + 2
    cost = np.full((n, n), np.inf)
    for i in range(b):
        for j in range(b):
            # a window pixel next to filled canvas outside may not carry the cut
            beside = ((i == 0 and not outside_free[0, j + 1])
                      or (i == b - 1 and not outside_free[n - 1, j + 1])
                      or (j == 0 and not outside_free[i + 1, 0])
                      or (j == b - 1 and not outside_free[i + 1, n - 1]))
            if not (keep[i, j] or beside):
                cost[i + 1, j + 1] = np.float32(error[i, j]) + np.float32(1e-6)
    for p in range(n):
        for q in range(n):
            if outside_free[p, q]:
                cost[p, q] = 0.0
    col = n // 2
    top = n // 2
    for p in range(1, n - 1):
        if keep[p - 1, col - 1]:
            top = p
            break
    return cost, top


@numba.njit(nogil=True, cache=True)
def filled_holes(mask):  # pragma: no cover - compiled
    """``mask`` with its holes filled.

    Everything not 4-connected to the border through ``~mask``
    (``scipy.ndimage.binary_fill_holes`` with its default structure).
    """
    h, w = mask.shape
    outside = np.zeros((h, w), np.bool_)
    stack = np.empty(h * w, np.int64)
    top = 0
    for i in range(h):
        for j in range(w):
            if (i == 0 or j == 0 or i == h - 1 or j == w - 1) and not mask[i, j]:
                outside[i, j] = True
                stack[top] = i * w + j
                top += 1
    while top > 0:
        top -= 1
        v = stack[top]
        y, x = v // w, v % w
        for k in range(4):
            yy, xx = y + (k == 1) - (k == 0), x + (k == 3) - (k == 2)
            if 0 <= yy < h and 0 <= xx < w and not mask[yy, xx] and not outside[yy, xx]:
                outside[yy, xx] = True
                stack[top] = yy * w + xx
                top += 1
    return ~outside


@numba.njit(nogil=True, cache=True)
def feathered(region, keep, kernel):  # pragma: no cover - compiled
    """The patch weight of :func:`tasks.quilting.blend_weights`, float32.

    ``region`` blurred by the separable ``kernel`` (zero beyond the window), 1 on ``keep``,
    0 outside the region where the blur left less than 1e-3.
    """
    b = region.shape[0]
    r = kernel.size // 2
    rows = np.zeros((b, b))
    for i in range(b):
        for j in range(b):
            s = 0.0
            for t in range(-r, r + 1):
                if 0 <= j + t < b and region[i, j + t]:
                    s += kernel[t + r]
            rows[i, j] = s
    out = np.empty((b, b), np.float32)
    for i in range(b):
        for j in range(b):
            s = 0.0
            for t in range(-r, r + 1):
                if 0 <= i + t < b:
                    s += kernel[t + r] * rows[i + t, j]
            if keep[i, j]:
                s = 1.0
            elif not region[i, j] and s < 1e-3:
                s = 0.0
            out[i, j] = s
    return out
