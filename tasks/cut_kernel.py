"""Compiled search (numba) of quilting's boundary cut: the cheapest loop through a slit.

:func:`tasks.quilting.boundary_cut` turns the error image into a grid of node costs (infinite
where the cut may not run) and asks for the cheapest closed loop, 4-connected, each step
costing the mean of its two nodes, that crosses the slit above the kept square once. A loop
crossing the slit at row ``r`` is the cheapest path from ``(r, col)`` to ``(r, col + 1)`` that
does not step across the slit, plus that step. :func:`cheapest_loop` runs Dijkstra's search
from each such row in turn with a binary heap on arrays, stops a search once nothing it could
still reach beats the best loop so far, and returns the best loop's nodes.

It replaces a sparse graph built per patch and scipy's Dijkstra (the same loops, up to the
choice among loops of equal cost), which held the GIL while the graph was built: threads
planning tiles at once waited on it. This loop releases the GIL (``nogil``) and keeps a fixed
order, so the same costs give the same loop on every thread and run. Compiled code is kept in
numba's on-disk cache, as :mod:`tasks.sketch_kernel`'s.
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
