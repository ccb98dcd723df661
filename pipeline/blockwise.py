"""Blockwise graphs that pass a lone block as it is (dask's ``concatenate`` copies it).

Shared by the stores' lazy arrays (:mod:`pipeline.stores.compressed`) and the graph builders,
so it lies below both.
"""

from __future__ import annotations


def blockwise(func, out_ind: str, *args, **kwargs):
    """``dask.array.blockwise(..., concatenate=True)`` without its copy of a lone block.

    Where blockwise contracts an index (one that the output lacks), ``concatenate=True``
    joins each argument's blocks along it into a new array, and copies the block even when
    it is the only one there (a block's window of fields, a ``V`` tile: every task copied
    its own). Where every argument has one block along every contracted index, this runs
    ``func`` with ``concatenate=False`` and passes that block as it is (dask's list of one
    unwrapped); elsewhere it is plain ``concatenate=True``. ``func`` sees the same values
    either way, under its own name and token.
    """
    import dask.array as da

    pairs = list(zip(args[::2], args[1::2], strict=True))
    lone = all(len(getattr(a, "chunks", ((0,),) * len(ind))[ind.index(i)]) == 1
               for a, ind in pairs if ind is not None for i in ind if i not in out_ind)
    if lone:
        return da.blockwise(_WholeBlocks(func), out_ind, *args, concatenate=False, **kwargs)
    return da.blockwise(func, out_ind, *args, concatenate=True, **kwargs)


class _WholeBlocks:
    """``func`` taking each contracted argument's lone block out of dask's lists."""

    def __init__(self, func) -> None:
        self.func, self.__name__ = func, func.__name__

    def __call__(self, *args, **kwargs):
        return self.func(*map(_lone, args), **kwargs)

    def __dask_tokenize__(self):
        from dask.base import normalize_token

        return ("whole_blocks", normalize_token(self.func))


def _lone(arg):
    """The one block of nested lists of one (dask's ``concatenate=False``), or ``arg``."""
    while isinstance(arg, list):
        if len(arg) != 1:
            raise ValueError(f"{len(arg)} blocks along a contracted index, where one was "
                             "expected")
        arg = arg[0]
    return arg
