"""Which tile variation goes where on an unbounded surface (paper 003, section 2.4).

Every vertex of the tile lattice gets a corner type from a hash of its integer coordinates and
a seed; the tile of a cell is the one whose four corners carry the types of the cell's four
vertices. Neighbouring cells share two vertices, hence corner types, hence a seamless edge, for
any surface size, and nothing has to be stored: the same seed gives the same layout everywhere,
as the paper's shader-side hash does. Rendering is then a pure gather from the tiles.
"""

from __future__ import annotations

import numpy as np

from tasks.hashing import hash_coords


def vertex_types(rows: np.ndarray, cols: np.ndarray, *, seed: int, corners: int) -> np.ndarray:
    """Corner type of the lattice vertices ``(rows[:, None], cols[None, :])``."""
    h = hash_coords(np.asarray(rows)[:, None], np.asarray(cols)[None, :], seed=seed)
    return (h % np.uint64(corners)).astype(np.int64)


def cell_tiles(row0: int, col0: int, ny: int, nx: int, *, seed: int, corners: int
               ) -> np.ndarray:
    """Tile index of the cells ``row0 .. row0+ny-1`` x ``col0 .. col0+nx-1``.

    Tiles are numbered as planned (:func:`tasks.quilting.plan_tiles`): corner types
    ``(top-left, top-right, bottom-left, bottom-right)`` in lexicographic order.
    """
    t = vertex_types(np.arange(row0, row0 + ny + 1), np.arange(col0, col0 + nx + 1),
                     seed=seed, corners=corners)
    v = corners
    return ((t[:-1, :-1] * v + t[:-1, 1:]) * v + t[1:, :-1]) * v + t[1:, 1:]


def gather(tiles: np.ndarray, y0: int, x0: int, ny: int, nx: int, *, seed: int,
           corners: int) -> np.ndarray:
    """Pixels ``[y0, y0+ny) x [x0, x0+nx)`` of the surface covered by ``tiles``.

    ``tiles`` is ``(n, ty, tx, ...)``. Coordinates may be negative: the surface is unbounded.
    """
    _, ty, tx = tiles.shape[:3]
    ys = np.arange(y0, y0 + ny)
    xs = np.arange(x0, x0 + nx)
    cy, cx = np.floor_divide(ys, ty), np.floor_divide(xs, tx)
    ids = cell_tiles(int(cy[0]), int(cx[0]), int(cy[-1] - cy[0] + 1), int(cx[-1] - cx[0] + 1),
                     seed=seed, corners=corners)
    which = ids[(cy - cy[0])[:, None], (cx - cx[0])[None, :]]
    return tiles[which, (ys % ty)[:, None], (xs % tx)[None, :]]
