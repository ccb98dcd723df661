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
from tasks.lattice import hermite_bands, lattice_cells


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
    return corner_code(t[:-1, :-1], t[:-1, 1:], t[1:, :-1], t[1:, 1:], corners=corners)


def corner_code(top_left, top_right, bottom_left, bottom_right, *, corners: int):
    """Index of the tile with these corner types among all ``corners^4``, lexicographically."""
    return ((top_left * corners + top_right) * corners + bottom_left) * corners + bottom_right


def region_tiles(y0: int, x0: int, ny: int, nx: int, *, tile_shape: tuple[int, int],
                 seed: int, corners: int) -> np.ndarray:
    """Tile indices (:func:`cell_tiles` order) of every cell the region overlaps."""
    ty, tx = tile_shape
    cy0, cx0 = y0 // ty, x0 // tx
    cy1, cx1 = (y0 + ny - 1) // ty, (x0 + nx - 1) // tx
    return cell_tiles(cy0, cx0, cy1 - cy0 + 1, cx1 - cx0 + 1, seed=seed, corners=corners)


def gather(tiles, y0: int, x0: int, ny: int, nx: int, *, seed: int, corners: int
           ) -> np.ndarray:
    """Pixels ``[y0, y0+ny) x [x0, x0+nx)`` of the surface covered by ``tiles``.

    ``tiles`` is ``(n, ty, tx, ...)``, or a mapping from tile index to ``(ty, tx, ...)`` arrays
    holding at least the tiles the region shows (:func:`region_tiles`). Coordinates may be
    negative: the surface is unbounded. Each lattice cell the region overlaps is one
    rectangular slice copy from its tile.
    """
    first = tiles[next(iter(tiles))] if isinstance(tiles, dict) else tiles[0]
    ty, tx = first.shape[:2]
    ids = region_tiles(y0, x0, ny, nx, tile_shape=(ty, tx), seed=seed, corners=corners)
    cy0, cx0 = y0 // ty, x0 // tx
    out = np.empty((ny, nx, *first.shape[2:]), first.dtype)
    for i in range(ids.shape[0]):
        cy = cy0 + i
        ya, yb = max(y0, cy * ty), min(y0 + ny, (cy + 1) * ty)
        for j in range(ids.shape[1]):
            cx = cx0 + j
            xa, xb = max(x0, cx * tx), min(x0 + nx, (cx + 1) * tx)
            out[ya - y0 : yb - y0, xa - x0 : xb - x0] = tiles[int(ids[i, j])][
                ya - cy * ty : yb - cy * ty, xa - cx * tx : xb - cx * tx]
    return out


def lattice_gather(tiles: np.ndarray, y0: int, x0: int, ny: int, nx: int, *, hnf,
                   basis=None, representative=None, seed: int = 0) -> np.ndarray:
    """Pixels of the surface covered by tiles stored in Hermite normal form (the roller).

    The tile lattice has the basis ``(h, s)``, ``(0, w)`` (``hnf = (h, w, s)``): texel
    ``(y, x)`` is stored texel ``(y - k h, x - k s - j w)`` of row band ``k = y // h``. With one
    tile that is all (slice copies). With several, the tile is chosen per lattice cell of the
    *cut* tile (:func:`lattice_cells`; ``basis`` the tile vectors ``(U, V)``): cell ``(i, j)``
    gets tile ``hash(i, j, seed) % n``.
    """
    n = tiles.shape[0]
    out = np.empty((ny, nx, *tiles.shape[3:]), tiles.dtype)
    if n == 1:
        for orows, ocols, rows, cols in hermite_bands(y0, x0, ny, nx, hnf):
            out[orows, ocols] = tiles[0, rows, cols]
        return out
    cells = lattice_cells(y0, x0, ny, nx, hnf=hnf, basis=basis, representative=representative)
    pick = (hash_coords(cells[..., 0], cells[..., 1], seed=seed) % np.uint64(n)).astype(np.int64)
    for orows, ocols, rows, cols in hermite_bands(y0, x0, ny, nx, hnf):
        out[orows, ocols] = tiles[pick[orows, ocols], np.arange(rows.start, rows.stop)[:, None],
                                  np.arange(cols.start, cols.stop)[None, :]]
    return out
