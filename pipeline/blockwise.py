"""Blockwise functions that take a lone block as it is (dask's ``concatenate`` copies it).

Shared by the stores' lazy arrays (:mod:`pipeline.stores.compressed`) and the graph builders,
so it lies below both.
"""

from __future__ import annotations


def whole_blocks(func):
    """``func`` for ``blockwise(..., concatenate=False)``: a lone block passed uncopied.

    Where blockwise contracts an index (one that the output lacks), ``concatenate=True``
    joins that argument's blocks along it into a new array, and copies the block even when
    it is the only one there (a block's window of fields, a ``V`` tile: every task copied
    its own). With ``concatenate=False`` dask passes nested lists of blocks instead; the
    function returned unwraps a list of one block, and joins longer lists as
    ``concatenate=True`` would, so ``func`` sees the same values as before. Each argument's
    contracted indices must be its last axes (as the callers' are: ``"yxf"``, ``"vlck"``).
    """
    return _WholeBlocks(func)


class _WholeBlocks:
    """:func:`whole_blocks`' function: named and tokenized as ``func`` (the graph's keys)."""

    def __init__(self, func) -> None:
        self.func, self.__name__ = func, func.__name__

    def __call__(self, *args, **kwargs):
        return self.func(*map(_whole, args), **kwargs)

    def __dask_tokenize__(self):
        return ("whole_blocks", self.func)


def _whole(arg):
    """A block as it is, or nested lists of blocks along trailing axes joined."""
    if not isinstance(arg, list):
        return arg
    depth, first = 0, arg
    while isinstance(first, list):
        depth, first = depth + 1, first[0]
    inner = arg
    while isinstance(inner, list) and len(inner) == 1:
        inner = inner[0]
    if not isinstance(inner, list):
        return inner
    from dask.array.core import concatenate_axes

    ndim = first.ndim
    return concatenate_axes(arg, list(range(ndim - depth, ndim)))
