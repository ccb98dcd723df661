"""A canvas being quilted: every pixel is a blend of sample pixels (a prescription in the making).

Quilting transfers patches of a sample image; blending a patch into its neighbourhood makes each
output pixel a weighted sum of sample pixels. The canvas keeps, for every pixel, up to
:data:`TERMS` (sample index, weight) pairs whose weights sum to 1, plus the blended values of the
reference image (what patch matching compares) and whether the pixel holds anything yet. The
terms are the rows of the prescription ``P`` (paper 003, section 2.1: transfer prescriptions),
so applying ``P`` to any layer does what the planner did to the reference (up to float32
rounding: the canvas blends values patch by patch, ``P`` sums each row's terms at once).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TERMS = 6  # sample pixels one output pixel may blend; the smallest weight makes room for more
_NEGLIGIBLE = 1e-4  # weights below this are dropped (and the rest renormalised)


@dataclass
class Canvas:
    """A rectangle of output pixels; see the module docstring."""

    index: np.ndarray  # (h, w, TERMS) int32 flat sample pixel, -1 where unused
    weight: np.ndarray  # (h, w, TERMS) float32, rows sum to 1 where filled
    value: np.ndarray  # (h, w, c) float32 blended reference values
    filled: np.ndarray  # (h, w) bool

    @staticmethod
    def empty(height: int, width: int, channels: int) -> Canvas:
        """A canvas with nothing on it."""
        return Canvas(np.full((height, width, TERMS), -1, np.int32),
                      np.zeros((height, width, TERMS), np.float32),
                      np.zeros((height, width, channels), np.float32),
                      np.zeros((height, width), bool))

    @property
    def shape(self) -> tuple[int, int]:
        """Height and width."""
        return self.filled.shape

    def window(self, y0: int, x0: int, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
        """Row and column indices of a window, clipped to the canvas (no wrap-around)."""
        rows = np.arange(max(y0, 0), min(y0 + h, self.shape[0]))
        cols = np.arange(max(x0, 0), min(x0 + w, self.shape[1]))
        return rows, cols

    def copy_from(self, other: Canvas, rows: slice, cols: slice, other_rows: slice,
                  other_cols: slice, where: np.ndarray | None = None) -> None:
        """Copy a region of another canvas onto this one (where ``where`` is true)."""
        sel = (rows, cols)
        src = (other_rows, other_cols)
        mask = other.filled[src] if where is None else where & other.filled[src]
        for name in ("index", "weight", "value"):
            target = getattr(self, name)[sel]
            target[mask] = getattr(other, name)[src][mask]
        self.filled[sel] |= mask

    def place(self, patch_index: np.ndarray, patch_value: np.ndarray, alpha: np.ndarray,
              y0: int, x0: int) -> None:
        """Blend a patch into the canvas at ``(y0, x0)``: ``new = alpha patch + (1-alpha) old``.

        ``patch_index`` are the flat sample indices of the patch pixels, ``patch_value`` their
        reference values, ``alpha`` the patch weights (1 wherever the canvas is empty). Parts
        outside the canvas are ignored.
        """
        from tasks.quilt_kernels import blend  # numba: not loaded by `btf --help`

        py0, px0 = max(-y0, 0), max(-x0, 0)
        if not blend(self.index, self.weight, self.value, self.filled,
                     np.asarray(patch_index, np.int32), np.asarray(patch_value, np.float32),
                     np.asarray(alpha, np.float32), y0 + py0, x0 + px0, py0, px0,
                     np.float32(_NEGLIGIBLE)):
            raise ValueError("a patch must cover empty canvas pixels with weight 1")
